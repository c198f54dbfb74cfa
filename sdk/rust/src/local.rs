//! What the service handles call through: a TCP (or TLS) HTTP/2 channel, or, for a client in the server's own
//! process, the server's router called directly.
//!
//! In-process, a call is handed to the server's tower service as an `http::Request` whose body is the encoded
//! message stream, and the response body is read back the same way: the same services, interceptors and codec
//! as over TCP, but no HTTP/2 framing, flow control or in-memory socket in between.

use std::convert::Infallible;
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use tokio::sync::watch;
use tonic::body::Body;
use tonic::codegen::http;
use tonic::transport::Channel;
use tower::ServiceExt as _;
use tower::util::BoxCloneSyncService;

type BoxError = Box<dyn std::error::Error + Send + Sync>;
type ResponseFuture = Pin<Box<dyn Future<Output = Result<http::Response<Body>, BoxError>> + Send>>;
/// The server's router as the in-process client holds it.
type LocalService = BoxCloneSyncService<http::Request<Body>, http::Response<Body>, BoxError>;

/// Where an in-process client's calls go.
#[derive(Clone)]
enum LocalState {
    /// The server has not started serving yet: calls wait.
    Waiting,
    Serving(LocalService),
    /// The server stopped: calls fail as `Unavailable`.
    Stopped,
}

/// A [`Client`](crate::Client)'s way to the server; cloning shares it.
#[derive(Clone)]
pub struct Transport(Kind);

#[derive(Clone)]
enum Kind {
    Channel(Channel),
    Local(watch::Receiver<LocalState>),
}

impl fmt::Debug for Transport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.0 {
            Kind::Channel(channel) => f.debug_tuple("Transport").field(channel).finish(),
            Kind::Local(_) => f.write_str("Transport(in-process)"),
        }
    }
}

impl Transport {
    pub(crate) fn channel(channel: Channel) -> Self {
        Self(Kind::Channel(channel))
    }
}

impl tower::Service<http::Request<Body>> for Transport {
    type Response = http::Response<Body>;
    type Error = BoxError;
    type Future = ResponseFuture;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        match &mut self.0 {
            Kind::Channel(channel) => {
                tower::Service::<http::Request<Body>>::poll_ready(channel, cx).map_err(Into::into)
            }
            // Readiness is the router's, checked when the call is made (`oneshot`).
            Kind::Local(_) => Poll::Ready(Ok(())),
        }
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        match &mut self.0 {
            Kind::Channel(channel) => {
                let call = channel.call(request);
                // Unwrapped, so tonic still reads a connect error as `Unavailable`.
                Box::pin(async move { call.await.map_err(Into::into) })
            }
            Kind::Local(state) => {
                let mut state = state.clone();
                Box::pin(async move {
                    let service = match state.wait_for(|s| !matches!(s, LocalState::Waiting)).await {
                        Ok(now) => match &*now {
                            LocalState::Serving(service) => Some(service.clone()),
                            LocalState::Waiting | LocalState::Stopped => None,
                        },
                        Err(_) => None,
                    };
                    match service {
                        Some(service) => service.oneshot(request).await,
                        None => Err(tonic::Status::unavailable("in-process server stopped").into()),
                    }
                })
            }
        }
    }
}

/// The server side of [`Client::in_process`](crate::Client::in_process): hand it the server's router with
/// [`LocalIncoming::serve`].
#[derive(Debug)]
pub struct LocalIncoming(watch::Sender<LocalState>);

impl fmt::Debug for LocalState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Waiting => "Waiting",
            Self::Serving(_) => "Serving",
            Self::Stopped => "Stopped",
        })
    }
}

impl LocalIncoming {
    /// Serves the client's calls with `router` (a server's `tonic::service::Routes`: its services with their
    /// interceptors, exactly as it serves TCP) until `stopped` resolves; from then on its calls fail as
    /// `Unavailable`. Streams already open end as the server ends them. Call it within a Tokio runtime.
    pub fn serve<S>(self, router: S, stopped: impl Future<Output = ()> + Send + 'static)
    where
        S: tower::Service<http::Request<Body>, Response = http::Response<Body>, Error = Infallible>
            + Clone
            + Send
            + Sync
            + 'static,
        S::Future: Send + 'static,
    {
        let service =
            BoxCloneSyncService::new(router.map_err(|never: Infallible| -> BoxError { match never {} }));
        self.0.send_replace(LocalState::Serving(service));
        tokio::spawn(async move {
            stopped.await;
            self.0.send_replace(LocalState::Stopped);
        });
    }
}

/// A connected pair: the client's transport and the server's end.
pub(crate) fn pair() -> (Transport, LocalIncoming) {
    let (tx, rx) = watch::channel(LocalState::Waiting);
    (Transport(Kind::Local(rx)), LocalIncoming(tx))
}

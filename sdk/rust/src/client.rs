//! The connection: how a [`Client`] reaches the server (a TCP channel, or in-process), its bearer token, and
//! the options of both.

use crate::local::{LocalIncoming, Transport};
use crate::{Error, Result, normalize_url};
use std::time::Duration;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

/// Adds `authorization: Bearer <token>` to every request when a token is set.
#[derive(Clone, Debug, Default)]
pub struct AuthInterceptor {
    header: Option<MetadataValue<tonic::metadata::Ascii>>,
}

impl Interceptor for AuthInterceptor {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> std::result::Result<tonic::Request<()>, tonic::Status> {
        if let Some(header) = &self.header {
            request.metadata_mut().insert("authorization", header.clone());
        }
        Ok(request)
    }
}

/// The channel type every service handle uses.
pub type AuthChannel = InterceptedService<Transport, AuthInterceptor>;

/// Options for [`Client::connect_with`].
#[derive(Clone, Debug)]
pub struct ConnectOptions {
    /// Bearer token sent with every call.
    pub token: Option<String>,
    /// Time allowed for the TCP and HTTP/2 handshake.
    pub connect_timeout_s: f64,
    /// PEM certificate authority to trust for `https://` URLs (e.g. a self-signed deployment); without it
    /// the system's root certificates are used.
    pub ca_pem: Option<Vec<u8>>,
    /// Server name to verify in the certificate when it differs from the URL's host.
    pub tls_domain: Option<String>,
}

impl Default for ConnectOptions {
    fn default() -> Self {
        Self {
            token: None,
            connect_timeout_s: 5.0,
            ca_pem: None,
            tls_domain: None,
        }
    }
}

/// The endpoint for `url` with the options' timeouts and TLS settings.
fn endpoint(url: &str, options: &ConnectOptions) -> Result<Endpoint> {
    let to_connect_error = |source| Error::Connect {
        url: url.to_owned(),
        source,
    };
    let dial = normalize_url(url);
    let endpoint = Endpoint::from_shared(dial.clone())
        .map_err(to_connect_error)?
        .connect_timeout(Duration::from_secs_f64(options.connect_timeout_s))
        .tcp_nodelay(true)
        // A long-lived stream notices a vanished server (a pulled cable sends no FIN) within seconds.
        .http2_keep_alive_interval(Duration::from_secs(10))
        .keep_alive_timeout(Duration::from_secs(5));
    if !dial.starts_with("https://") {
        return Ok(endpoint);
    }
    let mut tls = tonic::transport::ClientTlsConfig::new().with_native_roots();
    if let Some(pem) = &options.ca_pem {
        tls = tls.ca_certificate(tonic::transport::Certificate::from_pem(pem));
    }
    if let Some(domain) = &options.tls_domain {
        tls = tls.domain_name(domain.clone());
    }
    endpoint.tls_config(tls).map_err(to_connect_error)
}

/// A connection to a phone2act server.
#[derive(Clone, Debug)]
pub struct Client {
    transport: Transport,
    auth: AuthInterceptor,
}

impl Client {
    /// Connects to `url` (`127.0.0.1:50051`, `http://127.0.0.1:50051` or `https://host:port`) with an
    /// optional bearer token.
    pub async fn connect(url: &str, token: Option<&str>) -> Result<Self> {
        Self::connect_with(
            url,
            ConnectOptions {
                token: token.map(str::to_owned),
                ..ConnectOptions::default()
            },
        )
        .await
    }

    /// Connects with explicit options.
    pub async fn connect_with(url: &str, options: ConnectOptions) -> Result<Self> {
        let channel = endpoint(url, &options)?
            .connect()
            .await
            .map_err(|source| Error::Connect {
                url: url.to_owned(),
                source,
            })?;
        Self::on_channel(channel, options.token.as_deref())
    }

    /// Like [`Client::connect_with`], but the connection is made on the first call and made again after the
    /// server went away: for long-running clients (the phone gateway) that may start before the server.
    /// Call it within a Tokio runtime: the channel's connection task is spawned on it.
    pub fn connect_lazy(url: &str, options: &ConnectOptions) -> Result<Self> {
        let channel = endpoint(url, options)?.connect_lazy();
        Self::on_channel(channel, options.token.as_deref())
    }

    /// A client of a server in the same process, with no network stack in between: each call goes straight to
    /// the server's router (the same services and the same token check as over TCP, no HTTP/2 framing, no
    /// socket), messages still encoded as on the wire. Give the returned [`LocalIncoming`] to the server;
    /// calls made before it serves wait for it, calls made after it stopped fail as `Unavailable`. The
    /// server sees no peer address.
    pub fn in_process(token: Option<&str>) -> Result<(Self, LocalIncoming)> {
        let (transport, incoming) = crate::local::pair();
        Ok((Self::on_transport(transport, token)?, incoming))
    }

    /// The same connection sending `token` instead (several identities over one channel, e.g. in tests of
    /// the server's token check).
    pub fn with_token(&self, token: Option<&str>) -> Result<Self> {
        Self::on_transport(self.transport.clone(), token)
    }

    fn on_channel(channel: Channel, token: Option<&str>) -> Result<Self> {
        Self::on_transport(Transport::channel(channel), token)
    }

    fn on_transport(transport: Transport, token: Option<&str>) -> Result<Self> {
        let header = match token {
            Some(token) => {
                Some(MetadataValue::try_from(format!("Bearer {token}")).map_err(|_| Error::BadToken)?)
            }
            None => None,
        };
        Ok(Self {
            transport,
            auth: AuthInterceptor { header },
        })
    }

    /// What the service handles call through (shared: one connection for every handle).
    pub(crate) fn transport(&self) -> Transport {
        self.transport.clone()
    }

    /// The token every call carries.
    pub(crate) fn auth(&self) -> AuthInterceptor {
        self.auth.clone()
    }
}

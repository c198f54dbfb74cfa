//! The gateway's side of the gRPC connection to the phone2act server: one lazily connected HTTP/2 channel
//! shared by every phone, with the server's bearer token attached to each call.
//!
//! Lazy, because the embedded gateway starts alongside the server and the standalone one may start before
//! it; tonic reconnects the channel by itself when the server comes back.

use phone2act_proto::v1::policy_client::PolicyClient;
use phone2act_proto::v1::system_client::SystemClient;
use phone2act_proto::v1::teleop_client::TeleopClient;
use std::time::Duration;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

use crate::GatewayError;

/// Adds `authorization: Bearer <token>` when the server needs one.
#[derive(Clone, Debug, Default)]
pub struct Auth(Option<MetadataValue<Ascii>>);

impl Interceptor for Auth {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(header) = &self.0 {
            request.metadata_mut().insert("authorization", header.clone());
        }
        Ok(request)
    }
}

/// The shared channel to the server.
#[derive(Clone, Debug)]
pub struct Upstream {
    channel: Channel,
    auth: Auth,
}

impl Upstream {
    /// A lazily connecting channel to `server_url` (`http://host:port`).
    pub fn new(server_url: &str, grpc_token: Option<&str>) -> Result<Self, GatewayError> {
        let endpoint = Endpoint::from_shared(server_url.to_owned())
            .map_err(|e| GatewayError::ServerUrl(format!("{server_url}: {e}")))?
            .connect_timeout(Duration::from_secs(3))
            .tcp_nodelay(true)
            .http2_keep_alive_interval(Duration::from_secs(10))
            .keep_alive_timeout(Duration::from_secs(5));
        let auth = match grpc_token {
            Some(token) => Auth(Some(MetadataValue::try_from(format!("Bearer {token}")).map_err(
                |_| GatewayError::ServerUrl("gRPC token is not a valid header value".into()),
            )?)),
            None => Auth(None),
        };
        Ok(Self {
            channel: endpoint.connect_lazy(),
            auth,
        })
    }

    /// A Teleop client on the shared channel.
    pub fn teleop(&self) -> TeleopClient<InterceptedService<Channel, Auth>> {
        TeleopClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }

    /// A System client on the shared channel.
    pub fn system(&self) -> SystemClient<InterceptedService<Channel, Auth>> {
        SystemClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }

    /// A Policy client on the shared channel (read-only use: `GetObservation` for camera images).
    pub fn policy(&self) -> PolicyClient<InterceptedService<Channel, Auth>> {
        PolicyClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }
}

//! Typed async client for the phone2act.v1 API. `Client::connect` opens one HTTP/2 channel; the typed
//! service handles (`system()`, and the raw generated clients for the other services) share it. An optional
//! bearer token is attached to every call.

use phone2act_proto::v1;
use phone2act_proto::v1::episodes_client::EpisodesClient;
use phone2act_proto::v1::policy_client::PolicyClient;
use phone2act_proto::v1::system_client::SystemClient;
use phone2act_proto::v1::teleop_client::TeleopClient;
use std::time::Duration;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

pub use phone2act_proto::v1 as proto;

/// Errors from the client.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The URL could not be parsed or the connection could not be made.
    #[error("cannot connect to {url}: {source}")]
    Connect {
        url: String,
        #[source]
        source: tonic::transport::Error,
    },
    /// The token contains characters not allowed in an HTTP header.
    #[error("token is not a valid header value")]
    BadToken,
    /// The server answered with an error status.
    #[error("{}: {}", .0.code(), .0.message())]
    Status(#[from] tonic::Status),
}

/// Result alias for this crate.
pub type Result<T> = std::result::Result<T, Error>;

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
pub type AuthChannel = InterceptedService<Channel, AuthInterceptor>;

/// Options for [`Client::connect_with`].
#[derive(Clone, Debug)]
pub struct ConnectOptions {
    /// Bearer token sent with every call.
    pub token: Option<String>,
    /// Time allowed for the TCP and HTTP/2 handshake.
    pub connect_timeout_s: f64,
}

impl Default for ConnectOptions {
    fn default() -> Self {
        Self {
            token: None,
            connect_timeout_s: 5.0,
        }
    }
}

/// A connection to a phone2act server.
#[derive(Clone, Debug)]
pub struct Client {
    channel: Channel,
    auth: AuthInterceptor,
}

impl Client {
    /// Connects to `url` (e.g. `http://127.0.0.1:50051`) with an optional bearer token.
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
        let to_connect_error = |source| Error::Connect {
            url: url.to_owned(),
            source,
        };
        let endpoint = Endpoint::from_shared(url.to_owned())
            .map_err(to_connect_error)?
            .connect_timeout(Duration::from_secs_f64(options.connect_timeout_s))
            .tcp_nodelay(true);
        let channel = endpoint.connect().await.map_err(to_connect_error)?;
        let header = match options.token {
            Some(token) => {
                Some(MetadataValue::try_from(format!("Bearer {token}")).map_err(|_| Error::BadToken)?)
            }
            None => None,
        };
        Ok(Self {
            channel,
            auth: AuthInterceptor { header },
        })
    }

    /// The System service: arms, cameras, status.
    pub fn system(&self) -> SystemApi {
        SystemApi {
            inner: SystemClient::with_interceptor(self.channel.clone(), self.auth.clone()),
        }
    }

    /// The raw generated Teleop client.
    pub fn teleop_raw(&self) -> TeleopClient<AuthChannel> {
        TeleopClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }

    /// The raw generated Policy client.
    pub fn policy_raw(&self) -> PolicyClient<AuthChannel> {
        PolicyClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }

    /// The raw generated Episodes client.
    pub fn episodes_raw(&self) -> EpisodesClient<AuthChannel> {
        EpisodesClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }
}

/// Typed access to the System service.
#[derive(Clone, Debug)]
pub struct SystemApi {
    inner: SystemClient<AuthChannel>,
}

impl SystemApi {
    /// Configured arms with their current state.
    pub async fn list_arms(&mut self) -> Result<Vec<v1::ArmState>> {
        Ok(self
            .inner
            .list_arms(v1::ListArmsRequest {})
            .await?
            .into_inner()
            .arms)
    }

    /// Configured cameras with their current health.
    pub async fn list_cameras(&mut self) -> Result<Vec<v1::CameraStatus>> {
        Ok(self
            .inner
            .list_cameras(v1::ListCamerasRequest {})
            .await?
            .into_inner()
            .cameras)
    }

    /// A status snapshot.
    pub async fn status(&mut self) -> Result<v1::SystemStatus> {
        Ok(self.inner.get_status(v1::GetStatusRequest {}).await?.into_inner())
    }

    /// The dataset the recorder writes to.
    pub async fn dataset_info(&mut self) -> Result<v1::DatasetInfo> {
        Ok(self
            .inner
            .get_dataset_info(v1::GetDatasetInfoRequest {})
            .await?
            .into_inner())
    }

    /// A stream of status snapshots every `interval_s`.
    pub async fn watch_status(&mut self, interval_s: f64) -> Result<tonic::Streaming<v1::SystemStatus>> {
        Ok(self
            .inner
            .watch_status(v1::WatchStatusRequest { interval_s })
            .await?
            .into_inner())
    }
}

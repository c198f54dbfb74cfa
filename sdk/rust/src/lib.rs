//! Typed async client for the phone2act.v1 API. `Client::connect` opens one HTTP/2 channel; the typed
//! service handles (`system()`, and the raw generated clients for the other services) share it. An optional
//! bearer token is attached to every call.

use parking_lot::Mutex;
use phone2act_proto::PendingSample;
use phone2act_proto::v1;
use phone2act_proto::v1::episodes_client::EpisodesClient;
use phone2act_proto::v1::policy_client::PolicyClient;
use phone2act_proto::v1::scene_client::SceneClient;
use phone2act_proto::v1::system_client::SystemClient;
use phone2act_proto::v1::teleop_client::TeleopClient;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{Notify, mpsc};
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

pub use phone2act_proto::v1 as proto;

/// Errors from the client.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The URL could not be parsed or the connection could not be made. The reason is the error's
    /// `source()` (print the chain, e.g. anyhow's `{:#}`), not repeated in its own message.
    #[error("cannot connect to {url}")]
    Connect {
        url: String,
        #[source]
        source: tonic::transport::Error,
    },
    /// The token contains characters not allowed in an HTTP header.
    #[error("token is not a valid header value")]
    BadToken,
    /// The server ended a stream or sent something out of protocol.
    #[error("protocol: {0}")]
    Protocol(String),
    /// The session's stream is closed (the server ended it or the connection dropped).
    #[error("session closed")]
    Closed,
    /// The server answered with an error status. Displayed as `Code: message` once; the status is not
    /// also chained as a source, which would print the same message a second time in `{:#}` chains.
    #[error("{:?}: {}", .0.code(), .0.message())]
    Status(tonic::Status),
}

impl From<tonic::Status> for Error {
    fn from(status: tonic::Status) -> Self {
        Self::Status(status)
    }
}

/// The URL to dial for a target given as `host:port`, `http://host:port` or `https://host:port`: a target
/// without a scheme means plaintext HTTP/2, the server's default.
pub fn normalize_url(target: &str) -> String {
    let target = target.trim();
    if target.contains("://") {
        target.to_owned()
    } else {
        format!("http://{target}")
    }
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

/// Connections a [`Client::in_process`] may open before the server accepted the previous ones (one in
/// practice: the channel keeps a single HTTP/2 connection).
const LOCAL_ACCEPT_QUEUE: usize = 4;
/// Bytes in flight per direction of an in-process connection before the writer waits (HTTP/2 flow control
/// keeps far less than this outstanding for teleop traffic).
const LOCAL_PIPE_BYTES: usize = 256 * 1024;

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

/// The server side of [`Client::in_process`]: a stream of in-memory connections, each one a client's
/// HTTP/2 connection, for a tonic server's `serve_with_incoming`.
#[derive(Debug)]
pub struct LocalIncoming(mpsc::Receiver<tokio::io::DuplexStream>);

impl tokio_stream::Stream for LocalIncoming {
    type Item = std::io::Result<tokio::io::DuplexStream>;

    fn poll_next(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Self::Item>> {
        self.0.poll_recv(cx).map(|conn| conn.map(Ok))
    }
}

/// A connection to a phone2act server.
#[derive(Clone, Debug)]
pub struct Client {
    channel: Channel,
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

    /// A client of a server in the same process, over an in-memory pipe instead of a socket (no TCP, no
    /// loopback hop): give the returned [`LocalIncoming`] to the server. The token is still sent and still
    /// checked; the server sees no peer address.
    pub fn in_process(token: Option<&str>) -> Result<(Self, LocalIncoming)> {
        let (tx, rx) = mpsc::channel::<tokio::io::DuplexStream>(LOCAL_ACCEPT_QUEUE);
        let connector = tower::service_fn(move |_: tonic::codegen::http::Uri| {
            let tx = tx.clone();
            async move {
                let (ours, theirs) = tokio::io::duplex(LOCAL_PIPE_BYTES);
                tx.send(theirs).await.map_err(|_| {
                    std::io::Error::new(std::io::ErrorKind::ConnectionRefused, "in-process server stopped")
                })?;
                Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(ours))
            }
        });
        // The authority is never resolved: the connector above is the only way out.
        let channel =
            Endpoint::from_static("http://in-process.phone2act").connect_with_connector_lazy(connector);
        Ok((Self::on_channel(channel, token)?, LocalIncoming(rx)))
    }

    /// The same connection sending `token` instead (several identities over one channel, e.g. in tests of
    /// the server's token check).
    pub fn with_token(&self, token: Option<&str>) -> Result<Self> {
        Self::on_channel(self.channel.clone(), token)
    }

    fn on_channel(channel: Channel, token: Option<&str>) -> Result<Self> {
        let header = match token {
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

    /// The raw generated System client.
    pub fn system_raw(&self) -> SystemClient<AuthChannel> {
        SystemClient::with_interceptor(self.channel.clone(), self.auth.clone())
    }

    /// The System service: arms, cameras, status.
    pub fn system(&self) -> SystemApi {
        SystemApi {
            inner: self.system_raw(),
        }
    }

    /// The Episodes service: start, stop, discard, list, watch.
    pub fn episodes(&self) -> EpisodesApi {
        EpisodesApi {
            inner: self.episodes_raw(),
        }
    }

    /// The Scene service: reset and read a simulated arm's ball-and-basket scene.
    pub fn scene(&self) -> SceneApi {
        SceneApi {
            inner: SceneClient::with_interceptor(self.channel.clone(), self.auth.clone()),
        }
    }

    /// Opens a teleop session bound to `arm`. Samples are sent through a depth-1 queue: if the network is slower
    /// than the phone, [`TeleopSession::send`] reports the sample as superseded instead of queueing it.
    pub async fn teleop(&self, arm: &str, options: TeleopOptions) -> Result<TeleopSession> {
        TeleopSession::open(self.teleop_raw(), arm, options).await
    }

    /// Opens a policy session with `hello`; returns once the server answered with `SessionReady`.
    pub async fn policy(&self, hello: v1::PolicyHello) -> Result<PolicySession> {
        PolicySession::open(self.policy_raw(), hello).await
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

/// Typed access to the Scene service.
#[derive(Clone, Debug)]
pub struct SceneApi {
    inner: SceneClient<AuthChannel>,
}

impl SceneApi {
    /// Re-draws `arm`'s scene from `seed` (`None`: the arm's next seed); `home_arm` also puts the simulated
    /// arm at its initial joints, which the server refuses while a source drives it.
    pub async fn reset(&mut self, arm: &str, seed: Option<u64>, home_arm: bool) -> Result<v1::SceneState> {
        Ok(self
            .inner
            .reset(v1::ResetSceneRequest {
                arm: arm.to_owned(),
                seed,
                home_arm,
            })
            .await?
            .into_inner())
    }

    /// `arm`'s scene now.
    pub async fn get(&mut self, arm: &str) -> Result<v1::SceneState> {
        Ok(self
            .inner
            .get(v1::GetSceneRequest { arm: arm.to_owned() })
            .await?
            .into_inner())
    }
}

/// Typed access to the Episodes service.
#[derive(Clone, Debug)]
pub struct EpisodesApi {
    inner: EpisodesClient<AuthChannel>,
}

impl EpisodesApi {
    /// Starts recording an episode with `task`.
    pub async fn start(&mut self, task: &str) -> Result<v1::RecordingStatus> {
        self.start_by(task, "").await
    }

    /// Starts recording an episode with `task` by `operator` (kept in the episode's provenance).
    pub async fn start_by(&mut self, task: &str, operator: &str) -> Result<v1::RecordingStatus> {
        let response = self
            .inner
            .start(v1::StartEpisodeRequest {
                task: task.to_owned(),
                operator: operator.to_owned(),
            })
            .await?;
        response
            .into_inner()
            .status
            .ok_or_else(|| Error::Protocol("Start answered without status".into()))
    }

    /// Stops and saves the episode in progress; returns once it is committed.
    pub async fn stop(&mut self) -> Result<v1::StopEpisodeResponse> {
        Ok(self.inner.stop(v1::StopEpisodeRequest {}).await?.into_inner())
    }

    /// Throws away the episode in progress; returns the number of frames dropped.
    pub async fn discard(&mut self) -> Result<u64> {
        Ok(self
            .inner
            .discard(v1::DiscardEpisodeRequest {})
            .await?
            .into_inner()
            .frames_discarded)
    }

    /// Discards the episode in progress (if any) and starts again; an empty task keeps the previous one.
    pub async fn rerecord(&mut self, task: &str) -> Result<v1::RecordingStatus> {
        let response = self
            .inner
            .rerecord(v1::RerecordEpisodeRequest {
                task: task.to_owned(),
            })
            .await?;
        response
            .into_inner()
            .status
            .ok_or_else(|| Error::Protocol("Rerecord answered without status".into()))
    }

    /// Saved episodes.
    pub async fn list(&mut self) -> Result<v1::ListEpisodesResponse> {
        Ok(self.inner.list(v1::ListEpisodesRequest {}).await?.into_inner())
    }

    /// The recorder's state.
    pub async fn status(&mut self) -> Result<v1::RecordingStatus> {
        Ok(self.inner.status(v1::EpisodeStatusRequest {}).await?.into_inner())
    }

    /// Recorder state on every change and at least every `interval_s`.
    pub async fn watch(&mut self, interval_s: f64) -> Result<tonic::Streaming<v1::RecordingStatus>> {
        Ok(self
            .inner
            .watch(v1::WatchEpisodesRequest { interval_s })
            .await?
            .into_inner())
    }
}

/// Options for [`Client::teleop`].
#[derive(Clone, Debug, Default)]
pub struct TeleopOptions {
    /// Client name shown in status displays.
    pub client_name: String,
    /// Take the arm even if another phone owns it.
    pub take_over: bool,
}

/// An open teleop session.
#[derive(Debug)]
pub struct TeleopSession {
    outbox: Arc<Outbox>,
    feedback: tonic::Streaming<v1::TeleopFeedback>,
    seq: u64,
    superseded: u64,
}

#[derive(Debug, Default)]
struct OutboxState {
    pending: PendingSample,
    /// The session closed its end: the request stream ends once the pending sample is taken.
    closed: bool,
    /// The request stream is gone (the call ended): nothing sent now would reach the server.
    gone: bool,
}

/// The depth-1 latest-wins outbox between [`TeleopSession`] and its gRPC request stream: the stream takes the
/// pending sample when HTTP/2 flow control lets it send, and a sample offered meanwhile is folded into the
/// pending one ([`PendingSample::push`]) so the newest pose is what goes out and no button event is lost.
#[derive(Debug, Default)]
struct Outbox {
    state: Mutex<OutboxState>,
    /// A sample is pending, or the outbox closed.
    put: Notify,
    /// The stream took the pending sample, or went away.
    taken: Notify,
}

impl Outbox {
    /// Folds `sample` in; false if another one was still pending.
    fn offer(&self, sample: v1::PhoneSample) -> Result<bool> {
        let mut state = self.state.lock();
        if state.gone {
            return Err(Error::Closed);
        }
        let was_empty = state.pending.is_empty();
        state.pending.push(sample);
        drop(state);
        self.put.notify_one();
        Ok(was_empty)
    }

    /// Puts `sample` once nothing is pending.
    async fn put_when_empty(&self, sample: v1::PhoneSample) -> Result<()> {
        let mut sample = Some(sample);
        loop {
            {
                let mut state = self.state.lock();
                if state.gone {
                    return Err(Error::Closed);
                }
                if state.pending.is_empty() {
                    state.pending.push(sample.take().expect("put once"));
                    drop(state);
                    self.put.notify_one();
                    return Ok(());
                }
            }
            // `notify_one` keeps a permit when nobody waits yet, so a take between the check and here wakes us.
            self.taken.notified().await;
        }
    }

    async fn take(&self) -> Option<v1::PhoneSample> {
        loop {
            {
                let mut state = self.state.lock();
                if let Some(sample) = state.pending.take() {
                    drop(state);
                    self.taken.notify_one();
                    return Some(sample);
                }
                if state.closed {
                    return None;
                }
            }
            self.put.notified().await;
        }
    }

    fn close(&self) {
        self.state.lock().closed = true;
        self.put.notify_one();
    }
}

/// The request stream's hold on the outbox: when tonic drops the stream (the call ended), senders learn it.
struct OutboxTaker(Arc<Outbox>);

impl Drop for OutboxTaker {
    fn drop(&mut self) {
        self.0.state.lock().gone = true;
        self.0.taken.notify_one();
    }
}

impl TeleopSession {
    async fn open(mut client: TeleopClient<AuthChannel>, arm: &str, options: TeleopOptions) -> Result<Self> {
        let outbox = Arc::new(Outbox::default());
        let hello = v1::PhoneSample {
            seq: 0,
            arm: arm.to_owned(),
            client_name: options.client_name,
            take_over: options.take_over,
            ..v1::PhoneSample::default()
        };
        outbox.offer(hello)?;
        let requests = futures_util::stream::unfold(OutboxTaker(Arc::clone(&outbox)), |taker| async move {
            let sample = taker.0.take().await?;
            Some((sample, taker))
        });
        let feedback = client.stream(requests).await?.into_inner();
        Ok(Self {
            outbox,
            feedback,
            seq: 0,
            superseded: 0,
        })
    }

    /// Sends one sample (its `seq` is assigned here) without waiting. Returns false if the previous sample was
    /// still waiting for the network: the two are then folded into one (latest wins: the newest pose and seq
    /// go out, with the button events of both in order), so a burst never queues stale poses and never loses
    /// a button.
    pub fn send(&mut self, mut sample: v1::PhoneSample) -> Result<bool> {
        self.seq += 1;
        sample.seq = self.seq;
        let alone = self.outbox.offer(sample)?;
        if !alone {
            self.superseded += 1;
        }
        Ok(alone)
    }

    /// Sends one sample, waiting until the previous one went out instead of folding them (for scripted clients
    /// that need every sample to reach the server on its own).
    pub async fn send_wait(&mut self, mut sample: v1::PhoneSample) -> Result<u64> {
        self.seq += 1;
        sample.seq = self.seq;
        self.outbox.put_when_empty(sample).await?;
        Ok(self.seq)
    }

    /// Sends a pose with optional button events, waiting for room.
    pub async fn send_pose(
        &mut self,
        tracking_from_phone: v1::Pose,
        buttons: Vec<v1::ButtonEvent>,
        capture_time_ns: i64,
    ) -> Result<u64> {
        self.send_wait(v1::PhoneSample {
            tracking_from_phone: Some(tracking_from_phone),
            tracking: v1::TrackingState::Tracking as i32,
            buttons,
            capture_time_ns,
            ..v1::PhoneSample::default()
        })
        .await
    }

    /// Sends button events without a pose.
    pub async fn send_buttons(&mut self, buttons: Vec<v1::ButtonEvent>) -> Result<u64> {
        self.send_wait(v1::PhoneSample {
            buttons,
            ..v1::PhoneSample::default()
        })
        .await
    }

    /// The next feedback message; `Ok(None)` when the server ended the stream.
    pub async fn feedback(&mut self) -> Result<Option<v1::TeleopFeedback>> {
        Ok(self.feedback.message().await?)
    }

    /// Waits for the feedback that answers sample `seq` (or a later one).
    pub async fn feedback_for(&mut self, seq: u64) -> Result<v1::TeleopFeedback> {
        loop {
            match self.feedback.message().await? {
                Some(fb) if fb.echoed_seq >= seq => return Ok(fb),
                Some(_) => {}
                None => return Err(Error::Closed),
            }
        }
    }

    /// Samples folded locally into a newer one because the previous one was still in flight.
    pub fn superseded(&self) -> u64 {
        self.superseded
    }
}

impl Drop for TeleopSession {
    /// Ends the request stream (after any pending sample went out), as dropping a sender would.
    fn drop(&mut self) {
        self.outbox.close();
    }
}

/// Button-event constructors (shared with the gateway and the server's tests).
pub use phone2act_proto::buttons;
/// The short name of a recording phase, as status displays show it.
pub use phone2act_proto::convert_episode::phase_name;

/// An open policy session.
#[derive(Debug)]
pub struct PolicySession {
    tx: mpsc::Sender<v1::PolicyRequest>,
    events: tonic::Streaming<v1::PolicyEvent>,
    ready: v1::SessionReady,
}

impl PolicySession {
    async fn open(mut client: PolicyClient<AuthChannel>, hello: v1::PolicyHello) -> Result<Self> {
        // A few slots: chunks are small and rare (a few per second); the bound keeps a stuck server from
        // growing the queue.
        let (tx, rx) = mpsc::channel(8);
        tx.send(v1::PolicyRequest {
            request: Some(v1::policy_request::Request::Hello(hello)),
        })
        .await
        .map_err(|_| Error::Closed)?;
        let mut events = client.session(ReceiverStream::new(rx)).await?.into_inner();
        let ready = match events.message().await? {
            Some(v1::PolicyEvent {
                event: Some(v1::policy_event::Event::Ready(ready)),
            }) => ready,
            Some(other) => return Err(Error::Protocol(format!("expected SessionReady, got {other:?}"))),
            None => return Err(Error::Closed),
        };
        Ok(Self { tx, events, ready })
    }

    /// What the server said when the session opened: the session id and each arm's layout.
    pub fn ready(&self) -> &v1::SessionReady {
        &self.ready
    }

    /// The next event (observation, control change, chunk verdict); `Ok(None)` when the stream ended.
    pub async fn next_event(&mut self) -> Result<Option<v1::policy_event::Event>> {
        loop {
            match self.events.message().await? {
                Some(v1::PolicyEvent { event: Some(event) }) => return Ok(Some(event)),
                Some(v1::PolicyEvent { event: None }) => {}
                None => return Ok(None),
            }
        }
    }

    /// The next observation, skipping other events.
    pub async fn next_observation(&mut self) -> Result<v1::Observation> {
        loop {
            match self.next_event().await? {
                Some(v1::policy_event::Event::Observation(obs)) => return Ok(obs),
                Some(_) => {}
                None => return Err(Error::Closed),
            }
        }
    }

    /// Pushes an action chunk.
    pub async fn push_chunk(&self, chunk: v1::ActionChunk) -> Result<()> {
        self.request(v1::policy_request::Request::Chunk(chunk)).await
    }

    /// Asks for one observation now.
    pub async fn request_observation(&self) -> Result<()> {
        self.request(v1::policy_request::Request::Observe(v1::ObservationRequest {}))
            .await
    }

    /// Gives up control; the arms hold.
    pub async fn release(&self) -> Result<()> {
        self.request(v1::policy_request::Request::Release(v1::ReleaseControl {}))
            .await
    }

    async fn request(&self, request: v1::policy_request::Request) -> Result<()> {
        self.tx
            .send(v1::PolicyRequest {
                request: Some(request),
            })
            .await
            .map_err(|_| Error::Closed)
    }
}

impl PolicySession {
    /// Pushes a chunk as a unary call: a bad chunk comes back as an error status instead of an event.
    pub async fn push_chunk_checked(
        &self,
        client: &Client,
        chunk: v1::ActionChunk,
    ) -> Result<v1::ChunkAccepted> {
        let request = v1::PushChunkRequest {
            session_id: self.ready.session_id.clone(),
            chunk: Some(chunk),
        };
        Ok(client.policy_raw().push_chunk(request).await?.into_inner())
    }
}

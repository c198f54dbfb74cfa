//! The phone2act server as a library: [`run`] serves the phone2act.v1 API (plus gRPC health and reflection)
//! for a [`Config`] on a given listener until a shutdown future resolves. The `phone2act` binary is a thin
//! CLI around it; tests start it in-process on an ephemeral port.

pub mod app;
pub mod arm;
pub mod config;
pub mod control_stats;
pub mod episode_timing;
pub mod flight_log;
pub mod policy_session;
pub mod recording;
pub mod runtime;
pub mod services;
pub mod upload;

use crate::app::App;
pub use crate::config::Config;
use phone2act_proto::v1::bridge_server::BridgeServer;
use phone2act_proto::v1::cameras_server::CamerasServer;
use phone2act_proto::v1::episodes_server::EpisodesServer;
use phone2act_proto::v1::policy_server::PolicyServer;
use phone2act_proto::v1::scene_server::SceneServer;
use phone2act_proto::v1::system_server::SystemServer;
use phone2act_proto::v1::teleop_server::TeleopServer;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tonic::service::Routes;
use tonic::transport::Server;
use tonic::transport::server::TcpIncoming;

/// Rate of the arm controllers' periodic work (chunk steps, silence and staleness checks).
pub const ARM_TICK_HZ: f64 = 500.0;

/// Largest camera frame accepted over Cameras.Push (a 1920x1080 RGB8 frame is 6.2 MB).
pub const MAX_FRAME_BYTES: usize = 8 << 20;

/// How long in-flight streams get to finish after shutdown is requested.
pub const SHUTDOWN_GRACE: Duration = Duration::from_millis(700);

/// HTTP/2 flow-control window of one stream: what a client may send that the service has not read yet
/// (hyper's default, set here because [`HTTP2_CONNECTION_WINDOW_BYTES`] is sized against it).
pub const HTTP2_STREAM_WINDOW_BYTES: u32 = 1 << 20;

/// HTTP/2 flow-control window of one connection, all its streams together.
///
/// Why not hyper's 1 MiB: h2 (>= 0.4.16) closes the whole connection with GOAWAY `ENHANCE_YOUR_CALM`
/// ("too_many_data_frames") once the small DATA frames it holds unread cost more than a budget of half the
/// connection window, each frame under 256 bytes counting `256 - its length`. A teleop sample is one DATA
/// frame of about 44-90 bytes, so with 1 MiB windows the budget (512 KiB) ran out after ~2 500 unread
/// samples, a quarter of what the stream window lets a phone send: a phone streaming as fast as it can
/// lost its connection whenever the server fell ~20 ms behind (issue 17; the client saw "h2 protocol error:
/// error reading a body from connection", the server logged "too many small DATA frames"). With 16 MiB the
/// budget is 8 MiB, more than a full stream window of samples of 29 bytes or more can cost
/// (1 MiB / 29 * 227 < 7.9 MiB), so flow control holds such a client back before h2 would drop it.
pub const HTTP2_CONNECTION_WINDOW_BYTES: u32 = 16 << 20;

/// Errors that stop the server.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("cannot start: {0}")]
    Startup(String),
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    #[error("reflection service: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
}

/// Binds `addr` with a one-line error that says what to do when the port is taken.
pub async fn bind(addr: std::net::SocketAddr) -> Result<TcpListener, ServerError> {
    TcpListener::bind(addr).await.map_err(|e| {
        let hint = if e.kind() == std::io::ErrorKind::AddrInUse {
            " (another phone2act or program is using it; pick another with --listen)"
        } else {
            ""
        };
        ServerError::Startup(format!("cannot listen on {addr}: {e}{hint}"))
    })
}

/// Clients in the same process (e.g. the SDK's `Client::in_process`, the embedded phone gateway): called
/// once with the server's router (the same services and token check as over TCP, called directly, with no
/// HTTP/2 or socket in between) and a future that resolves when the server stops taking calls.
pub type LocalConnections = Box<dyn FnOnce(Routes, Pin<Box<dyn Future<Output = ()> + Send>>) + Send>;

/// Serves `config` on `listener` until `shutdown` resolves, then gives open streams [`SHUTDOWN_GRACE`] to end.
pub async fn run(
    config: Config,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    run_with_local(config, listener, None, shutdown).await
}

/// [`run`], also serving the in-process connections of `in_process` (the embedded phone gateway's).
pub async fn run_with_local(
    config: Config,
    listener: TcpListener,
    in_process: Option<LocalConnections>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let app = Arc::new(App::start(config).map_err(|e| ServerError::Startup(e.to_string()))?);
    serve_app_with_local(app, listener, in_process, shutdown).await
}

/// Serves an already started [`App`] (benchmarks keep a handle on it to read the control-path counters).
pub async fn serve_app(
    app: Arc<App>,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    serve_app_with_local(app, listener, None, shutdown).await
}

/// [`serve_app`], also serving the in-process connections of `in_process`.
pub async fn serve_app_with_local(
    app: Arc<App>,
    listener: TcpListener,
    in_process: Option<LocalConnections>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let local = listener
        .local_addr()
        .map_err(|e| ServerError::Startup(e.to_string()))?;
    tracing::info!(addr = %local, arms = app.arms().len(), cameras = app.cameras().len(), "phone2act serving");
    if let Some(warning) = services::auth::exposure_warning(local, app.config().server.token.is_some()) {
        tracing::warn!("{warning}");
    }

    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    for name in phone2act_proto::SERVICE_NAMES {
        health_reporter
            .set_service_status(name, tonic_health::ServingStatus::Serving)
            .await;
    }
    health_reporter
        .set_service_status("", tonic_health::ServingStatus::Serving)
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(phone2act_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(phone2act_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    let auth = services::auth::TokenCheck::new(app.config().server.token.clone());
    let system = SystemServer::with_interceptor(
        services::system::SystemService::new(Arc::clone(&app)),
        auth.clone(),
    );
    let teleop = TeleopServer::with_interceptor(
        services::teleop::TeleopService::new(Arc::clone(&app)),
        auth.clone(),
    );
    let policy = PolicyServer::with_interceptor(
        services::policy::PolicyService::new(Arc::clone(&app)),
        auth.clone(),
    );
    let episodes = EpisodesServer::with_interceptor(
        services::episodes::EpisodesService::new(Arc::clone(&app)),
        auth.clone(),
    );
    let bridge = BridgeServer::with_interceptor(
        services::bridge::BridgeService::new(Arc::clone(&app)),
        auth.clone(),
    );
    let scene =
        SceneServer::with_interceptor(services::scene::SceneService::new(Arc::clone(&app)), auth.clone());
    let cameras = tonic::service::interceptor::InterceptedService::new(
        CamerasServer::new(services::cameras::CamerasService::new(Arc::clone(&app)))
            .max_decoding_message_size(MAX_FRAME_BYTES),
        auth,
    );
    tokio::spawn(arm::run_ticks(
        app.arms().to_vec(),
        ARM_TICK_HZ,
        app.shutdown_signal(),
    ));

    if app.episode_timing().limits().any() {
        tokio::spawn(episode_timing::run_episode_timing(Arc::clone(&app)));
    }

    let app_for_shutdown = Arc::clone(&app);
    tokio::spawn(async move {
        shutdown.await;
        app_for_shutdown.begin_shutdown();
    });
    let stopping = |mut signal: tokio::sync::watch::Receiver<bool>| async move {
        let _ = signal.wait_for(|stopping| *stopping).await;
    };

    let routes = Routes::new(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(system)
        .add_service(teleop)
        .add_service(policy)
        .add_service(episodes)
        .add_service(bridge)
        .add_service(cameras)
        .add_service(scene)
        .prepare();
    // Both transports share one set of routes, so the services, their interceptors and the shutdown are the same.
    if let Some(serve_local) = in_process {
        serve_local(routes.clone(), Box::pin(stopping(app.shutdown_signal())));
    }
    let router = Server::builder()
        .tcp_nodelay(true)
        .initial_stream_window_size(HTTP2_STREAM_WINDOW_BYTES)
        .initial_connection_window_size(HTTP2_CONNECTION_WINDOW_BYTES)
        .add_routes(routes);
    // `Server::tcp_nodelay` only applies to listeners tonic binds itself; without NODELAY on accepted
    // sockets a reply written in two parts waits ~40 ms for the peer's delayed ACK.
    let tcp = router.serve_with_incoming_shutdown(
        TcpIncoming::from(listener).with_nodelay(Some(true)),
        stopping(app.shutdown_signal()),
    );
    tokio::pin!(tcp);
    let mut shutdown_seen = app.shutdown_signal();
    let result = tokio::select! {
        result = &mut tcp => result,
        () = async {
            let _ = shutdown_seen.wait_for(|stopping| *stopping).await;
            tokio::time::sleep(SHUTDOWN_GRACE).await;
        } => {
            tracing::warn!("streams still open after {SHUTDOWN_GRACE:?}; closing them");
            Ok(())
        }
    };
    app.stop();
    tracing::info!("phone2act stopped");
    result.map_err(ServerError::from)
}

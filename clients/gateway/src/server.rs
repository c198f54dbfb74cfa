//! The two listeners and their routes: plain `ws://` rosbridge (default :9090) and HTTPS (default :8443)
//! serving the phone page, its `wss://…/ws` socket and rosbridge over `wss://…/rosbridge`.

use crate::config::{GatewayConfig, HARD_MAX_MESSAGE_BYTES};
use crate::conn;
use crate::error::GatewayError;
use crate::native::PageHandler;
use crate::pairing::{Admission, Pairing};
use crate::rosbridge::{self, StatusLevel};
use crate::rosbridge_conn::RosbridgeHandler;
use crate::shared::Shared;
use crate::takeover::Holders;
use crate::tls;
use crate::upstream::Upstream;
use crate::web;
use axum::Router;
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{WebSocket, WebSocketUpgrade, close_code};
use axum::extract::{ConnectInfo, Query, State};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::serve::ListenerExt;
use phone2act_proto::v1::ListArmsRequest;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// Listeners bound by the caller (tests use port 0). An endpoint without a listener is not served.
#[derive(Debug, Default)]
pub struct Listeners {
    pub rosbridge: Option<tokio::net::TcpListener>,
    pub https: Option<tokio::net::TcpListener>,
}

/// Where a started gateway can be reached.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GatewayInfo {
    pub rosbridge_addr: Option<SocketAddr>,
    pub https_addr: Option<SocketAddr>,
    /// The URL to open on the phone (with the pairing token), when HTTPS is served.
    pub page_url: Option<String>,
    pub token: Option<String>,
    /// The certificate the HTTPS server presents.
    pub cert_path: Option<PathBuf>,
}

/// A bound, not yet running gateway.
#[derive(Debug)]
pub struct Gateway {
    shared: Arc<Shared>,
    shutdown_tx: watch::Sender<bool>,
    rosbridge: Option<tokio::net::TcpListener>,
    https: Option<(tokio::net::TcpListener, Arc<rustls::ServerConfig>)>,
    info: GatewayInfo,
}

impl Gateway {
    /// Binds the listeners the config enables; phones reach the server at `server_url` over the network.
    pub async fn bind(
        config: GatewayConfig,
        server_url: &str,
        grpc_token: Option<&str>,
    ) -> Result<Self, GatewayError> {
        Self::bind_upstream(config, Upstream::new(server_url, grpc_token)?).await
    }

    /// Binds the listeners the config enables; phones reach the server through `client` (for a server in
    /// the same process: [`phone2act_sdk::Client::in_process`]). The phones' own addresses still decide
    /// pairing and take-over: those rules live here, not in the server.
    pub async fn bind_client(
        config: GatewayConfig,
        client: phone2act_sdk::Client,
    ) -> Result<Self, GatewayError> {
        Self::bind_upstream(config, Upstream::from_client(client)).await
    }

    async fn bind_upstream(config: GatewayConfig, upstream: Upstream) -> Result<Self, GatewayError> {
        let bind = |addr: SocketAddr| async move {
            tokio::net::TcpListener::bind(addr)
                .await
                .map_err(|source| GatewayError::Bind { addr, source })
        };
        let rosbridge = if config.rosbridge {
            Some(bind(config.rosbridge_listen).await?)
        } else {
            None
        };
        let https = if config.https {
            Some(bind(config.https_listen).await?)
        } else {
            None
        };
        Self::with_upstream(config, upstream, Listeners { rosbridge, https })
    }

    /// Uses listeners bound by the caller; `config`'s listen addresses and enable flags are ignored.
    pub fn with_listeners(
        config: GatewayConfig,
        server_url: &str,
        grpc_token: Option<&str>,
        listeners: Listeners,
    ) -> Result<Self, GatewayError> {
        Self::with_upstream(config, Upstream::new(server_url, grpc_token)?, listeners)
    }

    /// [`Gateway::with_listeners`] reaching the server through `client` (see [`Gateway::bind_client`]).
    pub fn with_client(
        config: GatewayConfig,
        client: phone2act_sdk::Client,
        listeners: Listeners,
    ) -> Result<Self, GatewayError> {
        Self::with_upstream(config, Upstream::from_client(client), listeners)
    }

    fn with_upstream(
        config: GatewayConfig,
        upstream: Upstream,
        listeners: Listeners,
    ) -> Result<Self, GatewayError> {
        config.validate()?;
        let cert_dir = config.cert_dir.clone().unwrap_or_else(tls::default_cert_dir);
        let local =
            |l: &tokio::net::TcpListener| l.local_addr().map_err(|e| GatewayError::Config(e.to_string()));
        let rosbridge_addr = listeners.rosbridge.as_ref().map(local).transpose()?;
        let https_addr = listeners.https.as_ref().map(local).transpose()?;
        let mut token = None;
        let mut page_url = None;
        let mut cert_path = None;
        let https = match listeners.https {
            Some(listener) => {
                let addr = https_addr.expect("bound");
                let host = config.public_host.clone().unwrap_or_else(|| tls::lan_host(addr));
                let material = tls::load_or_generate(&config, &cert_dir, std::slice::from_ref(&host))?;
                cert_path = Some(material.cert_path.clone());
                token = tls::pairing_token(&config, &cert_dir)?;
                page_url = Some(tls::page_url(&host, addr.port(), token.as_deref()));
                Some((listener, tls::server_config(material)?))
            }
            None => None,
        };
        // Without HTTPS there is no page to pair through, but rosbridge still needs a token to refuse anyone
        // else: only `require_token = false` makes the gateway open.
        if token.is_none() && (config.rosbridge_require_token || rosbridge_addr.is_some()) {
            token = tls::pairing_token(&config, &cert_dir)?;
        }
        let (shutdown_tx, shutdown) = watch::channel(false);
        let info = GatewayInfo {
            rosbridge_addr,
            https_addr,
            page_url,
            token: token.clone(),
            cert_path,
        };
        let pairing = Pairing::new(
            config.local_addresses.clone(),
            config.allow.clone(),
            Duration::from_secs(config.pair_for_s),
        );
        let video = crate::webrtc::VideoHub::new(config.video);
        let shared = Arc::new(Shared {
            config,
            upstream,
            token,
            pairing,
            holders: Holders::default(),
            rosbridge_port: rosbridge_addr.map(|a| a.port()),
            video,
            images_on_control_runtime: false,
            connections: AtomicU64::new(1),
            shutdown,
        });
        Ok(Self {
            shared,
            shutdown_tx,
            rosbridge: listeners.rosbridge,
            https,
            info,
        })
    }

    /// Fetches and encodes rosbridge camera images on the runtime the gateway runs on, as the control path,
    /// instead of the video runtime: the placement before the video runtime took that work, kept only so that
    /// a benchmark can compare both in one run.
    #[cfg(feature = "mock")]
    pub fn fetch_images_on_control_runtime(&mut self) {
        if let Some(shared) = Arc::get_mut(&mut self.shared) {
            shared.images_on_control_runtime = true;
        }
    }

    /// Addresses, URL and token.
    pub fn info(&self) -> &GatewayInfo {
        &self.info
    }

    /// The URL and QR code block printed on start.
    pub fn banner(&self) -> String {
        let mut text = String::new();
        if let Some(url) = &self.info.page_url {
            text.push_str(
                "\nphone2act gateway: open this on the phone (Chrome on Android with ARCore):\n\n  ",
            );
            text.push_str(url);
            text.push('\n');
            if let Ok(qr) = tls::qr_text(url) {
                text.push('\n');
                text.push_str(&qr);
                text.push('\n');
            }
            text.push_str(
                "\nThe certificate is self-signed: on the warning page tap \"Advanced\" then \"Proceed\" (once per \
                 certificate).\nPhone and computer must be on the same Wi-Fi; guest networks often block it.\n",
            );
        }
        if let Some(addr) = self.info.rosbridge_addr {
            let host = self
                .shared
                .config
                .public_host
                .clone()
                .unwrap_or_else(|| tls::lan_host(addr));
            let _ = writeln!(
                text,
                "Phone2Act app / rosbridge clients: ws://{host}:{}",
                addr.port()
            );
        }
        text
    }

    /// Serves until `shutdown` resolves, then closes every socket (their teleop streams end with them).
    pub async fn run(self, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), GatewayError> {
        if self.shared.config.print_qr {
            println!("{}", self.banner());
        }
        let mut tasks = tokio::task::JoinSet::new();
        if let Some(listener) = self.rosbridge {
            let app = Router::new()
                .fallback(get(rosbridge_plain))
                .with_state(self.shared.clone());
            let mut stop = self.shared.shutdown.clone();
            // Feedback goes out one small frame per sample: with Nagle on, a frame often waits for the phone's
            // next packet to carry the ACK (gateway-bench page round trip at 60 Hz: p90 16.4 ms, 0.7 ms with it).
            let listener = listener.tap_io(|tcp| {
                if let Err(e) = tcp.set_nodelay(true) {
                    tracing::debug!(error = %e, "cannot set TCP_NODELAY");
                }
            });
            tasks.spawn(async move {
                axum::serve(listener, app.into_make_service_with_connect_info::<SocketAddr>())
                    .with_graceful_shutdown(async move {
                        let _ = stop.wait_for(|s| *s).await;
                    })
                    .await
                    .map_err(|e| GatewayError::Serve(e.to_string()))
            });
        }
        let handle = axum_server::Handle::<SocketAddr>::new();
        if let Some((listener, tls_config)) = self.https {
            let app = Router::new()
                .route("/ws", get(page_socket))
                .route("/rosbridge", get(rosbridge_tls))
                .route("/healthz", get(|| async { "ok" }))
                .merge(web::routes())
                .with_state(self.shared.clone());
            let std_listener = listener
                .into_std()
                .map_err(|e| GatewayError::Serve(e.to_string()))?;
            let acceptor = axum_server::tls_rustls::RustlsAcceptor::new(
                axum_server::tls_rustls::RustlsConfig::from_config(tls_config),
            )
            .acceptor(axum_server::accept::NoDelayAcceptor::new());
            let server = axum_server::from_tcp(std_listener)
                .map_err(|e| GatewayError::Serve(e.to_string()))?
                .acceptor(acceptor)
                .handle(handle.clone());
            tasks.spawn(async move {
                server
                    .serve(app.into_make_service_with_connect_info::<SocketAddr>())
                    .await
                    .map_err(|e| GatewayError::Serve(e.to_string()))
            });
        }
        tracing::info!(rosbridge = ?self.info.rosbridge_addr, https = ?self.info.https_addr, "gateway serving");
        if self.shared.token.is_none()
            && let Some(addr) = self.info.rosbridge_addr.filter(|a| !a.ip().is_loopback())
        {
            tracing::warn!(
                "rosbridge on {addr} has no pairing token (require_token = false): every address that can reach \
                 it can drive the arms"
            );
        }
        let result = tokio::select! {
            () = shutdown => Ok(()),
            Some(done) = tasks.join_next() => done.map_err(|e| GatewayError::Serve(e.to_string())).and_then(|r| r),
        };
        let _ = self.shutdown_tx.send(true);
        handle.graceful_shutdown(Some(Duration::from_secs(2)));
        let drain = async { while tasks.join_next().await.is_some() {} };
        if tokio::time::timeout(Duration::from_secs(3), drain).await.is_err() {
            tracing::warn!("gateway connections did not close in time");
        }
        result
    }
}

fn token_ok(shared: &Shared, query: &HashMap<String, String>) -> bool {
    match &shared.token {
        None => true,
        Some(expected) => query
            .get("token")
            .is_some_and(|got| tls::token_matches(expected, got)),
    }
}

fn upgrade(ws: WebSocketUpgrade) -> WebSocketUpgrade {
    // The hard cap protects memory; the configured (smaller) limit is enforced per message with an error reply.
    ws.max_message_size(HARD_MAX_MESSAGE_BYTES)
        .max_frame_size(HARD_MAX_MESSAGE_BYTES)
}

async fn refuse(socket: WebSocket, first: String, reason: &'static str) {
    let mut socket = socket;
    let _ = socket.send(axum::extract::ws::Message::Text(first.into())).await;
    let _ = socket
        .send(axum::extract::ws::Message::Close(Some(
            axum::extract::ws::CloseFrame {
                code: close_code::POLICY,
                reason: reason.into(),
            },
        )))
        .await;
}

const TOKEN_HELP: &str =
    "wrong or missing pairing token: open the URL (or scan the QR code) the gateway printed";
const PAIR_HELP: &str = "this address is not paired with the phone2act gateway: open the phone page URL the \
     gateway printed (scan its QR code) on this phone to pair it, or add the address to [gateway] allow";

/// Decides a rosbridge connection; a refusal is logged (with the address and how to pair) and answered.
fn admit_rosbridge(shared: &Shared, peer: SocketAddr, query: &HashMap<String, String>) -> Admission {
    let now = Instant::now();
    let has_token = shared.token.is_some();
    let token_ok = has_token && token_ok(shared, query);
    let admission = if shared.config.rosbridge_require_token {
        // The operator asked for the token on rosbridge: neither address nor pairing is enough.
        if token_ok {
            Admission::Token
        } else {
            Admission::Refused
        }
    } else {
        shared.pairing.admit(peer.ip(), token_ok, has_token, now)
    };
    if admission.admitted() {
        tracing::debug!(%peer, ?admission, "rosbridge connection admitted");
    } else if shared.pairing.should_log_refusal(peer.ip(), now) {
        let pair_for_h = shared.config.pair_for_s as f64 / 3600.0;
        tracing::warn!(
            %peer,
            "rosbridge connection from {} refused: not paired. To pair it, open the phone page URL printed at \
             start (scan the QR code) on that phone; the address may then use rosbridge for {pair_for_h:.1} h. \
             Or add it to [gateway] allow.",
            peer.ip()
        );
    }
    admission
}

async fn serve_rosbridge(socket: WebSocket, shared: Arc<Shared>, peer: SocketAddr, admission: Admission) {
    if !admission.admitted() {
        let help = if shared.config.rosbridge_require_token {
            TOKEN_HELP
        } else {
            PAIR_HELP
        };
        refuse(
            socket,
            rosbridge::status(StatusLevel::Error, help, None),
            "not paired",
        )
        .await;
        return;
    }
    let max = shared.config.max_message_bytes;
    let stop = shared.shutdown.clone();
    conn::run(socket, max, stop, |wiring| {
        RosbridgeHandler::new(shared, wiring, peer.ip())
    })
    .await;
}

async fn rosbridge_plain(
    State(shared): State<Arc<Shared>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Query(query): Query<HashMap<String, String>>,
    ws: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Response {
    let Ok(ws) = ws else {
        return (
            axum::http::StatusCode::UPGRADE_REQUIRED,
            "phone2act gateway: this port speaks rosbridge v2 over WebSocket. The phone page is served over HTTPS \
             (see the URL printed at start).\n",
        )
            .into_response();
    };
    let admission = admit_rosbridge(&shared, peer, &query);
    upgrade(ws).on_upgrade(move |socket| serve_rosbridge(socket, shared, peer, admission))
}

async fn rosbridge_tls(
    State(shared): State<Arc<Shared>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Query(query): Query<HashMap<String, String>>,
    ws: WebSocketUpgrade,
) -> Response {
    let admission = admit_rosbridge(&shared, peer, &query);
    upgrade(ws).on_upgrade(move |socket| serve_rosbridge(socket, shared, peer, admission))
}

async fn page_socket(
    State(shared): State<Arc<Shared>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Query(query): Query<HashMap<String, String>>,
    ws: WebSocketUpgrade,
) -> Response {
    let authorised = token_ok(&shared, &query);
    upgrade(ws).on_upgrade(move |socket| async move {
        if !authorised {
            if shared.pairing.should_log_refusal(peer.ip(), Instant::now()) {
                tracing::warn!(%peer, "phone page socket refused: wrong or missing pairing token");
            }
            refuse(
                socket,
                serde_json::json!({"type": "error", "fatal": true, "message": TOKEN_HELP}).to_string(),
                "wrong or missing pairing token",
            )
            .await;
            return;
        }
        // The page proved the token: the same phone's rosbridge app may now connect from this address.
        if shared.token.is_some()
            && let Some(until) = shared.pairing.pair(peer.ip(), Instant::now())
        {
            tracing::info!(
                %peer,
                "paired {} for rosbridge for {:.1} h",
                peer.ip(),
                until.saturating_duration_since(Instant::now()).as_secs_f64() / 3600.0
            );
        }
        let mut system = shared.upstream.system();
        let (arms, cameras) = tokio::join!(
            tokio::time::timeout(Duration::from_secs(2), system.list_arms(ListArmsRequest {})),
            tokio::time::timeout(Duration::from_secs(2), shared.upstream.camera_names()),
        );
        let arms = match arms {
            Ok(Ok(response)) => response.into_inner().arms.into_iter().map(|a| a.arm).collect(),
            _ => vec![shared.config.default_arm.clone()],
        };
        // Without the list the page offers no preview; the arms still work.
        let cameras = cameras.ok().and_then(Result::ok).unwrap_or_default();
        let max = shared.config.max_message_bytes;
        let stop = shared.shutdown.clone();
        conn::run(socket, max, stop, |wiring| {
            let handler = PageHandler::new(shared, wiring, peer.ip());
            handler.welcome(&arms, &cameras);
            handler
        })
        .await;
    })
}

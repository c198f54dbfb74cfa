//! Helpers for the gateway's integration tests: a gateway on port-0 listeners in front of the mock server,
//! and WebSocket clients for plain `ws://` and `wss://` (trusting the gateway's own certificate).

#![allow(dead_code)]

use futures_util::{SinkExt, StreamExt};
use phone2act_gateway::mock_server::MockServer;
use phone2act_gateway::{Gateway, GatewayConfig, GatewayInfo, Listeners};
use serde_json::Value;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpStream;
use tokio::sync::oneshot;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;

pub(crate) struct Harness {
    pub mock: MockServer,
    pub info: GatewayInfo,
    pub _dir: tempfile::TempDir,
    stop: Option<oneshot::Sender<()>>,
    pub task: tokio::task::JoinHandle<Result<(), phone2act_gateway::GatewayError>>,
}

impl Drop for Harness {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

pub(crate) async fn start(arms: &[&str], tweak: impl FnOnce(&mut GatewayConfig)) -> Harness {
    let mock = MockServer::start(arms, Instant::now(), true).await.unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut config = GatewayConfig {
        cert_dir: Some(dir.path().to_owned()),
        print_qr: false,
        public_host: Some("127.0.0.1".into()),
        ..GatewayConfig::default()
    };
    tweak(&mut config);
    // The enable flags pick which listeners exist (with_listeners serves whatever it is given).
    let listeners = Listeners {
        rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
        https: if config.https {
            Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap())
        } else {
            None
        },
    };
    let gateway = Gateway::with_listeners(config, &mock.url(), None, listeners).unwrap();
    let info = gateway.info().clone();
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(gateway.run(async {
        let _ = stopped.await;
    }));
    Harness {
        mock,
        info,
        _dir: dir,
        stop: Some(stop),
        task,
    }
}

pub(crate) type Plain = WebSocketStream<TcpStream>;
pub(crate) type Tls = WebSocketStream<tokio_rustls::client::TlsStream<TcpStream>>;

pub(crate) async fn rosbridge(h: &Harness) -> Plain {
    plain(&format!("ws://{}/", h.info.rosbridge_addr.unwrap())).await
}

pub(crate) async fn plain(url: &str) -> Plain {
    let hostport = url
        .trim_start_matches("ws://")
        .split('/')
        .next()
        .unwrap()
        .to_owned();
    let tcp = TcpStream::connect(hostport).await.unwrap();
    tokio_tungstenite::client_async(url, tcp).await.unwrap().0
}

/// A `wss://` client that trusts exactly the gateway's certificate and checks the host name `localhost`.
pub(crate) async fn wss(h: &Harness, path_and_query: &str) -> Tls {
    let pem = std::fs::read(h.info.cert_path.as_ref().unwrap()).unwrap();
    let mut roots = rustls::RootCertStore::empty();
    for cert in rustls::pki_types::CertificateDer::pem_slice_iter(&pem) {
        roots.add(cert.unwrap()).unwrap();
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
    let addr = h.info.https_addr.unwrap();
    let tcp = TcpStream::connect(addr).await.unwrap();
    let tls = connector
        .connect("localhost".try_into().unwrap(), tcp)
        .await
        .unwrap();
    let url = format!("wss://localhost:{}{path_and_query}", addr.port());
    tokio_tungstenite::client_async(url, tls).await.unwrap().0
}

use rustls::pki_types::pem::PemObject;

pub(crate) async fn send<S>(ws: &mut WebSocketStream<S>, text: &str)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    ws.send(Message::Text(text.into())).await.unwrap();
}

/// The next JSON text message, or `None` on timeout or close.
pub(crate) async fn next_json<S>(ws: &mut WebSocketStream<S>, timeout: Duration) -> Option<Value>
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        match tokio::time::timeout_at(deadline, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => return Some(serde_json::from_str(t.as_str()).unwrap()),
            Ok(Some(Ok(Message::Ping(_) | Message::Pong(_)))) => {}
            _ => return None,
        }
    }
}

/// Reads until a message matches `pred` (skipping others), or `None`.
pub(crate) async fn wait_json<S>(
    ws: &mut WebSocketStream<S>,
    timeout: Duration,
    pred: impl Fn(&Value) -> bool,
) -> Option<Value>
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    let deadline = Instant::now() + timeout;
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        let v = next_json(ws, left).await?;
        if pred(&v) {
            return Some(v);
        }
    }
    None
}

pub(crate) fn pose_msg(topic: &str, x: f64) -> String {
    format!(
        r#"{{"op":"publish","topic":"{topic}","type":"geometry_msgs/PoseStamped","msg":{{"header":{{"stamp":{{"sec":1763726400,"nanosec":5000000}},"frame_id":"phone_ar_frame"}},"pose":{{"position":{{"x":{x},"y":0.0,"z":0.0}},"orientation":{{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}}}}}"#
    )
}

//! Gateway helpers shared by the end-to-end test binaries that include this module: a gateway in front of a
//! gRPC server (through the SDK client it is given: in-process, as `phone2act serve` embeds it, or over TCP)
//! on ephemeral ports, and its wss:// page socket over a TCP connection the caller opened (from
//! whichever local address plays the phone).
#![allow(dead_code)] // each test binary uses the part it needs

use phone2act_gateway::{Gateway, GatewayConfig, GatewayInfo, Listeners};
use rustls::pki_types::pem::PemObject;
use std::sync::Arc;
use tokio::net::TcpStream;
use tokio_tungstenite::WebSocketStream;

/// A gateway serving until dropped.
pub(crate) struct RunningGateway {
    pub info: GatewayInfo,
    _dir: tempfile::TempDir,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Drop for RunningGateway {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

/// Starts a gateway reaching its server through `client` (holding the server's token as `phone2act serve`
/// hands it over) on ephemeral ports, with its certificate in a temporary directory; `tweak` adjusts the
/// configuration first.
pub(crate) async fn start_gateway(
    client: phone2act_sdk::Client,
    tweak: impl FnOnce(&mut GatewayConfig),
) -> RunningGateway {
    let dir = tempfile::tempdir().unwrap();
    let mut config = GatewayConfig {
        cert_dir: Some(dir.path().to_owned()),
        print_qr: false,
        public_host: Some("127.0.0.1".into()),
        ..GatewayConfig::default()
    };
    tweak(&mut config);
    let listeners = Listeners {
        rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
        https: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
    };
    let gateway = Gateway::with_client(config, client, listeners).unwrap();
    let info = gateway.info().clone();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(gateway.run(async {
        let _ = stopped.await;
    }));
    RunningGateway {
        info,
        _dir: dir,
        stop: Some(stop),
    }
}

/// The page socket `path` over `tcp` (already connected to the gateway's HTTPS port), trusting only the
/// gateway's own certificate.
pub(crate) async fn wss_over(
    info: &GatewayInfo,
    tcp: TcpStream,
    path: &str,
) -> WebSocketStream<tokio_rustls::client::TlsStream<TcpStream>> {
    let pem = std::fs::read(info.cert_path.as_ref().unwrap()).unwrap();
    let mut roots = rustls::RootCertStore::empty();
    for cert in rustls::pki_types::CertificateDer::pem_slice_iter(&pem) {
        roots.add(cert.unwrap()).unwrap();
    }
    let config =
        rustls::ClientConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()
            .unwrap()
            .with_root_certificates(roots)
            .with_no_client_auth();
    let port = info.https_addr.unwrap().port();
    let tls = tokio_rustls::TlsConnector::from(Arc::new(config))
        .connect("localhost".try_into().unwrap(), tcp)
        .await
        .unwrap();
    tokio_tungstenite::client_async(format!("wss://localhost:{port}{path}"), tls)
        .await
        .unwrap()
        .0
}

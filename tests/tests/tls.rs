//! The Rust SDK over TLS: the System service behind a TLS listener with a self-signed certificate, reached
//! with that certificate as the trusted CA; without it the handshake is refused.

use phone2act_proto::v1::system_server::SystemServer;
use phone2act_server::app::App;
use phone2act_server::services::system::SystemService;
use phone2act_tests::default_config;
use std::sync::Arc;
use tonic::transport::{Identity, Server, ServerTlsConfig};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_sdk_talks_tls_with_a_given_ca_and_refuses_an_untrusted_certificate() {
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap();
    let cert_pem = cert.cert.pem();
    let key_pem = cert.signing_key.serialize_pem();

    let dir = tempfile::tempdir().unwrap();
    let app = Arc::new(App::start(default_config(dir.path())).unwrap());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(
        Server::builder()
            .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(&cert_pem, &key_pem)))
            .unwrap()
            .add_service(SystemServer::new(SystemService::new(Arc::clone(&app))))
            .serve_with_incoming_shutdown(tonic::transport::server::TcpIncoming::from(listener), async {
                let _ = stop_rx.await;
            }),
    );

    let url = format!("https://localhost:{port}");
    let trusted = phone2act_sdk::ConnectOptions {
        ca_pem: Some(cert_pem.clone().into_bytes()),
        ..phone2act_sdk::ConnectOptions::default()
    };
    let client = phone2act_sdk::Client::connect_with(&url, trusted).await.unwrap();
    let arms = client.system().list_arms().await.unwrap();
    assert_eq!(arms[0].arm, "main");

    // The system roots do not know this certificate: no connection.
    let untrusted = phone2act_sdk::ConnectOptions {
        connect_timeout_s: 3.0,
        ..phone2act_sdk::ConnectOptions::default()
    };
    let refused = phone2act_sdk::Client::connect_with(&url, untrusted).await;
    assert!(
        refused.is_err(),
        "an unknown self-signed certificate must not be trusted"
    );

    let _ = stop_tx.send(());
    server.await.unwrap().unwrap();
    app.stop();
}

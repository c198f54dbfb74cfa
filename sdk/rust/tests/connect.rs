//! Connection errors the SDK must report clearly.

#[tokio::test]
async fn a_server_that_is_down_names_the_url() {
    let err = phone2act_sdk::Client::connect("http://127.0.0.1:9", None)
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("cannot connect to http://127.0.0.1:9"), "{err}");
}

#[tokio::test]
async fn tls_to_a_plaintext_port_fails_the_handshake_instead_of_hanging() {
    // A plain TCP listener that never speaks TLS.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("https://{}", listener.local_addr().unwrap());
    let accept = tokio::spawn(async move {
        let (socket, _) = listener.accept().await.unwrap();
        drop(socket);
    });
    let options = phone2act_sdk::ConnectOptions {
        connect_timeout_s: 2.0,
        ..phone2act_sdk::ConnectOptions::default()
    };
    let err = phone2act_sdk::Client::connect_with(&url, options)
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains(&url), "{err}");
    accept.await.unwrap();
}

#[tokio::test]
async fn a_malformed_url_is_refused() {
    let err = phone2act_sdk::Client::connect("not a url", None)
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("cannot connect to not a url"), "{err}");
}

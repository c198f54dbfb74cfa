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

#[test]
fn every_url_form_a_user_types_is_dialable() {
    use phone2act_sdk::normalize_url;
    assert_eq!(normalize_url("127.0.0.1:50051"), "http://127.0.0.1:50051");
    assert_eq!(normalize_url(" localhost:1 "), "http://localhost:1");
    assert_eq!(normalize_url("http://h:1"), "http://h:1");
    assert_eq!(normalize_url("https://h:1"), "https://h:1");
}

#[tokio::test]
async fn a_target_without_scheme_is_dialed_not_refused_as_a_url() {
    // Port 9 (discard) is closed here: the error must be the connection, not "scheme is missing".
    let err = phone2act_sdk::Client::connect("127.0.0.1:9", None)
        .await
        .unwrap_err();
    let text = format!("{err:#}");
    assert!(text.contains("cannot connect to 127.0.0.1:9"), "{text}");
    assert!(!text.contains("scheme"), "{text}");
}

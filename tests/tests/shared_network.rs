//! On a shared network (issue 12): with a server token set, a rosbridge or phone-page client that is neither
//! paired nor token-bearing can neither drive an arm, nor take one over, nor read state; opening the phone
//! page with the token pairs the phone's address for rosbridge, and the pairing expires; a guessed policy
//! session id pushes nothing. A client bound to 127.0.0.2 plays the phone on the Wi-Fi: the gateway is told
//! that only 127.0.0.1 is this machine, so no other machine's address is ever used.

use futures_util::{SinkExt, StreamExt};
use parking_lot::Mutex;
use phone2act_gateway::GatewayConfig;
use phone2act_sdk::Client;
use phone2act_sdk::proto as v1;
use phone2act_tests::{TestServer, default_config, pos};
use serde_json::Value;
use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tokio::net::{TcpSocket, TcpStream};
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;

const T: Duration = Duration::from_secs(10);
const SERVER_TOKEN: &str = "server-secret-for-the-test";
/// Plays the phone on the Wi-Fi.
const PHONE: &str = "127.0.0.2";

/// Everything the gateway logs in this test binary (one global subscriber; the gateway logs from worker
/// threads, so a thread-local default would miss it).
fn log() -> Arc<Mutex<Vec<u8>>> {
    static LOG: OnceLock<Arc<Mutex<Vec<u8>>>> = OnceLock::new();
    LOG.get_or_init(|| {
        let buf = Arc::new(Mutex::new(Vec::new()));
        let writer = buf.clone();
        tracing_subscriber::fmt()
            .with_ansi(false)
            .with_env_filter("phone2act_gateway=info")
            .with_writer(move || LogWriter(writer.clone()))
            .init();
        buf
    })
    .clone()
}

struct LogWriter(Arc<Mutex<Vec<u8>>>);

impl std::io::Write for LogWriter {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.0.lock().extend_from_slice(data);
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn log_text() -> String {
    String::from_utf8_lossy(&log().lock()).into_owned()
}

mod common;
use common::RunningGateway as Running;

async fn start_gateway(server: &TestServer, pair_for_s: u64) -> Running {
    start_gateway_with(server, |c| c.pair_for_s = pair_for_s).await
}

/// Only 127.0.0.1 counts as this machine, so 127.0.0.2 plays the phone; the gateway holds the server's token.
async fn start_gateway_with(server: &TestServer, tweak: impl FnOnce(&mut GatewayConfig)) -> Running {
    common::start_gateway(server.in_process_client(Some(SERVER_TOKEN)), |c| {
        c.local_addresses = Some(vec!["127.0.0.1".parse().unwrap()]);
        tweak(c);
    })
    .await
}

async fn tcp_from(local_ip: &str, to: SocketAddr) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket
        .bind(SocketAddr::new(local_ip.parse().unwrap(), 0))
        .unwrap();
    socket.connect(to).await.unwrap()
}

async fn rosbridge_from(local_ip: &str, gw: &Running, query: &str) -> WebSocketStream<TcpStream> {
    let addr = gw.info.rosbridge_addr.unwrap();
    let tcp = tcp_from(local_ip, addr).await;
    tokio_tungstenite::client_async(format!("ws://{addr}/{query}"), tcp)
        .await
        .unwrap()
        .0
}

async fn page_from(
    local_ip: &str,
    gw: &Running,
    path: &str,
) -> WebSocketStream<tokio_rustls::client::TlsStream<TcpStream>> {
    let tcp = tcp_from(local_ip, gw.info.https_addr.unwrap()).await;
    common::wss_over(&gw.info, tcp, path).await
}

/// Reads until the socket closes; returns the text frames and the close code.
async fn until_closed<S>(ws: &mut WebSocketStream<S>) -> (Vec<String>, Option<CloseCode>)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    let mut texts = Vec::new();
    loop {
        match tokio::time::timeout(T, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => texts.push(t.as_str().to_owned()),
            Ok(Some(Ok(Message::Close(frame)))) => return (texts, frame.map(|f| f.code)),
            Ok(Some(Ok(_))) => {}
            Ok(Some(Err(_)) | None) => return (texts, None),
            Err(elapsed) => panic!("the gateway kept an unpaired socket open ({elapsed}): {texts:?}"),
        }
    }
}

async fn send<S>(ws: &mut WebSocketStream<S>, text: &str)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    // A refused socket may already be closing; what matters is what reaches the arm.
    let _ = ws.send(Message::Text(text.into())).await;
}

fn app_pose(z: f64) -> String {
    format!(
        r#"{{"op":"publish","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped","msg":{{"header":{{"stamp":{{"sec":0,"nanosec":0}},"frame_id":"phone_ar_frame"}},"pose":{{"position":{{"x":0.0,"y":0.0,"z":{z:?}}},"orientation":{{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}}}}}"#
    )
}

const APP_FOLLOW: &str = r#"{"op":"publish","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray","msg":{"layout":{"dim":[],"data_offset":0},"data":[0,0]}}"#;
const SUBSCRIBE_STATUS: &str =
    r#"{"op":"subscribe","id":"s","topic":"/phone2act/status","type":"std_msgs/String"}"#;

async fn arm_state(client: &Client) -> v1::ArmState {
    phone2act_tests::arm_state(client, "main").await
}

async fn wait_until<F, Fut>(check: F) -> bool
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    phone2act_tests::wait_until(T, check).await
}

async fn first_publish(ws: &mut WebSocketStream<TcpStream>) -> Value {
    loop {
        match tokio::time::timeout(T, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => {
                let v: Value = serde_json::from_str(t.as_str()).unwrap();
                if v["op"] == "publish" {
                    return v;
                }
            }
            Ok(Some(Ok(_))) => {}
            other => panic!("an admitted client got no state: {other:?}"),
        }
    }
}

/// Tries everything an unpaired phone on the Wi-Fi could do; returns what it read.
async fn unpaired_attempts(gw: &Running, query: &str) -> Vec<String> {
    let mut app = rosbridge_from(PHONE, gw, query).await;
    send(&mut app, SUBSCRIBE_STATUS).await;
    for i in 0..5 {
        send(&mut app, &app_pose(-0.01 * f64::from(i))).await;
        send(&mut app, APP_FOLLOW).await;
    }
    let (texts, code) = until_closed(&mut app).await;
    assert_eq!(code, Some(CloseCode::Policy), "{texts:?}");
    texts
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_in_process_connection_checks_the_token_as_tcp_does() {
    // The embedded gateway reaches the server without a socket; that must not be a way around the token.
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    config.server.token = Some(SERVER_TOKEN.into());
    let server = TestServer::start(config).await.unwrap();
    for token in [None, Some("not-the-token")] {
        let err = server
            .in_process_client(token)
            .system()
            .status()
            .await
            .unwrap_err();
        assert!(
            matches!(&err, phone2act_sdk::Error::Status(s) if s.code() == tonic::Code::Unauthenticated),
            "{token:?}: {err}"
        );
        let mut teleop = server.in_process_client(token).teleop_raw();
        let refused = teleop
            .stream(tokio_stream::iter([v1::PhoneSample {
                arm: "main".into(),
                ..v1::PhoneSample::default()
            }]))
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{token:?}");
    }
    let status = server
        .in_process_client(Some(SERVER_TOKEN))
        .system()
        .status()
        .await
        .unwrap();
    assert_eq!(status.arms.len(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unpaired_peer_is_refused_pairing_through_the_page_admits_it_and_expires() {
    let log = log();
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    config.server.token = Some(SERVER_TOKEN.into());
    let server = TestServer::start(config).await.unwrap();
    let client = Client::connect(&server.url(), Some(SERVER_TOKEN)).await.unwrap();
    // Pairings last 2 s here so that expiry is observable; see the wait below.
    let gw = start_gateway(&server, 2).await;
    tokio::time::sleep(Duration::from_millis(300)).await;

    // An authenticated policy owns the arm.
    let policy = client
        .policy(phone2act_tests::policy_hello(&["main"], "authenticated", 60.0))
        .await
        .unwrap();
    let before = arm_state(&client).await;
    assert_eq!(before.owner(), v1::ControlSource::Policy);

    // The unpaired phone: no token, a wrong token; rosbridge on ws:// and on wss://…/rosbridge; the page.
    for query in ["", "?token=guess"] {
        let texts = unpaired_attempts(&gw, query).await;
        // It learns why, and nothing else: no published state.
        assert_eq!(texts.len(), 1, "{texts:?}");
        let v: Value = serde_json::from_str(&texts[0]).unwrap();
        assert_eq!(v["op"], "status");
        assert!(v["msg"].as_str().unwrap().contains("not paired"), "{v}");
    }
    let mut tls_rosbridge = page_from(PHONE, &gw, "/rosbridge").await;
    send(&mut tls_rosbridge, SUBSCRIBE_STATUS).await;
    send(&mut tls_rosbridge, APP_FOLLOW).await;
    let (texts, code) = until_closed(&mut tls_rosbridge).await;
    assert_eq!(code, Some(CloseCode::Policy), "{texts:?}");
    let mut page = page_from(PHONE, &gw, "/ws?token=guess").await;
    send(&mut page, r#"{"type":"hello","arm":"main","take_over":true}"#).await;
    let (texts, code) = until_closed(&mut page).await;
    assert_eq!(code, Some(CloseCode::Policy), "{texts:?}");
    assert!(texts.iter().all(|t| !t.contains("feedback")), "{texts:?}");
    // The server's terminal names the address and says how to pair it.
    assert!(
        wait_until(|| async { log_text().contains("127.0.0.2 refused: not paired") }).await,
        "no refusal log line: {}",
        log_text()
    );
    assert!(log_text().contains("open the phone page URL"));
    let after = arm_state(&client).await;
    assert_eq!(
        after.owner(),
        v1::ControlSource::Policy,
        "the policy lost the arm"
    );
    assert_eq!(after.owner_id, before.owner_id);
    assert!(!after.engaged);

    // Opening the page with the token pairs 127.0.0.2 ...
    let token = gw.info.token.clone().unwrap();
    let page = page_from(PHONE, &gw, &format!("/ws?token={token}")).await;
    assert!(
        wait_until(|| async { log_text().contains("paired 127.0.0.2 for rosbridge") }).await,
        "{}",
        log_text()
    );
    drop(page);
    drop(policy);
    assert!(wait_until(|| async { arm_state(&client).await.owner() == v1::ControlSource::None }).await);
    // ... so the app on that phone now reads state and drives.
    let mut app = rosbridge_from(PHONE, &gw, "").await;
    send(&mut app, SUBSCRIBE_STATUS).await;
    let status = first_publish(&mut app).await;
    assert_eq!(status["topic"], "/phone2act/status");
    send(&mut app, &app_pose(0.0)).await;
    send(&mut app, APP_FOLLOW).await;
    assert!(
        wait_until(|| async { arm_state(&client).await.engaged }).await,
        "a paired phone could not drive"
    );
    drop(app);

    // Pairings last 2 s: 2.2 s after the page opened, a new connection is refused. Expiry is compared with
    // the clock at connect time, so a slow machine can only make the wait longer, never the check pass.
    tokio::time::sleep(Duration::from_millis(2200)).await;
    let texts = unpaired_attempts(&gw, "").await;
    assert!(texts[0].contains("not paired"), "{texts:?}");

    // Loopback (127.0.0.1 here) is always let in.
    let mut local = rosbridge_from("127.0.0.1", &gw, "").await;
    send(&mut local, SUBSCRIBE_STATUS).await;
    assert_eq!(first_publish(&mut local).await["topic"], "/phone2act/status");
    drop(local);
    drop(log);
    drop(gw);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_guessed_session_id_pushes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut policy = client
        .policy(phone2act_tests::policy_hello(&["main"], "victim", 60.0))
        .await
        .unwrap();
    let real = policy.ready().session_id.clone();
    let (number, secret) = real.split_once('.').expect("id.secret");
    assert_eq!(secret.len(), 32, "128 random bits in hex: {real}");
    let obs = policy.next_observation().await.unwrap();
    let start = pos(obs.arms[0].robot_from_ee.as_ref().unwrap());
    let width = policy.ready().arms[0].action_names.len();
    let step = |dx: f64| {
        let mut values = vec![0.0; width];
        values[0] = dx;
        v1::ActionStep { values }
    };
    let chunk = v1::ActionChunk {
        arm: "main".into(),
        steps: (1..=10).map(|i| step(0.005 * f64::from(i))).collect(),
        step_period_s: 0.05,
        observation_id: obs.observation_id,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    };
    // Another client guesses: small integers, the visible number, the number with a wrong or truncated key.
    let attacker = server.client().await.unwrap();
    let mut flipped = secret.as_bytes().to_vec();
    flipped[0] = if flipped[0] == b'0' { b'1' } else { b'0' };
    let guesses = [
        "0".to_owned(),
        "1".to_owned(),
        "2".to_owned(),
        number.to_owned(),
        format!("{number}."),
        format!("{number}.{}", String::from_utf8(flipped).unwrap()),
        format!("{number}.{}", secret.get(..31).unwrap()),
        format!("{number}.{secret}0"),
    ];
    for guess in &guesses {
        let err = attacker
            .policy_raw()
            .push_chunk(v1::PushChunkRequest {
                session_id: guess.clone(),
                chunk: Some(chunk.clone()),
            })
            .await
            .unwrap_err();
        assert_eq!(err.code(), tonic::Code::NotFound, "{guess}: {err}");
    }
    // Ten 50 ms steps would have moved the arm 5 cm by now.
    tokio::time::sleep(Duration::from_millis(800)).await;
    let still = phone2act_tests::sim_pose_of(&client, "main").await;
    let moved = ((still[0] - start[0]).powi(2) + (still[1] - start[1]).powi(2)).sqrt();
    assert!(moved < 0.002, "a guessed id moved the arm {moved} m");
    // The session's own id still works (anchored at arrival: the observation is old by now).
    let fresh = v1::ActionChunk {
        observation_id: 0,
        ..chunk
    };
    let accepted = policy.push_chunk_checked(&client, fresh).await.unwrap();
    assert!(accepted.steps_scheduled > 0, "{accepted:?}");
    drop(policy);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_address_cannot_take_an_arm_from_a_silent_phone_until_it_disconnects() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    config.server.token = Some(SERVER_TOKEN.into());
    let server = TestServer::start(config).await.unwrap();
    let client = Client::connect(&server.url(), Some(SERVER_TOKEN)).await.unwrap();
    // 127.0.0.2 is admitted (allow list) but is another address than the holder's.
    let gw = start_gateway_with(&server, |c| c.allow = vec![PHONE.parse().unwrap()]).await;
    tokio::time::sleep(Duration::from_millis(300)).await;

    let mut holder = rosbridge_from("127.0.0.1", &gw, "").await;
    send(&mut holder, &app_pose(0.0)).await;
    send(&mut holder, APP_FOLLOW).await;
    assert!(wait_until(|| async { arm_state(&client).await.engaged }).await);
    let owner = arm_state(&client).await.owner_id;
    let held = pos(arm_state(&client).await.robot_from_target.as_ref().unwrap());
    // The holder goes silent with its socket open (reading, so it answers pings).
    let holder_task = tokio::spawn(async move { while let Some(Ok(_)) = holder.next().await {} });

    let mut other = rosbridge_from(PHONE, &gw, "").await;
    send(&mut other, r#"{"op":"set_level","level":"error"}"#).await;
    // 1.5 s of poses walking 5 cm, five times the take-over silence: the arm must not change hands.
    for i in 0..75 {
        send(&mut other, &app_pose(-0.05 * f64::from(i) / 75.0)).await;
        if i % 10 == 0 {
            send(&mut other, APP_FOLLOW).await;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let state = arm_state(&client).await;
    assert_eq!(state.owner_id, owner, "another address took the arm");
    let now = pos(state.robot_from_target.as_ref().unwrap());
    let moved = ((now[0] - held[0]).powi(2) + (now[1] - held[1]).powi(2) + (now[2] - held[2]).powi(2)).sqrt();
    assert!(moved < 1e-9, "the arm moved {moved} m");
    let refusal = loop {
        match tokio::time::timeout(T, other.next()).await {
            Ok(Some(Ok(Message::Text(t)))) if t.as_str().contains("status") => break t.as_str().to_owned(),
            Ok(Some(Ok(_))) => {}
            other => panic!("no refusal status: {other:?}"),
        }
    };
    assert!(
        refusal.contains("driven by another phone (127.0.0.1)"),
        "{refusal}"
    );

    // Once the holder disconnects, the arm is free for the other phone (after its 2 s refusal back-off).
    holder_task.abort();
    let deadline = tokio::time::Instant::now() + T;
    let mut z = -0.05;
    let mut took = false;
    while !took && tokio::time::Instant::now() < deadline {
        z -= 0.0005;
        send(&mut other, &app_pose(z)).await;
        send(&mut other, APP_FOLLOW).await;
        tokio::time::sleep(Duration::from_millis(20)).await;
        took = arm_state(&client).await.owner_id != owner;
    }
    assert!(took, "the arm stayed bound to a closed socket");
    drop(other);
    drop(gw);
    server.shutdown().await.unwrap();
}

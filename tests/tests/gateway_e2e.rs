//! The phone gateway in front of the real server (issue 6): the Phone2Act Android app's messages replayed byte
//! for byte move the simulated arm and toggle its gripper; `/left` and `/right` namespaces drive their own
//! arms; the phone page's socket records an episode. Everything over real sockets.

use futures_util::{SinkExt, StreamExt};
use phone2act_gateway::{Gateway, GatewayConfig, GatewayInfo, Listeners};
use phone2act_sdk::Client;
use phone2act_tests::{TestServer, bimanual_config, default_config, pos, sim_pose_of};
use rustls::pki_types::pem::PemObject;
use serde_json::Value;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpStream;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;

const T: Duration = Duration::from_secs(10);

struct RunningGateway {
    info: GatewayInfo,
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

async fn start_gateway(server: &TestServer) -> RunningGateway {
    let dir = tempfile::tempdir().unwrap();
    let config = GatewayConfig {
        cert_dir: Some(dir.path().to_owned()),
        print_qr: false,
        public_host: Some("127.0.0.1".into()),
        ..GatewayConfig::default()
    };
    let listeners = Listeners {
        rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
        https: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
    };
    let gateway = Gateway::with_listeners(config, &server.url(), None, listeners).unwrap();
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

async fn rosbridge(gw: &RunningGateway) -> WebSocketStream<TcpStream> {
    let addr = gw.info.rosbridge_addr.unwrap();
    let tcp = TcpStream::connect(addr).await.unwrap();
    tokio_tungstenite::client_async(format!("ws://{addr}/"), tcp)
        .await
        .unwrap()
        .0
}

async fn send<S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin>(
    ws: &mut WebSocketStream<S>,
    text: &str,
) {
    ws.send(Message::Text(text.into())).await.unwrap();
}

/// The app's AR pose publish, in the app's own key order and number formatting (Dart `jsonEncode`).
fn app_pose(sec: i64, nanosec: i64, p: [f64; 3]) -> String {
    format!(
        r#"{{"op":"publish","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped","msg":{{"header":{{"stamp":{{"sec":{sec},"nanosec":{nanosec}}},"frame_id":"phone_ar_frame"}},"pose":{{"position":{{"x":{:?},"y":{:?},"z":{:?}}},"orientation":{{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}}}}}"#,
        p[0], p[1], p[2]
    )
}

fn app_volume(up: i32, down: i32) -> String {
    format!(
        r#"{{"op":"publish","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray","msg":{{"layout":{{"dim":[],"data_offset":0}},"data":[{up},{down}]}}}}"#
    )
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

async fn arm_state(client: &Client, arm: &str) -> phone2act_sdk::proto::ArmState {
    client
        .system()
        .list_arms()
        .await
        .unwrap()
        .into_iter()
        .find(|a| a.arm == arm)
        .unwrap()
}

async fn wait_until<F, Fut>(mut check: F) -> bool
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = tokio::time::Instant::now() + T;
    while tokio::time::Instant::now() < deadline {
        if check().await {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    false
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_android_apps_bytes_move_the_sim_arm_and_toggle_the_gripper() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let gw = start_gateway(&server).await;
    tokio::time::sleep(Duration::from_millis(400)).await;
    let before = sim_pose_of(&client, "main").await;

    let mut app = rosbridge(&gw).await;
    // Exactly what the app sends on connect: one advertise per topic, no id, no latch.
    send(
        &mut app,
        r#"{"op":"advertise","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped"}"#,
    )
    .await;
    send(
        &mut app,
        r#"{"op":"advertise","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray"}"#,
    )
    .await;
    let (sec, mut nanosec) = (1_763_726_400_i64, 0_i64);
    let mut tick = tokio::time::interval(Duration::from_millis(20));
    for _ in 0..5 {
        tick.tick().await;
        nanosec += 20_000_000;
        send(&mut app, &app_pose(sec, nanosec, [0.0, 0.0, 0.0])).await;
    }
    // The volume monitor starts and reports the app's state [0, 0]: follow (and gripper closed), as the
    // original planner reads it.
    send(&mut app, &app_volume(0, 0)).await;
    assert!(
        wait_until(|| async { arm_state(&client, "main").await.engaged }).await,
        "[0, 0] did not engage"
    );
    let gripper_before = arm_state(&client, "main").await.gripper_target;
    let engaged_target = pos(arm_state(&client, "main")
        .await
        .robot_from_target
        .as_ref()
        .unwrap());

    // Walk the phone 8 cm forward (-Z in ARCore's frame) at the app's 50 Hz, 5 mm per message.
    for i in 1..=16 {
        tick.tick().await;
        nanosec += 20_000_000;
        send(
            &mut app,
            &app_pose(sec, nanosec, [0.0, 0.0, -0.005 * f64::from(i)]),
        )
        .await;
    }
    // ARCore repeats poses between its 30 Hz updates; so does the app.
    for _ in 0..10 {
        tick.tick().await;
        nanosec += 20_000_000;
        send(&mut app, &app_pose(sec, nanosec, [0.0, 0.0, -0.08])).await;
    }
    let moved = wait_until(|| async {
        let target = pos(arm_state(&client, "main")
            .await
            .robot_from_target
            .as_ref()
            .unwrap());
        (dist(target, engaged_target) - 0.08).abs() < 0.005
    })
    .await;
    let target = pos(arm_state(&client, "main")
        .await
        .robot_from_target
        .as_ref()
        .unwrap());
    assert!(
        moved,
        "target moved {} m for an 8 cm phone move",
        dist(target, engaged_target)
    );
    assert!(
        wait_until(|| async { dist(sim_pose_of(&client, "main").await, target) < 0.01 }).await,
        "the sim arm did not follow its target"
    );
    let after = sim_pose_of(&client, "main").await;
    assert!(
        dist(after, before) > 0.06,
        "sim arm did not move: {before:?} -> {after:?}"
    );

    // Volume up flips the gripper toggle state: [1, 0] opens it.
    send(&mut app, &app_volume(1, 0)).await;
    assert!(
        wait_until(|| async {
            (arm_state(&client, "main").await.gripper_target - gripper_before).abs() > 0.5
        })
        .await,
        "volume-up did not toggle the gripper"
    );
    // A valid session produces no status errors for the app.
    let quiet = tokio::time::timeout(Duration::from_millis(200), app.next()).await;
    assert!(
        !matches!(quiet, Ok(Some(Ok(Message::Text(_))))),
        "unexpected reply to valid app traffic: {quiet:?}"
    );
    drop(app);
    drop(gw);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn left_and_right_namespaces_drive_their_own_arms() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(bimanual_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let gw = start_gateway(&server).await;
    tokio::time::sleep(Duration::from_millis(400)).await;
    let mut ws = rosbridge(&gw).await;
    let clutch = |ns: &str| {
        format!(
            r#"{{"op":"publish","topic":"/{ns}/phone2act/clutch","type":"std_msgs/msg/Bool","msg":{{"data":true}}}}"#
        )
    };
    let pose = |ns: &str, p: [f64; 3]| {
        format!(
            r#"{{"op":"publish","topic":"/{ns}/Phone2Act/ar_pose","msg":{{"pose":{{"position":{{"x":{},"y":{},"z":{}}},"orientation":{{"x":0,"y":0,"z":0,"w":1}}}}}}}}"#,
            p[0], p[1], p[2]
        )
    };
    for ns in ["left", "right"] {
        send(&mut ws, &pose(ns, [0.0, 0.0, 0.0])).await;
        send(&mut ws, &clutch(ns)).await;
    }
    assert!(
        wait_until(|| async {
            arm_state(&client, "left").await.engaged && arm_state(&client, "right").await.engaged
        })
        .await
    );
    let l0 = pos(arm_state(&client, "left")
        .await
        .robot_from_target
        .as_ref()
        .unwrap());
    let r0 = pos(arm_state(&client, "right")
        .await
        .robot_from_target
        .as_ref()
        .unwrap());
    // Left phone forward (-Z), right phone up (+Y), 4 cm in 1 cm steps.
    for i in 1..=4 {
        let d = 0.01 * f64::from(i);
        send(&mut ws, &pose("left", [0.0, 0.0, -d])).await;
        send(&mut ws, &pose("right", [0.0, d, 0.0])).await;
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
    assert!(
        wait_until(|| async {
            let l = pos(arm_state(&client, "left")
                .await
                .robot_from_target
                .as_ref()
                .unwrap());
            let r = pos(arm_state(&client, "right")
                .await
                .robot_from_target
                .as_ref()
                .unwrap());
            (dist(l, l0) - 0.04).abs() < 0.005 && (dist(r, r0) - 0.04).abs() < 0.005
        })
        .await,
        "each arm should have moved 4 cm"
    );
    let l = pos(arm_state(&client, "left")
        .await
        .robot_from_target
        .as_ref()
        .unwrap());
    let r = pos(arm_state(&client, "right")
        .await
        .robot_from_target
        .as_ref()
        .unwrap());
    let dl = [l[0] - l0[0], l[1] - l0[1], l[2] - l0[2]];
    let dr = [r[0] - r0[0], r[1] - r0[1], r[2] - r0[2]];
    let cos = (dl[0] * dr[0] + dl[1] * dr[1] + dl[2] * dr[2]) / (dist(l, l0) * dist(r, r0));
    assert!(cos.abs() < 0.2, "left and right moved alike: {dl:?} {dr:?}");

    // Robot feedback for rosbridge subscribers comes back as PoseStamped in the robot base frame.
    send(&mut ws, r#"{"op":"subscribe","id":"fb","topic":"/left/phone2act/robot_feedback","type":"geometry_msgs/PoseStamped"}"#)
        .await;
    let fb = loop {
        match tokio::time::timeout(T, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => {
                let v: Value = serde_json::from_str(t.as_str()).unwrap();
                if v["op"] == "publish" {
                    break v;
                }
            }
            Ok(Some(Ok(_))) => {}
            other => panic!("no feedback publish: {other:?}"),
        }
    };
    assert_eq!(fb["topic"], "/left/phone2act/robot_feedback");
    let ee = sim_pose_of(&client, "left").await;
    let got = [
        fb["msg"]["pose"]["position"]["x"].as_f64().unwrap(),
        fb["msg"]["pose"]["position"]["y"].as_f64().unwrap(),
        fb["msg"]["pose"]["position"]["z"].as_f64().unwrap(),
    ];
    assert!(dist(got, ee) < 0.02, "feedback {got:?} vs measured {ee:?}");
    drop(ws);
    drop(gw);
    server.shutdown().await.unwrap();
}

async fn wss(gw: &RunningGateway, path: &str) -> WebSocketStream<tokio_rustls::client::TlsStream<TcpStream>> {
    let pem = std::fs::read(gw.info.cert_path.as_ref().unwrap()).unwrap();
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
    let addr = gw.info.https_addr.unwrap();
    let tcp = TcpStream::connect(addr).await.unwrap();
    let tls = tokio_rustls::TlsConnector::from(Arc::new(config))
        .connect("localhost".try_into().unwrap(), tcp)
        .await
        .unwrap();
    tokio_tungstenite::client_async(format!("wss://localhost:{}{path}", addr.port()), tls)
        .await
        .unwrap()
        .0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_socket_records_an_episode() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let gw = start_gateway(&server).await;
    tokio::time::sleep(Duration::from_millis(400)).await;
    let token = gw.info.token.clone().unwrap();
    let mut page = wss(&gw, &format!("/ws?token={token}")).await;
    let mut seq = 0u64;
    let mut sample = |buttons: &str, z: f64| {
        seq += 1;
        format!(
            r#"{{"type":"sample","seq":{seq},"t_ns":{},"tracking":"tracking","pose":{{"p":[0.0,1.4,{z}],"q":[0,0,0,1]}},"buttons":[{buttons}]}}"#,
            seq * 16_000_000
        )
    };
    send(
        &mut page,
        &sample(
            r#"{"clutch":"engage"},{"record":"start","task":"put the ball in the basket"}"#,
            0.0,
        ),
    )
    .await;
    for i in 1..=40 {
        send(&mut page, &sample("", -0.001 * f64::from(i))).await;
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
    send(&mut page, &sample(r#"{"record":"stop"}"#, -0.04)).await;
    let saved = wait_until(|| async {
        client
            .episodes()
            .list()
            .await
            .is_ok_and(|l| l.episodes.len() == 1)
    })
    .await;
    assert!(saved, "no episode saved");
    let episodes = client.episodes().list().await.unwrap().episodes;
    assert_eq!(episodes[0].task, "put the ball in the basket");
    assert!(
        episodes[0].length_frames >= 10,
        "episode too short: {:?}",
        episodes[0]
    );

    // The page saw its own round trips and the recording state.
    let mut phases = Vec::new();
    // The server sends idle feedback every 100 ms, so drain for a bounded time rather than until silence.
    let drain_until = tokio::time::Instant::now() + Duration::from_secs(1);
    while let Ok(Some(Ok(msg))) = tokio::time::timeout_at(drain_until, page.next()).await {
        if let Message::Text(t) = msg {
            let v: Value = serde_json::from_str(t.as_str()).unwrap();
            if v["type"] == "feedback" {
                assert!(v["seq"].as_u64().unwrap() <= seq);
                phases.push(v["recording"]["phase"].as_str().unwrap().to_owned());
            }
        }
    }
    assert!(
        phases.iter().any(|p| p == "recording"),
        "page never saw recording: {phases:?}"
    );
    drop(page);
    drop(gw);
    server.shutdown().await.unwrap();
}

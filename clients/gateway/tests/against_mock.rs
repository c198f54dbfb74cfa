//! The gateway against the mock Teleop/System server over real sockets: what reaches the server for each kind
//! of client, and what bad input does (and does not) break.

// Poses pass through untouched: exact equality is the property under test.
#![allow(clippy::float_cmp)]

mod common;

use common::*;
use futures_util::StreamExt;
use phone2act_proto::v1::{RecordingPhase, button_event, clutch_command, gripper_command, record_command};
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

const T: Duration = Duration::from_secs(5);

/// Byte for byte what the Phone2Act Android app sends, in the order it sends it.
const APP_ADVERTISE_POSE: &str =
    r#"{"op":"advertise","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped"}"#;
const APP_ADVERTISE_VOLUME: &str =
    r#"{"op":"advertise","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray"}"#;
/// The app's volume publish for toggle states `[up, down]`.
fn app_volume(up: i32, down: i32) -> String {
    format!(
        r#"{{"op":"publish","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray","msg":{{"layout":{{"dim":[],"data_offset":0}},"data":[{up},{down}]}}}}"#
    )
}

fn gripper_set(b: &phone2act_proto::v1::ButtonEvent) -> Option<f64> {
    match &b.event {
        Some(button_event::Event::Gripper(g)) if g.kind() == gripper_command::Kind::Set => Some(g.position),
        _ => None,
    }
}

fn clutch_kind(b: &phone2act_proto::v1::ButtonEvent) -> Option<clutch_command::Kind> {
    match &b.event {
        Some(button_event::Event::Clutch(c)) => Some(c.kind()),
        _ => None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn android_app_volume_states_are_read_as_the_original_planner_reads_them() {
    let h = start(&["main"], |_| {}).await;
    let mut ws = rosbridge(&h).await;
    send(&mut ws, APP_ADVERTISE_POSE).await;
    send(&mut ws, APP_ADVERTISE_VOLUME).await;
    send(&mut ws, &pose_msg("/Phone2Act/ar_pose", 0.01)).await;
    assert!(
        h.mock.wait_for(T, |m| !m.received().is_empty()).await,
        "no sample arrived"
    );
    // The volume monitor starts: the app reports its state [0, 0]: follow, gripper closed (1.0).
    send(&mut ws, &app_volume(0, 0)).await;
    assert!(
        h.mock
            .wait_for(T, |m| {
                let a = m.arm("main").unwrap();
                a.engaged && a.gripper_target > 0.99
            })
            .await,
        "[0, 0] did not follow with the gripper closed"
    );
    send(&mut ws, &pose_msg("/Phone2Act/ar_pose", 0.05)).await;
    // Volume up: [1, 0]: still following, gripper open.
    send(&mut ws, &app_volume(1, 0)).await;
    assert!(
        h.mock
            .wait_for(T, |m| {
                let a = m.arm("main").unwrap();
                a.engaged && a.gripper_target < 0.01
            })
            .await,
        "[1, 0] did not open the gripper"
    );
    // Volume down: [1, 1]: hold.
    send(&mut ws, &app_volume(1, 1)).await;
    assert!(
        h.mock.wait_for(T, |m| !m.arm("main").unwrap().engaged).await,
        "[1, 1] did not hold"
    );
    // A repeated state changes nothing (the server ignores a disengage while disengaged).
    send(&mut ws, &app_volume(1, 1)).await;

    let received = h.mock.received();
    assert!(received.iter().all(|r| r.arm == "main"));
    let first = &received[0].sample;
    assert_eq!(
        first.capture_time_ns, 1_763_726_400_005_000_000,
        "header stamp not carried"
    );
    assert_eq!(first.client_name, "phone2act-android");
    let poses: Vec<f64> = received
        .iter()
        .filter_map(|r| {
            r.sample
                .tracking_from_phone
                .and_then(|p| p.position_m)
                .map(|p| p.x)
        })
        .collect();
    assert!(poses.contains(&0.05), "second pose missing: {poses:?}");
    assert!(
        h.mock
            .wait_for(T, |m| m
                .received()
                .iter()
                .map(|r| r.sample.buttons.len())
                .sum::<usize>()
                == 8)
            .await
    );
    let buttons: Vec<_> = h
        .mock
        .received()
        .iter()
        .flat_map(|r| r.sample.buttons.clone())
        .collect();
    let gripper: Vec<_> = buttons.iter().filter_map(gripper_set).collect();
    let clutch: Vec<_> = buttons.iter().filter_map(clutch_kind).collect();
    assert_eq!(gripper, vec![1.0, 0.0, 0.0, 0.0], "{buttons:?}");
    assert_eq!(
        clutch,
        vec![
            clutch_command::Kind::Engage,
            clutch_command::Kind::Engage,
            clutch_command::Kind::Disengage,
            clutch_command::Kind::Disengage
        ]
    );
    // The app's messages are valid: no status errors came back.
    assert_eq!(next_json(&mut ws, Duration::from_millis(200)).await, None);
    // A state other than 0/1 is refused and changes nothing.
    send(&mut ws, r#"{"op":"set_level","level":"error"}"#).await;
    send(&mut ws, &app_volume(2, 0)).await;
    let e = wait_json(&mut ws, T, |v| v["op"] == "status").await.unwrap();
    assert!(e["msg"].as_str().unwrap().contains("0 or 1"), "{e}");
    assert!(!h.mock.arm("main").unwrap().engaged);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn namespaces_drive_their_own_arms_and_feedback_is_published() {
    let h = start(&["left", "right"], |_| {}).await;
    let mut ws = rosbridge(&h).await;
    send(&mut ws, &pose_msg("/left/Phone2Act/ar_pose", 0.1)).await;
    send(&mut ws, &pose_msg("/right/Phone2Act/ar_pose", 0.2)).await;
    assert!(
        h.mock
            .wait_for(T, |m| {
                let r = m.received();
                r.iter().any(|s| s.arm == "left") && r.iter().any(|s| s.arm == "right")
            })
            .await
    );
    for r in h.mock.received() {
        let x = r.sample.tracking_from_phone.unwrap().position_m.unwrap().x;
        assert_eq!(x, if r.arm == "left" { 0.1 } else { 0.2 }, "pose crossed arms");
    }
    send(
        &mut ws,
        r#"{"op":"subscribe","id":"s1","topic":"/right/phone2act/robot_feedback","type":"geometry_msgs/msg/PoseStamped"}"#,
    )
    .await;
    let fb = wait_json(&mut ws, T, |v| v["op"] == "publish")
        .await
        .expect("no feedback publish");
    assert_eq!(fb["topic"], "/right/phone2act/robot_feedback");
    assert_eq!(fb["msg"]["pose"]["position"]["x"], 0.2);
    assert_eq!(fb["msg"]["header"]["frame_id"], "robot_base");
    send(&mut ws, r#"{"op":"subscribe","topic":"/left/phone2act/status"}"#).await;
    let status = wait_json(&mut ws, T, |v| v["topic"] == "/left/phone2act/status")
        .await
        .unwrap();
    let inner: serde_json::Value = serde_json::from_str(status["msg"]["data"].as_str().unwrap()).unwrap();
    assert_eq!(inner["arm"], "left");
    assert_eq!(inner["recording"]["phase"], "idle");
    send(
        &mut ws,
        r#"{"op":"unsubscribe","id":"s1","topic":"/right/phone2act/robot_feedback"}"#,
    )
    .await;
    send(
        &mut ws,
        r#"{"op":"unsubscribe","topic":"/left/phone2act/status"}"#,
    )
    .await;
    // Drain what was in flight, then nothing more may come.
    tokio::time::sleep(Duration::from_millis(150)).await;
    while next_json(&mut ws, Duration::from_millis(50)).await.is_some() {}
    assert_eq!(
        next_json(&mut ws, Duration::from_millis(300)).await,
        None,
        "publishes after unsubscribe"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_is_refused_and_harms_nobody() {
    let h = start(&["main", "left"], |_| {}).await;
    let mut bad = rosbridge(&h).await;
    let mut good = rosbridge(&h).await;
    // Without set_level a client gets no status messages (rosbridge sends none; roslibpy fails on them).
    send(&mut good, "{not json").await;
    assert_eq!(
        next_json(&mut good, Duration::from_millis(300)).await,
        None,
        "unasked status sent"
    );
    send(&mut bad, r#"{"op":"set_level","level":"error"}"#).await;
    send(&mut good, &pose_msg("/left/Phone2Act/ar_pose", 0.3)).await;
    assert!(
        h.mock
            .wait_for(T, |m| m.received().iter().any(|r| r.arm == "left"))
            .await
    );

    send(&mut bad, "{not json").await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert_eq!(
        (e["op"].as_str(), e["level"].as_str()),
        (Some("status"), Some("error"))
    );
    assert!(e["msg"].as_str().unwrap().contains("malformed JSON"));

    send(&mut bad, r#"{"op":"teleport","id":"t:1"}"#).await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert_eq!(e["id"], "t:1");
    assert!(e["msg"].as_str().unwrap().contains("unknown op"));

    let big = format!(
        r#"{{"op":"publish","topic":"/Phone2Act/ar_pose","msg":{{"pad":"{}"}}}}"#,
        "x".repeat(10 << 20)
    );
    send(&mut bad, &big).await;
    let e = next_json(&mut bad, T).await.expect("no reply to a 10 MB frame");
    assert!(e["msg"].as_str().unwrap().contains("exceeds the limit"), "{e}");

    let nan = r#"{"op":"publish","id":"n","topic":"/Phone2Act/ar_pose","msg":{"pose":{"position":{"x":NaN,"y":0,"z":0},"orientation":{"x":0,"y":0,"z":0,"w":1}}}}"#;
    send(&mut bad, nan).await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert!(e["msg"].as_str().unwrap().contains("pose.position.x"), "{e}");
    assert!(
        !h.mock.received().iter().any(|r| r.arm == "main"),
        "a refused message reached the server"
    );

    send(&mut bad, &pose_msg("/Phone2Act/volume", 0.0)).await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert!(
        e["msg"]
            .as_str()
            .unwrap()
            .contains("carries std_msgs/Int32MultiArray"),
        "{e}"
    );

    send(&mut bad, r#"{"op":"call_service","id":"c","service":"/reset"}"#).await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert_eq!(
        (e["op"].as_str(), e["result"].as_bool()),
        (Some("service_response"), Some(false))
    );
    send(
        &mut bad,
        r#"{"op":"call_service","id":"s","service":"/rosapi/services"}"#,
    )
    .await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert_eq!(
        (e["result"].as_bool(), e["id"].as_str()),
        (Some(true), Some("s")),
        "{e}"
    );
    assert!(
        e["values"]["services"]
            .as_array()
            .is_some_and(|s| s.iter().any(|s| s == "/rosapi/topics")),
        "{e}"
    );
    // A subscription nothing will ever answer is an error, not silence.
    send(
        &mut bad,
        r#"{"op":"subscribe","id":"u","topic":"/no/such/topic"}"#,
    )
    .await;
    let e = next_json(&mut bad, T).await.unwrap();
    assert_eq!(
        (e["level"].as_str(), e["id"].as_str()),
        (Some("error"), Some("u")),
        "{e}"
    );
    assert!(
        e["msg"]
            .as_str()
            .unwrap()
            .contains("unknown topic /no/such/topic"),
        "{e}"
    );

    // The same connection still works, and so does the other phone.
    send(&mut bad, &pose_msg("/Phone2Act/ar_pose", 0.7)).await;
    assert!(
        h.mock
            .wait_for(T, |m| m.received().iter().any(|r| r.arm == "main"))
            .await,
        "bad socket broken"
    );
    let before = h.mock.received().iter().filter(|r| r.arm == "left").count();
    send(&mut good, &pose_msg("/left/Phone2Act/ar_pose", 0.31)).await;
    assert!(
        h.mock
            .wait_for(T, |m| m.received().iter().filter(|r| r.arm == "left").count()
                > before)
            .await
    );

    // An unknown arm is the server's refusal, relayed once as a status error.
    let h2 = start(&["main"], |c| c.rosbridge_status_level = "error".into()).await;
    let mut ws = rosbridge(&h2).await;
    send(&mut ws, &pose_msg("/left/Phone2Act/ar_pose", 0.0)).await;
    let e = wait_json(&mut ws, T, |v| v["op"] == "status").await.unwrap();
    assert!(e["msg"].as_str().unwrap().contains("NotFound"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_beyond_the_hard_cap_closes_only_that_socket() {
    let h = start(&["main"], |_| {}).await;
    let mut huge = rosbridge(&h).await;
    let mut other = rosbridge(&h).await;
    let text = "x".repeat(phone2act_gateway::config::HARD_MAX_MESSAGE_BYTES + 1);
    let _ = futures_util::SinkExt::send(&mut huge, Message::Text(text.into())).await;
    let closed = tokio::time::timeout(T, async {
        loop {
            match huge.next().await {
                Some(Ok(Message::Close(frame))) => return frame.map(|f| u16::from(f.code)),
                None | Some(Err(_)) => return None,
                _ => {}
            }
        }
    })
    .await
    .expect("socket not closed");
    if let Some(code) = closed {
        assert_eq!(code, 1009);
    }
    send(&mut other, &pose_msg("/Phone2Act/ar_pose", 0.2)).await;
    assert!(
        h.mock.wait_for(T, |m| !m.received().is_empty()).await,
        "other phone harmed"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_socket_needs_the_token_and_drives_recording() {
    let h = start(&["left", "right"], |_| {}).await;
    let token = h.info.token.clone().expect("a token is generated by default");
    assert!(
        h.info
            .page_url
            .as_ref()
            .unwrap()
            .ends_with(&format!("?token={token}"))
    );

    let mut wrong = wss(&h, "/ws?token=nope").await;
    let e = next_json(&mut wrong, T).await.unwrap();
    assert_eq!(e["type"], "error");
    assert!(e["message"].as_str().unwrap().contains("pairing token"));
    let mut missing = wss(&h, "/ws").await;
    assert_eq!(next_json(&mut missing, T).await.unwrap()["type"], "error");
    assert_eq!(
        next_json(&mut missing, Duration::from_millis(300)).await,
        None,
        "socket stayed open"
    );

    let mut page = wss(&h, &format!("/ws?token={token}")).await;
    let welcome = next_json(&mut page, T).await.unwrap();
    assert_eq!(welcome["type"], "welcome");
    assert_eq!(welcome["arms"], serde_json::json!(["left", "right"]));
    // The page tells the Phone2Act app's users the port rosbridge really listens on (here an ephemeral one).
    assert_eq!(
        welcome["rosbridge_port"],
        serde_json::json!(h.info.rosbridge_addr.unwrap().port())
    );
    send(&mut page, r#"{"type":"hello","arm":"right"}"#).await;
    let open = wait_json(&mut page, T, |v| v["type"] == "session").await.unwrap();
    assert_eq!(
        (open["state"].as_str(), open["arm"].as_str()),
        (Some("open"), Some("right"))
    );

    send(
        &mut page,
        r#"{"type":"sample","seq":1,"t_ns":1000,"pose":{"p":[0.0,1.4,-0.2],"q":[0,0,0,1]},"buttons":[{"clutch":"engage"},{"record":"start","task":"put the ball in the basket"}]}"#,
    )
    .await;
    let fb = wait_json(&mut page, T, |v| v["type"] == "feedback" && v["seq"] == 1)
        .await
        .unwrap();
    assert_eq!(fb["t_ns"], 1000);
    assert_eq!(fb["state"]["engaged"], true);
    assert_eq!(fb["recording"]["phase"], "recording");
    assert_eq!(h.mock.recording().task, "put the ball in the basket");

    send(
        &mut page,
        r#"{"type":"sample","seq":2,"pose":{"p":[null,0,0],"q":[0,0,0,1]}}"#,
    )
    .await;
    let e = wait_json(&mut page, T, |v| v["type"] == "error").await.unwrap();
    assert_eq!(e["seq"], 2);
    send(
        &mut page,
        r#"{"type":"sample","seq":3,"buttons":[{"record":"stop"}]}"#,
    )
    .await;
    assert!(
        h.mock.wait_for(T, |m| m.recording().episodes_saved == 1).await,
        "stop did not reach the server"
    );
    assert_eq!(h.mock.recording().phase, RecordingPhase::Idle as i32);
    let records: Vec<_> = h
        .mock
        .received()
        .iter()
        .flat_map(|r| r.sample.buttons.clone())
        .filter_map(|b| match b.event {
            Some(button_event::Event::Record(r)) => Some(r.kind()),
            _ => None,
        })
        .collect();
    assert_eq!(
        records,
        vec![record_command::Kind::Start, record_command::Kind::Stop]
    );
    assert!(h.mock.received().iter().all(|r| r.arm == "right"));

    // The page hands its arm to a headset controller's socket: `release` is taken and another socket claims the
    // arm. (The mock does not hold arms exclusively; tests/browser/test_headset.mjs hands arms over on the real
    // server.)
    assert_eq!(welcome["controllers"], serde_json::json!({}));
    send(&mut page, r#"{"type":"release"}"#).await;
    let mut controller = wss(&h, &format!("/ws?token={token}")).await;
    next_json(&mut controller, T).await.unwrap();
    send(&mut controller, r#"{"type":"hello","arm":"right"}"#).await;
    let open = wait_json(&mut controller, T, |v| v["type"] == "session")
        .await
        .unwrap();
    assert_eq!(
        (open["state"].as_str(), open["arm"].as_str()),
        (Some("open"), Some("right")),
        "the released arm was not free: {open}"
    );
    drop(controller);

    send(&mut page, r#"{"type":"hello","arm":"middle"}"#).await;
    let refused = wait_json(&mut page, T, |v| {
        v["type"] == "session" && v["state"] == "refused"
    })
    .await
    .unwrap();
    assert_eq!(refused["code"], "NotFound");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rosbridge_token_and_pages_over_https() {
    let h = start(&["main"], |c| c.rosbridge_require_token = true).await;
    let mut ws = rosbridge(&h).await;
    let e = next_json(&mut ws, T).await.unwrap();
    assert_eq!(
        (e["op"].as_str(), e["level"].as_str()),
        (Some("status"), Some("error"))
    );
    let token = h.info.token.clone().unwrap();
    let url = format!("ws://{}/?token={token}", h.info.rosbridge_addr.unwrap());
    let mut ok = plain(&url).await;
    send(&mut ok, &pose_msg("/Phone2Act/ar_pose", 0.0)).await;
    assert!(h.mock.wait_for(T, |m| !m.received().is_empty()).await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_restart_is_survived() {
    let epoch = std::time::Instant::now();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let mock =
        phone2act_gateway::mock_server::MockServer::start_on(listener, &["main"], epoch, true).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let config = phone2act_gateway::GatewayConfig {
        cert_dir: Some(dir.path().to_owned()),
        print_qr: false,
        ..Default::default()
    };
    let listeners = phone2act_gateway::Listeners {
        rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
        https: None,
    };
    let gw = phone2act_gateway::Gateway::with_listeners(config, &mock.url(), None, listeners).unwrap();
    let ws_addr = gw.info().rosbridge_addr.unwrap();
    tokio::spawn(gw.run(std::future::pending()));
    let mut ws = plain(&format!("ws://{ws_addr}/")).await;
    send(&mut ws, &pose_msg("/Phone2Act/ar_pose", 0.1)).await;
    assert!(mock.wait_for(T, |m| !m.received().is_empty()).await);
    drop(mock);
    tokio::time::sleep(Duration::from_millis(200)).await;
    // Same port, fresh server: the phone keeps publishing and the gateway reconnects by itself.
    let listener = tokio::net::TcpListener::bind(addr).await.unwrap();
    let mock =
        phone2act_gateway::mock_server::MockServer::start_on(listener, &["main"], epoch, true).unwrap();
    let ok = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            send(&mut ws, &pose_msg("/Phone2Act/ar_pose", 0.2)).await;
            if !mock.received().is_empty() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    assert!(ok.is_ok(), "gateway did not reconnect to the restarted server");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_https_rosbridge_still_refuses_addresses_that_are_not_local() {
    // Only 127.0.0.1 counts as this machine; a client bound to 127.0.0.2 plays a phone on the Wi-Fi.
    let h = start(&["main"], |c| {
        c.https = false;
        c.local_addresses = Some(vec!["127.0.0.1".parse().unwrap()]);
    })
    .await;
    let token = h.info.token.clone().expect("a token even without HTTPS");
    let addr = h.info.rosbridge_addr.unwrap();
    let connect = |query: String| async move {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind("127.0.0.2:0".parse().unwrap()).unwrap();
        let tcp = socket.connect(addr).await.unwrap();
        tokio_tungstenite::client_async(format!("ws://{addr}/{query}"), tcp)
            .await
            .unwrap()
            .0
    };
    let mut phone = connect(String::new()).await;
    send(&mut phone, &pose_msg("/Phone2Act/ar_pose", 0.01)).await;
    let refusal = next_json(&mut phone, T).await.expect("no refusal");
    assert!(
        refusal["msg"].as_str().unwrap().contains("not paired"),
        "{refusal}"
    );
    // The token in the URL admits it.
    let mut phone = connect(format!("?token={token}")).await;
    send(&mut phone, &pose_msg("/Phone2Act/ar_pose", 0.02)).await;
    assert!(
        h.mock.wait_for(T, |m| !m.received().is_empty()).await,
        "a token-bearing client was not served"
    );
    // Nothing from the refused socket reached the server.
    assert!(h.mock.received().iter().all(|r| {
        r.sample
            .tracking_from_phone
            .and_then(|p| p.position_m)
            .map(|p| p.x)
            == Some(0.02)
    }));
}

/// The in-process transport (what `phone2act serve` gives its embedded gateway): a call made before the server
/// serves waits for it instead of failing, streams and unary calls reach the same services as over TCP, and
/// once the server stopped a call fails as `Unavailable` (which a teleop link retries) instead of hanging.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_in_process_client_waits_for_its_server_and_is_refused_after_it_stopped() {
    use phone2act_proto::v1::ListArmsRequest;
    let mock = phone2act_gateway::mock_server::MockServer::start(&["main"], std::time::Instant::now(), true)
        .await
        .unwrap();
    let (client, incoming) = phone2act_sdk::Client::in_process(None).unwrap();
    let early = tokio::spawn({
        let client = client.clone();
        async move { client.system_raw().list_arms(ListArmsRequest {}).await }
    });
    // Not a timing bound: with nobody serving, the call cannot have completed however long this sleeps.
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert!(
        !early.is_finished(),
        "a call before the server serves must wait for it"
    );
    mock.serve_in_process(incoming);
    let arms = tokio::time::timeout(T, early).await.unwrap().unwrap().unwrap();
    assert_eq!(arms.into_inner().arms[0].arm, "main");

    let (events, mut events_rx) = tokio::sync::mpsc::channel(16);
    let link = client.teleop_link("main", events);
    link.send(phone2act_proto::v1::PhoneSample {
        seq: 41,
        ..Default::default()
    });
    assert!(
        mock.wait_for(T, |m| m
            .received()
            .iter()
            .any(|r| r.sample.seq == 41 && r.arm == "main"))
            .await,
        "the link's first sample reaches the server with the caller's seq"
    );
    assert!(matches!(
        tokio::time::timeout(T, events_rx.recv()).await.unwrap(),
        Some(phone2act_sdk::TeleopEvent::Open { .. })
    ));
    drop(link);

    drop(mock);
    // The server's stop reaches the client through a task of the runtime: calls in the meantime may still be
    // served; within T (seconds, against a hop of microseconds) one must be refused, and none may hang.
    let refused = tokio::time::timeout(T, async {
        loop {
            match client.system_raw().list_arms(ListArmsRequest {}).await {
                Ok(_) => tokio::time::sleep(Duration::from_millis(10)).await,
                Err(status) => return status,
            }
        }
    })
    .await
    .expect("a call after the server stopped fails instead of waiting");
    assert_eq!(refused.code(), tonic::Code::Unavailable, "{refused:?}");
}

//! Every parser fed arbitrary and mutated bytes (issue 12), on the stable toolchain with proptest: rosbridge
//! JSON and the phone page's JSON through real gateway sockets, the Dobot feedback packet and dashboard
//! replies, Feetech packets and Modbus gripper frames, the Bridge/Cameras gRPC inputs over a real server, and
//! the TOML config. Each suite asserts no panic (a process-wide panic hook counts them, including panics in
//! server tasks that would otherwise only kill a connection), no hang (every wait is bounded) and a clear
//! error (non-empty message, non-OK status). Each prints how many inputs it tried; the case counts keep every
//! suite to a few seconds in a debug build.

use futures_util::{SinkExt, StreamExt};
use phone2act_bridges::dobot::feedback::{FeedbackPacket, FrameReader, PACKET_LEN};
use phone2act_bridges::dobot::gripper::{modbus_write_register, parse_modbus_write_register};
use phone2act_bridges::dobot::protocol::{parse_reply, split_command};
use phone2act_bridges::feetech::protocol::{Decoded, decode, instruction_packet, status_packet};
use phone2act_gateway::mock_server::MockServer;
use phone2act_gateway::rosbridge as rb;
use phone2act_proto::v1::bridge_client::BridgeClient;
use phone2act_proto::v1::cameras_client::CamerasClient;
use phone2act_sdk::proto as v1;
use phone2act_server::Config;
use phone2act_tests::TestServer;
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::{Config as RunnerConfig, TestRunner};
use prost::Message as _;
use std::cell::Cell;
use std::sync::Once;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

mod common;

static PANICS: AtomicUsize = AtomicUsize::new(0);

/// Counts every panic outside this file (in a parser, a gateway or server task, on any thread), then
/// reports it as usual. This file's own assertion failures are not counted, so one failing suite does not
/// fail the others.
fn count_panics() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if info
                .location()
                .is_none_or(|l| !l.file().ends_with("fuzz_parsers.rs"))
            {
                PANICS.fetch_add(1, Ordering::SeqCst);
            }
            default(info);
        }));
    });
}

fn runner(cases: u32) -> TestRunner {
    TestRunner::new(RunnerConfig {
        cases,
        failure_persistence: None,
        ..RunnerConfig::default()
    })
}

/// A valid input with a few byte-level edits: flips, overwrites with bytes that matter to parsers (quotes,
/// braces, 0xFF, multi-byte UTF-8 lead bytes), insertions, deletions and a truncation.
fn mutated(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let interesting = prop::sample::select(vec![
        b'"', b'{', b'}', b'[', b']', b',', b':', b'\\', b'N', b'-', b'0', b'e', b';', b'(', b')', 0x00,
        0xFF, 0xFE, 0xC3, 0xE2, 0xF0, 0x80, b'\n',
    ]);
    let edit = (
        0..5u8,
        any::<prop::sample::Index>(),
        prop_oneof![interesting, any::<u8>()],
    );
    (prop::sample::select(seeds), prop::collection::vec(edit, 1..6)).prop_map(|(mut bytes, edits)| {
        for (kind, at, byte) in edits {
            if bytes.is_empty() {
                bytes.push(byte);
                continue;
            }
            let i = at.index(bytes.len());
            match kind {
                0 => bytes[i] ^= 1 << (byte % 8),
                1 => bytes[i] = byte,
                2 => bytes.insert(i, byte),
                3 => {
                    bytes.remove(i);
                }
                _ => bytes.truncate(i),
            }
        }
        bytes
    })
}

/// Arbitrary bytes, and mutations of the seeds, half each.
fn fuzz_bytes(seeds: Vec<Vec<u8>>, max_len: usize) -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![prop::collection::vec(any::<u8>(), 0..max_len), mutated(seeds)]
}

fn report(name: &str, tried: usize, started: Instant) {
    println!(
        "fuzz {name}: {tried} inputs in {:.2} s, none panicked",
        started.elapsed().as_secs_f64()
    );
    assert_eq!(PANICS.load(Ordering::SeqCst), 0, "{name}: a parser panicked");
}

// ---------------------------------------------------------------- rosbridge JSON, parser level

const APP_POSE: &str = r#"{"op":"publish","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped","msg":{"header":{"stamp":{"sec":1763726400,"nanosec":5000000},"frame_id":"phone_ar_frame"},"pose":{"position":{"x":0.01,"y":0.0,"z":-0.2},"orientation":{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}"#;
const APP_VOLUME: &str = r#"{"op":"publish","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray","msg":{"layout":{"dim":[],"data_offset":0},"data":[1,0]}}"#;
const ROSLIB_MESSAGES: [&str; 6] = [
    r#"{"op":"advertise","id":"advertise:/Phone2Act/ar_pose:1","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/msg/PoseStamped"}"#,
    r#"{"op":"subscribe","id":"subscribe:/phone2act/status:2","topic":"/phone2act/status","type":"std_msgs/String","throttle_rate":100}"#,
    r#"{"op":"unsubscribe","id":"subscribe:/phone2act/status:2","topic":"/phone2act/status"}"#,
    r#"{"op":"publish","topic":"/left/phone2act/clutch","msg":{"data":true}}"#,
    r#"{"op":"call_service","id":"c1","service":"/rosapi/topics","args":{}}"#,
    r#"{"op":"set_level","level":"error","id":"l"}"#,
];

fn rosbridge_seeds() -> Vec<Vec<u8>> {
    [APP_POSE, APP_VOLUME]
        .into_iter()
        .chain(ROSLIB_MESSAGES)
        .map(|s| s.as_bytes().to_vec())
        .collect()
}

#[test]
fn rosbridge_json_parser() {
    count_panics();
    let started = Instant::now();
    let tried = Cell::new(0usize);
    runner(8_000)
        .run(&fuzz_bytes(rosbridge_seeds(), 400), |bytes| {
            tried.set(tried.get() + 1);
            // What the socket loop hands over for a binary frame; text frames are valid UTF-8 already.
            let text = String::from_utf8_lossy(&bytes);
            match rb::parse(&text) {
                Ok(incoming) => {
                    if let rb::Op::Publish { msg, .. } = incoming.op {
                        let results = [
                            rb::parse_pose_stamped(&msg).err(),
                            rb::parse_volume(&msg).err(),
                            rb::parse_float32(&msg).err(),
                            rb::parse_bool(&msg).err(),
                        ];
                        for e in results.into_iter().flatten() {
                            prop_assert!(!e.0.is_empty());
                        }
                    }
                }
                Err((_, e)) => prop_assert!(!e.0.is_empty()),
            }
            Ok(())
        })
        .unwrap();
    report("rosbridge JSON (parser)", tried.get(), started);
}

// ---------------------------------------------------------------- both gateway sockets, end to end

struct MockGateway {
    mock: MockServer,
    info: phone2act_gateway::GatewayInfo,
    _gateway: common::RunningGateway,
}

async fn mock_gateway() -> MockGateway {
    let mock = MockServer::start(&["main"], Instant::now(), true).await.unwrap();
    // Every error goes back to the client, so the reply path is fuzzed too.
    let gateway = common::start_gateway(
        phone2act_sdk::Client::connect_lazy(&mock.url(), &phone2act_sdk::ConnectOptions::default()).unwrap(),
        |c| c.rosbridge_status_level = "info".into(),
    )
    .await;
    MockGateway {
        mock,
        info: gateway.info.clone(),
        _gateway: gateway,
    }
}

/// Frames for one socket: text (lossy UTF-8, as a browser would refuse to send invalid text) and raw binary.
fn frames(seeds: Vec<Vec<u8>>, cases: u32) -> Vec<Message> {
    let mut runner = runner(cases);
    let strategy = (fuzz_bytes(seeds, 300), any::<bool>());
    (0..cases)
        .map(|_| {
            let (bytes, binary) = strategy.new_tree(&mut runner).unwrap().current();
            if binary {
                Message::Binary(bytes.into())
            } else {
                Message::Text(String::from_utf8_lossy(&bytes).into_owned().into())
            }
        })
        .collect()
}

/// Sends every frame on `ws`, then `valid`, and checks the socket is still up and `valid` reached the mock.
async fn survive<S>(ws: &mut tokio_tungstenite::WebSocketStream<S>, frames: Vec<Message>, valid: &str)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    // Replies are drained concurrently so the gateway's bounded outgoing queue never matters.
    for frame in frames {
        ws.send(frame).await.expect("the gateway closed the socket");
        while let Ok(Some(msg)) = tokio::time::timeout(Duration::ZERO, ws.next()).await {
            assert!(msg.is_ok(), "socket error: {msg:?}");
        }
    }
    ws.send(Message::Text(valid.into())).await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rosbridge_and_page_sockets() {
    // 800 frames per socket: a few seconds in a debug build with the mock server behind.
    const CASES: u32 = 800;
    count_panics();
    let gw = mock_gateway().await;

    let started = Instant::now();
    let addr = gw.info.rosbridge_addr.unwrap();
    let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let mut ws = tokio_tungstenite::client_async(format!("ws://{addr}/"), tcp)
        .await
        .unwrap()
        .0;
    survive(&mut ws, frames(rosbridge_seeds(), CASES), APP_POSE).await;
    // The valid pose after the garbage reaches the server (bounded wait: 10 s is far above the few ms it takes).
    assert!(
        gw.mock
            .wait_for(Duration::from_secs(10), |m| m.received().iter().any(|r| {
                r.sample
                    .tracking_from_phone
                    .and_then(|p| p.position_m)
                    .is_some_and(|p| (p.z + 0.2).abs() < 1e-12)
            }))
            .await,
        "the rosbridge socket stopped working"
    );
    report("rosbridge socket", CASES as usize, started);

    let started = Instant::now();
    let page_seeds: Vec<Vec<u8>> = [
        r#"{"type":"hello","arm":"main","take_over":false}"#,
        r#"{"type":"sample","seq":7,"t_ns":123456789,"tracking":"tracking","pose":{"p":[0.0,1.4,-0.1],"q":[0,0,0,1]},"buttons":[{"clutch":"engage"},{"gripper":0.4},{"record":"start","task":"pick"}]}"#,
        r#"{"type":"sample","seq":8,"tracking":"lost","buttons":[{"gripper":"toggle"},{"record":"stop"}]}"#,
    ]
    .into_iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    let token = gw.info.token.clone().unwrap();
    let mut page = page_socket(&gw, &format!("/ws?token={token}")).await;
    survive(
        &mut page,
        frames(page_seeds, CASES),
        r#"{"type":"sample","seq":99999,"tracking":"tracking","pose":{"p":[0.0,1.4,-0.3],"q":[0,0,0,1]},"buttons":[]}"#,
    )
    .await;
    assert!(
        gw.mock
            .wait_for(Duration::from_secs(10), |m| m
                .received()
                .iter()
                .any(|r| r.sample.seq == 99_999))
            .await,
        "the page socket stopped working"
    );
    report("page socket", CASES as usize, started);
}

async fn page_socket(
    gw: &MockGateway,
    path: &str,
) -> tokio_tungstenite::WebSocketStream<tokio_rustls::client::TlsStream<tokio::net::TcpStream>> {
    let tcp = tokio::net::TcpStream::connect(gw.info.https_addr.unwrap())
        .await
        .unwrap();
    common::wss_over(&gw.info, tcp, path).await
}

// ---------------------------------------------------------------- Dobot and Feetech

#[test]
fn dobot_feedback_packets() {
    count_panics();
    let started = Instant::now();
    let valid = FeedbackPacket::default().encode();
    assert_eq!(valid.len(), PACKET_LEN);
    let tried = Cell::new(0usize);
    let strategy = prop_oneof![
        prop::collection::vec(any::<u8>(), 0..2 * PACKET_LEN),
        mutated(vec![valid.clone()]),
        // Valid packets split at arbitrary points, as TCP delivers them, with garbage in between.
        (
            prop::collection::vec(any::<u8>(), 0..64),
            any::<prop::sample::Index>()
        )
            .prop_map(move |(garbage, at)| {
                let mut bytes = valid.clone();
                let i = at.index(bytes.len());
                bytes.splice(i..i, garbage);
                bytes.extend_from_slice(&valid);
                bytes
            }),
    ];
    runner(3_000)
        .run(&strategy, |bytes| {
            tried.set(tried.get() + 1);
            if let Err(e) = FeedbackPacket::parse(&bytes) {
                prop_assert!(!e.to_string().is_empty());
            }
            let mut reader = FrameReader::default();
            for chunk in bytes.chunks(97) {
                reader.push(chunk);
                // Bounded: each call consumes input or returns None.
                for _ in 0..=bytes.len() {
                    match reader.next_packet() {
                        None => break,
                        Some(Err(e)) => prop_assert!(!e.to_string().is_empty()),
                        Some(Ok(_)) => {}
                    }
                }
                prop_assert!(reader.pending() <= bytes.len());
            }
            Ok(())
        })
        .unwrap();
    report("Dobot feedback packet", tried.get(), started);
}

#[test]
fn dobot_dashboard_replies_and_gripper_frames() {
    count_panics();
    let started = Instant::now();
    let seeds: Vec<Vec<u8>> = [
        "0,{-473.0,-141.0,469.0,-180.0,0.0,90.0},GetPose();",
        "0,{},EnableRobot();",
        "-1,{},ServoP(1,2,3,4,5,6,t=0.1);",
        "0,{{1,2},{3,4}},GetAngle();",
        "0,{5},RobotMode();",
        "ServoP(-473.0,-141.0,469.0,-180.0,0.0,90.0,t=0.03,aheadtime=50,gain=500)",
        "MovL(pose={1,2,3,4,5,6},v=50)",
    ]
    .into_iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    let tried = Cell::new(0usize);
    runner(5_000)
        .run(&fuzz_bytes(seeds, 200), |bytes| {
            tried.set(tried.get() + 1);
            let text = String::from_utf8_lossy(&bytes);
            match parse_reply(&text) {
                Ok(reply) => {
                    if let Err(e) = reply.numbers() {
                        prop_assert!(!e.to_string().is_empty());
                    }
                }
                Err(e) => prop_assert!(!e.to_string().is_empty()),
            }
            let _ = split_command(&text);
            Ok(())
        })
        .unwrap();
    report("Dobot dashboard replies", tried.get(), started);

    let started = Instant::now();
    let frames = vec![
        modbus_write_register(1, 0x0103, 0).to_vec(),
        modbus_write_register(1, 0x0103, 1000).to_vec(),
    ];
    let tried = Cell::new(0usize);
    runner(10_000)
        .run(&fuzz_bytes(frames, 16), |bytes| {
            tried.set(tried.get() + 1);
            let _ = parse_modbus_write_register(&bytes);
            Ok(())
        })
        .unwrap();
    report("Dobot gripper Modbus frame", tried.get(), started);
}

#[test]
fn feetech_packets() {
    count_panics();
    let started = Instant::now();
    let seeds = vec![
        instruction_packet(1, 0x02, &[0x38, 0x02]).unwrap(),
        status_packet(3, 0, &[0x00, 0x08]),
        status_packet(6, 0x20, &[]),
        [status_packet(1, 0, &[1, 2]), status_packet(2, 0, &[3, 4])].concat(),
    ];
    let tried = Cell::new(0usize);
    runner(10_000)
        .run(&fuzz_bytes(seeds, 64), |bytes| {
            tried.set(tried.get() + 1);
            // Drain the buffer as the bus reader does: every step must make progress or stop.
            let mut buf = bytes.as_slice();
            for _ in 0..=bytes.len() {
                match decode(buf) {
                    Decoded::Packet(_, used) | Decoded::Error(_, used) => {
                        prop_assert!(used >= 1 && used <= buf.len(), "used {} of {}", used, buf.len());
                        buf = &buf[used..];
                    }
                    Decoded::Incomplete(garbage) => {
                        prop_assert!(garbage <= buf.len());
                        break;
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    report("Feetech packets", tried.get(), started);
}

// ---------------------------------------------------------------- TOML config

#[test]
fn toml_config() {
    count_panics();
    let started = Instant::now();
    let reference = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../server/config/reference.toml"
    ))
    .unwrap();
    let seeds = vec![
        phone2act_server::config::EMBEDDED_DEFAULT.as_bytes().to_vec(),
        reference,
        b"[[arms]]\nname = \"main\"\nbridge = \"sim\"\n[arms.teleop.gate]\nstale_timeout_s = 0.3\n".to_vec(),
    ];
    let tried = Cell::new(0usize);
    runner(5_000)
        .run(&fuzz_bytes(seeds, 300), |bytes| {
            tried.set(tried.get() + 1);
            let text = String::from_utf8_lossy(&bytes);
            if let Err(e) = Config::from_toml_str(&text, "fuzz.toml", Vec::new()) {
                prop_assert!(!e.to_string().is_empty());
            }
            Ok(())
        })
        .unwrap();
    report("TOML config", tried.get(), started);
}

// ---------------------------------------------------------------- Cameras.Push and Bridge.Attach over gRPC

fn float() -> impl Strategy<Value = f64> {
    prop_oneof![
        -2.0..2.0f64,
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(-1e308),
        any::<f64>()
    ]
}

fn camera_frame() -> impl Strategy<Value = v1::CameraFrame> {
    let valid = v1::CameraFrame {
        camera: "pushed".into(),
        width: 64,
        height: 64,
        encoding: v1::ImageEncoding::Rgb8 as i32,
        data: vec![7; 64 * 64 * 3],
        capture_time_ns: 1,
        frame_seq: 1,
    }
    .encode_to_vec();
    let typed = (
        prop::sample::select(vec!["pushed", "", "nope", "pushed\u{e9}"]),
        prop_oneof![Just(64u32), 0..100u32, Just(u32::MAX)],
        prop_oneof![Just(64u32), 0..100u32, Just(u32::MAX)],
        -1..8i32,
        prop_oneof![
            Just(vec![3u8; 64 * 64 * 3]),
            prop::collection::vec(any::<u8>(), 0..2000)
        ],
        any::<i64>(),
        any::<u64>(),
    )
        .prop_map(
            |(camera, width, height, encoding, data, capture_time_ns, frame_seq)| v1::CameraFrame {
                camera: camera.into(),
                width,
                height,
                encoding,
                data,
                capture_time_ns,
                frame_seq,
            },
        );
    // Mutated wire bytes that still decode as a frame (the server never sees bytes prost refuses).
    let from_bytes = mutated(vec![valid]).prop_filter_map("not a CameraFrame", |b| {
        v1::CameraFrame::decode(b.as_slice()).ok()
    });
    prop_oneof![typed, from_bytes]
}

fn bridge_message() -> impl Strategy<Value = v1::BridgeUpstream> {
    use v1::bridge_upstream::Message as M;
    let pose = (prop::array::uniform3(float()), prop::array::uniform4(float()))
        .prop_map(|(p, q)| v1::Pose::from_parts(p, q));
    let message = prop_oneof![
        (
            prop::sample::select(vec!["ext", "", "nope"]),
            prop::collection::vec(prop::sample::select(vec!["a", "b", "c", "", "d"]), 0..5),
            any::<bool>()
        )
            .prop_map(|(arm, joints, orientation)| M::Hello(v1::BridgeHello {
                arm: arm.into(),
                bridge_name: "fuzz".into(),
                joint_names: joints.into_iter().map(str::to_owned).collect(),
                supports_orientation: orientation,
                ..v1::BridgeHello::default()
            })),
        (
            any::<i64>(),
            prop::collection::vec(float(), 0..6),
            prop::option::of(pose),
            float(),
            any::<u64>()
        )
            .prop_map(|(t, joints, pose, gripper, seq)| M::Feedback(v1::RobotFeedback {
                capture_time_ns: t,
                joint_positions_rad: joints,
                robot_from_ee: pose,
                gripper_position: gripper,
                applied_seq: seq,
            })),
        (
            -1..6i32,
            prop::collection::vec(any::<char>(), 0..40).prop_map(String::from_iter)
        )
            .prop_map(|(health, message)| M::Status(v1::BridgeStatusReport { health, message })),
    ];
    prop::option::weighted(0.95, message).prop_map(|message| v1::BridgeUpstream { message })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cameras_push_and_bridge_attach_over_grpc() {
    count_panics();
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(phone2act_tests::remote_config(dir.path()))
        .await
        .unwrap();
    let channel = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();

    // One call per case: a thousand keep each suite to a few seconds against a debug server.
    let started = Instant::now();
    let mut cameras = CamerasClient::new(channel.clone());
    let mut runner = runner(1_000);
    let strategy = prop::collection::vec(camera_frame(), 1..4);
    let mut frames_tried = 0;
    for _ in 0..1_000 {
        let batch = strategy.new_tree(&mut runner).unwrap().current();
        frames_tried += batch.len();
        let call = cameras.push(tokio_stream::iter(batch));
        match tokio::time::timeout(Duration::from_secs(10), call).await {
            Ok(Ok(summary)) => assert_eq!(summary.into_inner().camera, "pushed"),
            Ok(Err(status)) => assert!(!status.message().is_empty(), "{status:?}"),
            Err(elapsed) => panic!("Cameras.Push hung ({elapsed})"),
        }
    }
    let ok = v1::CameraFrame {
        camera: "pushed".into(),
        width: 64,
        height: 64,
        encoding: v1::ImageEncoding::Rgb8 as i32,
        data: vec![1; 64 * 64 * 3],
        capture_time_ns: 0,
        frame_seq: 1_000_000,
    };
    let summary = cameras.push(tokio_stream::iter(vec![ok])).await.unwrap();
    assert_eq!(
        summary.into_inner().frames_accepted,
        1,
        "the camera stopped working"
    );
    report("Cameras.Push", frames_tried, started);

    let started = Instant::now();
    let mut bridge = BridgeClient::new(channel);
    let strategy = prop::collection::vec(bridge_message(), 1..6);
    let mut messages_tried = 0;
    for _ in 0..1_000 {
        let batch = strategy.new_tree(&mut runner).unwrap().current();
        messages_tried += batch.len();
        // The request stream ends after the batch: the server must end the call, whatever it was sent.
        let call = async {
            match bridge.attach(tokio_stream::iter(batch)).await {
                Ok(response) => {
                    let mut inbound = response.into_inner();
                    loop {
                        match inbound.message().await {
                            Ok(Some(_)) => {}
                            Ok(None) => return None,
                            Err(status) => return Some(status),
                        }
                    }
                }
                Err(status) => Some(status),
            }
        };
        match tokio::time::timeout(Duration::from_secs(10), call).await {
            Ok(Some(status)) => assert!(!status.message().is_empty(), "{status:?}"),
            Ok(None) => {}
            Err(elapsed) => panic!("Bridge.Attach did not end after its request stream did ({elapsed})"),
        }
    }
    let client = server.client().await.unwrap();
    assert_eq!(client.system().list_arms().await.unwrap().len(), 1);
    report("Bridge.Attach", messages_tried, started);
    server.shutdown().await.unwrap();
}

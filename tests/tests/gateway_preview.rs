//! Camera images through the gateway in front of the real server with its sim camera.
//!
//! The phone page's preview (issue 18): off until a socket asks, only that socket gets frames, at most
//! `max_fps` of them, one in flight until the page acknowledges it, a clear error for an unknown camera, and
//! the control session unharmed. rosbridge's image topics: images keep coming while the same socket drives
//! the arm, and none follows the unsubscribe. An ignored benchmark prints the rosbridge socket's round trip
//! with an image topic subscribed, its images fetched on the video runtime or on the control path's.

use futures_util::{SinkExt, StreamExt};
use phone2act_tests::{TestServer, default_config};
use serde_json::Value;
use std::time::{Duration, Instant};
use tokio::net::TcpStream;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;

mod common;
use common::RunningGateway;

type Page = WebSocketStream<tokio_rustls::client::TlsStream<TcpStream>>;

/// Generous for a first frame on a loaded 2-core machine: a camera list, one observation and a JPEG
/// decode/encode in a debug build take well under a second there.
const FIRST_FRAME: Duration = Duration::from_secs(10);

async fn page(gw: &RunningGateway) -> Page {
    let tcp = TcpStream::connect(gw.info.https_addr.unwrap()).await.unwrap();
    let token = gw.info.token.clone().unwrap();
    common::wss_over(&gw.info, tcp, &format!("/ws?token={token}")).await
}

async fn send(ws: &mut Page, text: &str) {
    ws.send(Message::Text(text.into())).await.unwrap();
}

/// What one page socket received during a read.
#[derive(Default)]
struct Received {
    texts: Vec<Value>,
    frames: Vec<(Instant, Vec<u8>)>,
}

impl Received {
    fn of_type(&self, kind: &str) -> Vec<&Value> {
        self.texts.iter().filter(|v| v["type"] == kind).collect()
    }
}

/// Reads `ws` for `window` (or until `until` holds), acknowledging each preview frame if `ack`.
async fn read(
    ws: &mut Page,
    window: Duration,
    ack: bool,
    mut until: impl FnMut(&Received) -> bool,
) -> Received {
    let mut got = Received::default();
    let deadline = tokio::time::Instant::now() + window;
    while !until(&got) {
        let Ok(Some(Ok(msg))) = tokio::time::timeout_at(deadline, ws.next()).await else {
            break;
        };
        match msg {
            Message::Text(t) => got.texts.push(serde_json::from_str(t.as_str()).unwrap()),
            Message::Binary(b) => {
                got.frames.push((Instant::now(), b.to_vec()));
                if ack {
                    send(ws, r#"{"type":"preview_ack"}"#).await;
                }
            }
            _ => {}
        }
    }
    got
}

fn sample(seq: u64) -> String {
    format!(
        r#"{{"type":"sample","seq":{seq},"t_ns":{},"tracking":"tracking","pose":{{"p":[0.0,1.4,0.0],"q":[0,0,0,1]}}}}"#,
        seq * 16_000_000
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_asking_socket_gets_preview_frames_at_most_max_fps() {
    let dir = tempfile::tempdir().unwrap();
    // The test camera is 320x240 at 15 fps.
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let gw = common::start_gateway(server.in_process_client(None), |_| {}).await;

    // A control session that never asks for the preview.
    let mut quiet = page(&gw).await;
    let welcome = read(&mut quiet, FIRST_FRAME, false, |r| {
        !r.of_type("welcome").is_empty()
    })
    .await;
    assert_eq!(
        welcome.of_type("welcome")[0]["cameras"],
        serde_json::json!(["front"]),
        "the page is told the cameras"
    );
    send(&mut quiet, r#"{"type":"hello","arm":"main"}"#).await;

    let mut viewer = page(&gw).await;
    send(
        &mut viewer,
        r#"{"type":"preview","camera":"front","max_fps":2,"width":160}"#,
    )
    .await;
    let first = read(&mut viewer, FIRST_FRAME, true, |r| !r.frames.is_empty()).await;
    let on = first.of_type("preview");
    assert_eq!(on.len(), 1, "{:?}", first.texts);
    assert_eq!(on[0]["state"], "on");
    assert_eq!(on[0]["width"], 160);
    assert_eq!(first.frames.len(), 1, "no preview frame: {:?}", first.texts);
    let frame = phone2act_capture::jpeg::decode_jpeg(&first.frames[0].1).unwrap();
    // 320x240 shrunk to fit 160 px: half of each side, the camera's aspect kept.
    assert_eq!((frame.width, frame.height), (160, 120));

    // Throttle: the gateway fetches at most once per 1/max_fps (a tokio interval that delays, never bursts,
    // after a late tick), so a window of W seconds holds at most 1 + W * max_fps frames however loaded the
    // machine is; only the upper bound is checked (a loaded machine may deliver fewer).
    let window = Duration::from_secs(3);
    let mut seq = 0;
    let later = {
        let reading = read(&mut viewer, window, true, |_| false);
        let driving = async {
            // The quiet socket drives meanwhile, at the page's rate.
            let until = Instant::now() + window;
            while Instant::now() < until {
                seq += 1;
                send(&mut quiet, &sample(seq)).await;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        };
        tokio::join!(reading, driving).0
    };
    let frames = later.frames.len();
    println!(
        "preview: {frames} frames in 3 s at max_fps 2 (bound {})",
        1 + 3 * 2
    );
    assert!(frames <= 1 + 3 * 2, "{frames} frames in 3 s at max_fps 2");
    assert!(frames >= 1, "the preview stopped");

    let quiet_got = read(&mut quiet, Duration::from_millis(500), false, |_| false).await;
    assert!(
        quiet_got.frames.is_empty(),
        "a socket that did not ask got frames"
    );
    assert!(quiet_got.of_type("preview").is_empty(), "{:?}", quiet_got.texts);
    assert!(
        !quiet_got.of_type("feedback").is_empty(),
        "the control session got no feedback"
    );

    // Off: the gateway confirms, and nothing follows its confirmation (a frame already on the link may
    // precede it; the slot refuses frames of a stopped preview).
    send(&mut viewer, r#"{"type":"preview_off"}"#).await;
    let off = read(&mut viewer, FIRST_FRAME, true, |r| {
        !r.of_type("preview").is_empty()
    })
    .await;
    assert_eq!(off.of_type("preview")[0]["state"], "off");
    let after = read(&mut viewer, Duration::from_millis(1500), true, |_| false).await;
    assert!(
        after.frames.is_empty(),
        "{} frames after preview_off",
        after.frames.len()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_page_that_does_not_acknowledge_gets_one_frame_and_no_queue() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let gw = common::start_gateway(server.in_process_client(None), |_| {}).await;
    let mut viewer = page(&gw).await;
    send(&mut viewer, r#"{"type":"preview","camera":"front","max_fps":10}"#).await;
    let first = read(&mut viewer, FIRST_FRAME, false, |r| !r.frames.is_empty()).await;
    assert_eq!(first.frames.len(), 1, "no preview frame: {:?}", first.texts);
    // A stalled reader (a slow link) is not sent more: 10 periods at 10 fps pass without a second frame,
    // whatever the load, because the gateway waits for the acknowledgement.
    let stalled = read(&mut viewer, Duration::from_secs(1), false, |_| false).await;
    assert!(
        stalled.frames.is_empty(),
        "{} frames without an ack",
        stalled.frames.len()
    );
    send(&mut viewer, r#"{"type":"preview_ack"}"#).await;
    let resumed = read(&mut viewer, FIRST_FRAME, false, |r| !r.frames.is_empty()).await;
    assert_eq!(resumed.frames.len(), 1, "the ack did not resume the preview");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unknown_camera_is_an_error_and_the_session_carries_on() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let gw = common::start_gateway(server.in_process_client(None), |_| {}).await;
    let mut p = page(&gw).await;
    send(&mut p, r#"{"type":"hello","arm":"main"}"#).await;
    send(&mut p, r#"{"type":"preview","camera":"rear"}"#).await;
    let got = read(&mut p, FIRST_FRAME, true, |r| !r.of_type("preview").is_empty()).await;
    let errors = got.of_type("error");
    assert_eq!(errors.len(), 1, "{:?}", got.texts);
    let message = errors[0]["message"].as_str().unwrap();
    assert!(
        message.contains("unknown camera \"rear\"") && message.contains("front"),
        "{message}"
    );
    assert_eq!(got.of_type("preview")[0]["state"], "off");
    // Out-of-range settings are refused the same way.
    send(&mut p, r#"{"type":"preview","camera":"front","max_fps":60}"#).await;
    let bad = read(&mut p, FIRST_FRAME, true, |r| !r.of_type("error").is_empty()).await;
    assert!(
        bad.of_type("error")[0]["message"]
            .as_str()
            .unwrap()
            .contains("max_fps"),
        "{:?}",
        bad.texts
    );
    // The control session carries on: samples still get feedback echoing their seq.
    for seq in 1..=5 {
        send(&mut p, &sample(seq)).await;
    }
    let fb = read(&mut p, FIRST_FRAME, true, |r| {
        r.of_type("feedback").iter().any(|f| f["seq"] == 5)
    })
    .await;
    assert!(
        fb.of_type("feedback").iter().any(|f| f["seq"] == 5),
        "no feedback after the refused previews: {:?}",
        fb.texts
    );
    assert!(fb.frames.is_empty(), "frames from a refused preview");
}

type Ros = WebSocketStream<TcpStream>;

const IMAGE_TOPIC: &str = "/cameras/front/image/compressed";

async fn rosbridge(gw: &RunningGateway) -> Ros {
    let addr = gw.info.rosbridge_addr.unwrap();
    let tcp = TcpStream::connect(addr).await.unwrap();
    tcp.set_nodelay(true).unwrap();
    tokio_tungstenite::client_async(format!("ws://{addr}/"), tcp)
        .await
        .unwrap()
        .0
}

/// The app's AR pose publish on the default arm's topic.
fn app_pose(stamp_ns: i64, p: [f64; 3]) -> String {
    format!(
        r#"{{"op":"publish","topic":"/Phone2Act/ar_pose","type":"geometry_msgs/PoseStamped","msg":{{"header":{{"stamp":{{"sec":{},"nanosec":{}}},"frame_id":"phone_ar_frame"}},"pose":{{"position":{{"x":{:?},"y":{:?},"z":{:?}}},"orientation":{{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}}}}}"#,
        stamp_ns / 1_000_000_000,
        stamp_ns % 1_000_000_000,
        p[0],
        p[1],
        p[2]
    )
}

fn get_time(id: u64) -> String {
    format!(r#"{{"op":"call_service","id":"t:{id}","service":"/rosapi/get_time"}}"#)
}

/// What one rosbridge socket received: the image topic's JPEGs and the ids of the service answers, in order.
#[derive(Default)]
struct RosReceived {
    images: Vec<Vec<u8>>,
    answers: Vec<String>,
    /// For each answer, how many images had arrived before it.
    images_before_answer: Vec<usize>,
}

/// Reads `rx` into `got` until the socket closes.
async fn read_ros(
    mut rx: futures_util::stream::SplitStream<Ros>,
    got: std::sync::Arc<parking_lot::Mutex<RosReceived>>,
) {
    use base64::Engine as _;
    while let Some(Ok(msg)) = rx.next().await {
        let Message::Text(text) = msg else { continue };
        let v: Value = serde_json::from_str(text.as_str()).unwrap();
        let mut got = got.lock();
        match v["op"].as_str() {
            Some("publish") if v["topic"] == IMAGE_TOPIC => {
                assert_eq!(v["msg"]["format"], "jpeg");
                let data = v["msg"]["data"].as_str().unwrap();
                let jpeg = base64::engine::general_purpose::STANDARD.decode(data).unwrap();
                got.images.push(jpeg);
            }
            Some("service_response") => {
                let n = got.images.len();
                got.images_before_answer.push(n);
                got.answers.push(v["id"].as_str().unwrap_or_default().to_owned());
            }
            _ => {}
        }
    }
}

/// The Phone2Act app on one rosbridge socket: a pose on the default arm's topic every 20 ms (its 50 Hz), and a
/// `/rosapi/get_time` call after every 5th.
struct App {
    tx: futures_util::stream::SplitSink<Ros, Message>,
    tick: tokio::time::Interval,
    stamp_ns: i64,
    poses: u64,
    calls: u64,
}

impl App {
    fn new(tx: futures_util::stream::SplitSink<Ros, Message>) -> Self {
        Self {
            tx,
            tick: tokio::time::interval(Duration::from_millis(20)),
            stamp_ns: 1_763_726_400_000_000_000,
            poses: 0,
            calls: 0,
        }
    }

    async fn send(&mut self, text: String) {
        self.tx.send(Message::Text(text.into())).await.unwrap();
    }

    async fn pose(&mut self, p: [f64; 3]) {
        self.tick.tick().await;
        self.stamp_ns += 20_000_000;
        self.poses += 1;
        self.send(app_pose(self.stamp_ns, p)).await;
        if self.poses.is_multiple_of(5) {
            self.calls += 1;
            self.send(get_time(self.calls)).await;
        }
    }
}

fn target_of(state: &phone2act_proto::v1::ArmState) -> [f64; 3] {
    phone2act_tests::pos(state.robot_from_target.as_ref().unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rosbridge_image_topic_keeps_coming_while_the_same_socket_drives_the_arm() {
    let dir = tempfile::tempdir().unwrap();
    // The test camera is 320x240 at 15 fps.
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    let gw = common::start_gateway(server.in_process_client(None), |_| {}).await;
    let (tx, rx) = rosbridge(&gw).await.split();
    let got = std::sync::Arc::new(parking_lot::Mutex::new(RosReceived::default()));
    let reader = tokio::spawn(read_ros(rx, got.clone()));
    let images = || got.lock().images.len();
    let mut app = App::new(tx);

    app.send(format!(
        r#"{{"op":"subscribe","id":"img:1","topic":"{IMAGE_TOPIC}","type":"sensor_msgs/CompressedImage"}}"#
    ))
    .await;
    let first = phone2act_tests::wait_until(FIRST_FRAME, || async { images() > 0 }).await;
    assert!(first, "no image on {IMAGE_TOPIC}");
    for _ in 0..5 {
        app.pose([0.0; 3]).await;
    }
    // The app's volume state [0, 0]: follow.
    app.send(
        r#"{"op":"publish","topic":"/Phone2Act/volume","type":"std_msgs/msg/Int32MultiArray","msg":{"layout":{"dim":[],"data_offset":0},"data":[0,0]}}"#.into(),
    )
    .await;
    // Poses go on while waiting (at most 10 s: the server engages at its next tick, a loaded machine delays it).
    let mut engaged = false;
    for _ in 0..500 {
        app.pose([0.0; 3]).await;
        if phone2act_tests::arm_state(&client, "main").await.engaged {
            engaged = true;
            break;
        }
    }
    assert!(engaged, "[0, 0] did not engage the arm");
    let start = target_of(&phone2act_tests::arm_state(&client, "main").await);
    let images_before_move = images();
    // 8 cm forward (-Z) in 5 mm steps, then held until the target is there and 3 more images came meanwhile:
    // at most 20 s of holding (a loaded 2-core machine slows the sim and the camera, it does not stop them).
    for i in 1..=16 {
        app.pose([0.0, 0.0, -0.005 * f64::from(i)]).await;
    }
    let mut moved_m = 0.0;
    for _ in 0..1000 {
        app.pose([0.0, 0.0, -0.08]).await;
        let target = target_of(&phone2act_tests::arm_state(&client, "main").await);
        moved_m = (0..3).map(|k| (target[k] - start[k]).powi(2)).sum::<f64>().sqrt();
        if (moved_m - 0.08).abs() < 0.005 && images() >= images_before_move + 3 {
            break;
        }
    }
    assert!(
        (moved_m - 0.08).abs() < 0.005,
        "target moved {moved_m} m for an 8 cm phone move with an image topic subscribed"
    );
    assert!(
        images() >= images_before_move + 3,
        "images stopped while the app drove: {images_before_move} before the move, {} after",
        images()
    );
    for jpeg in &got.lock().images {
        let frame = phone2act_capture::jpeg::decode_jpeg(jpeg).unwrap();
        assert_eq!((frame.width, frame.height), (320, 240));
    }
    // Every service call was answered, in order, between the images.
    let calls = app.calls;
    let answered = |n: u64| {
        let got = got.clone();
        move || {
            let got = got.clone();
            async move { got.lock().answers.len() as u64 >= n }
        }
    };
    assert!(
        phone2act_tests::wait_until(FIRST_FRAME, answered(calls)).await,
        "{} of {calls} service calls answered",
        got.lock().answers.len()
    );
    let expected: Vec<String> = (1..=calls).map(|i| format!("t:{i}")).collect();
    assert_eq!(got.lock().answers, expected);

    // Unsubscribed: no image follows the answer to a call made after the unsubscribe (an image already on the
    // socket comes before it; a fetch still running is refused).
    app.send(format!(
        r#"{{"op":"unsubscribe","id":"img:1","topic":"{IMAGE_TOPIC}"}}"#
    ))
    .await;
    app.calls += 1;
    app.send(get_time(app.calls)).await;
    assert!(
        phone2act_tests::wait_until(FIRST_FRAME, answered(app.calls)).await,
        "the call after the unsubscribe was not answered"
    );
    let images_at_answer = *got.lock().images_before_answer.last().unwrap();
    // Five times the image period (100 ms): a poller left running would have published meanwhile.
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(images(), images_at_answer, "images after the unsubscribe");
    drop(app);
    reader.abort();
}

/// Where a benchmarked gateway runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Deploy {
    /// As `phone2act-gateway`: its own thread and single-threaded runtime, the server over loopback TCP.
    Standalone,
    /// As `phone2act serve` embeds it: on the server's runtime, the server in-process.
    Embedded,
}

/// A gateway serving rosbridge only, until dropped.
struct BenchGateway {
    addr: std::net::SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    _dir: tempfile::TempDir,
}

impl Drop for BenchGateway {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Runs `f`'s future on a new thread with a single-threaded runtime of its own, as a separate process would.
fn on_own_thread<T, F>(f: impl FnOnce() -> F + Send + 'static) -> std::thread::JoinHandle<T>
where
    T: Send + 'static,
    F: std::future::Future<Output = T>,
{
    std::thread::spawn(move || {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap()
            .block_on(f())
    })
}

/// Starts a rosbridge-only gateway; with `images_on_control`, its image fetches run on its control runtime.
async fn bench_gateway(server: &TestServer, deploy: Deploy, images_on_control: bool) -> BenchGateway {
    use phone2act_gateway::{Gateway, GatewayConfig, Listeners};
    let dir = tempfile::tempdir().unwrap();
    let config = GatewayConfig {
        cert_dir: Some(dir.path().to_owned()),
        print_qr: false,
        public_host: Some("127.0.0.1".into()),
        ..GatewayConfig::default()
    };
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let start = move |mut gateway: Gateway| {
        if images_on_control {
            gateway.fetch_images_on_control_runtime();
        }
        let addr = gateway.info().rosbridge_addr.unwrap();
        (
            addr,
            gateway.run(async {
                let _ = stopped.await;
            }),
        )
    };
    match deploy {
        Deploy::Embedded => {
            let listeners = Listeners {
                rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
                https: None,
            };
            let gateway = Gateway::with_client(config, server.in_process_client(None), listeners).unwrap();
            let (addr, run) = start(gateway);
            tokio::spawn(run);
            BenchGateway {
                addr,
                stop: Some(stop),
                thread: None,
                _dir: dir,
            }
        }
        Deploy::Standalone => {
            let url = server.url();
            let (addr_tx, addr_rx) = std::sync::mpsc::channel();
            let thread = on_own_thread(move || async move {
                let listeners = Listeners {
                    rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap()),
                    https: None,
                };
                let gateway = Gateway::with_listeners(config, &url, None, listeners).unwrap();
                let (addr, run) = start(gateway);
                addr_tx.send(addr).unwrap();
                let _ = run.await;
            });
            BenchGateway {
                addr: addr_rx.recv().unwrap(),
                stop: Some(stop),
                thread: Some(thread),
                _dir: dir,
            }
        }
    }
}

/// One benchmark row: a socket to its gateway, and whether it subscribes to the image topic.
struct Row {
    name: String,
    ws: Ros,
    images: bool,
    round_trips_ns: Vec<u64>,
    images_seen: usize,
    calls: u64,
}

impl Row {
    /// Sends a `get_time` call and reads until its answer; returns the round trip, counting images meanwhile.
    async fn call(&mut self) -> u64 {
        self.calls += 1;
        let id = format!("t:{}", self.calls);
        let sent = Instant::now();
        self.ws
            .send(Message::Text(get_time(self.calls).into()))
            .await
            .unwrap();
        loop {
            let Message::Text(text) = self.ws.next().await.unwrap().unwrap() else {
                continue;
            };
            let v: Value = serde_json::from_str(text.as_str()).unwrap();
            if v["op"] == "service_response" && v["id"] == id.as_str() {
                return sent.elapsed().as_nanos() as u64;
            }
            if v["topic"] == IMAGE_TOPIC {
                self.images_seen += 1;
            }
        }
    }

    /// One slice: subscribe (image rows) and wait for the first image, then `calls` round trips 20 ms apart
    /// (the app's 50 Hz), then unsubscribe and drain.
    async fn slice(&mut self, calls: usize) {
        if self.images {
            let sub = format!(
                r#"{{"op":"subscribe","id":"img:1","topic":"{IMAGE_TOPIC}","type":"sensor_msgs/CompressedImage"}}"#
            );
            self.ws.send(Message::Text(sub.into())).await.unwrap();
            let seen = self.images_seen;
            while self.images_seen == seen {
                self.call().await;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        let mut tick = tokio::time::interval(Duration::from_millis(20));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        for _ in 0..calls {
            tick.tick().await;
            let rtt = self.call().await;
            self.round_trips_ns.push(rtt);
        }
        if self.images {
            let unsub = format!(r#"{{"op":"unsubscribe","id":"img:1","topic":"{IMAGE_TOPIC}"}}"#);
            self.ws.send(Message::Text(unsub.into())).await.unwrap();
            // The answer to a call after the unsubscribe comes after its last image.
            self.call().await;
        }
    }
}

fn percentile_ms(sorted: &[u64], p: f64) -> f64 {
    let idx = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[idx] as f64 / 1e6
}

/// The rosbridge socket's round trip (a `/rosapi/get_time` call, answered on the gateway's control runtime)
/// with the camera topic subscribed, its images fetched and encoded on the video runtime (as shipped) or on
/// the control runtime (as before the video runtime took them), and with no image topic; each for the
/// standalone and the embedded gateway. Rows alternate in slices of 1.5 s for 10 rounds, so every row sees
/// the same load; one image subscription at a time. The shipped camera (640x480 at 30 fps, sim render).
///
/// `cargo test -p phone2act-tests --test gateway_preview -- --ignored --nocapture round_trip`
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "benchmark: prints the round trips; run with --ignored --nocapture"]
async fn rosbridge_round_trip_with_an_image_topic_on_the_video_or_the_control_runtime() {
    const ROUNDS: usize = 10;
    const CALLS_PER_SLICE: usize = 75;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(phone2act_tests::embedded_default(dir.path()))
        .await
        .unwrap();
    let mut gateways = Vec::new();
    let mut rows = Vec::new();
    for deploy in [Deploy::Standalone, Deploy::Embedded] {
        let video = bench_gateway(&server, deploy, false).await;
        let control = bench_gateway(&server, deploy, true).await;
        for (what, addr, images) in [
            ("no image topic", video.addr, false),
            ("images on control runtime", control.addr, true),
            ("images on video runtime", video.addr, true),
        ] {
            rows.push((format!("{deploy:?}, {what}"), addr, images));
        }
        gateways.push(video);
        gateways.push(control);
    }
    // The client on a thread and runtime of its own, like a phone: it takes no CPU from the gateway's runtime.
    let client = on_own_thread(move || async move {
        let mut measured = Vec::new();
        for (name, addr, images) in rows {
            let tcp = TcpStream::connect(addr).await.unwrap();
            tcp.set_nodelay(true).unwrap();
            let ws = tokio_tungstenite::client_async(format!("ws://{addr}/"), tcp)
                .await
                .unwrap()
                .0;
            measured.push(Row {
                name,
                ws,
                images,
                round_trips_ns: Vec::new(),
                images_seen: 0,
                calls: 0,
            });
        }
        for _ in 0..ROUNDS {
            for row in &mut measured {
                row.slice(CALLS_PER_SLICE).await;
            }
        }
        measured
    });
    let measured = tokio::task::spawn_blocking(move || client.join().unwrap())
        .await
        .unwrap();
    println!(
        "rosbridge get_time round trip, {ROUNDS} rounds x {CALLS_PER_SLICE} calls per row, release={}",
        !cfg!(debug_assertions)
    );
    println!(
        "{:<42} {:>6} {:>8} {:>8} {:>8} {:>8} {:>7}",
        "row", "calls", "p50 ms", "p95 ms", "p99 ms", "max ms", "images"
    );
    for row in measured {
        let mut rtt = row.round_trips_ns;
        rtt.sort_unstable();
        println!(
            "{:<42} {:>6} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>7}",
            row.name,
            rtt.len(),
            percentile_ms(&rtt, 0.50),
            percentile_ms(&rtt, 0.95),
            percentile_ms(&rtt, 0.99),
            percentile_ms(&rtt, 1.0),
            row.images_seen
        );
        if row.images {
            assert!(row.images_seen > 0, "{}: no image arrived", row.name);
        }
    }
    drop(gateways);
}

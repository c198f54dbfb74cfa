//! The phone page's camera preview (issue 18) through the gateway in front of the real server with its sim
//! camera: off until a socket asks, only that socket gets frames, at most `max_fps` of them, one in flight
//! until the page acknowledges it, a clear error for an unknown camera, and the control session unharmed.

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
    let frame = phone2act_recorder::jpeg::decode_jpeg(&first.frames[0].1).unwrap();
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

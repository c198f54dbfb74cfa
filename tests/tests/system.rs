//! The System service end to end: a real server on an ephemeral port, the real SDK over TCP.

use phone2act_tests::TestServer;
use std::time::{Duration, Instant};
use tokio_stream::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lists_the_main_arm_and_its_camera_and_streams_status() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start_default(dir.path()).await.unwrap();
    let client = server.client().await.unwrap();
    let mut system = client.system();

    let arms = system.list_arms().await.unwrap();
    assert_eq!(arms.len(), 1);
    assert_eq!(arms[0].arm, "main");
    assert_eq!(arms[0].bridge_kind, "sim");

    let cameras = system.list_cameras().await.unwrap();
    assert_eq!(cameras.len(), 1);
    assert_eq!(cameras[0].kind, "sim_render");
    assert_eq!((cameras[0].width, cameras[0].height), (640, 480));

    let mut watch = system.watch_status(0.02).await.unwrap();
    let first = watch.next().await.unwrap().unwrap();
    let second = watch.next().await.unwrap().unwrap();
    assert_eq!(second.sequence, first.sequence + 1);
    assert!(
        second.server_time_ns > first.server_time_ns,
        "snapshots must advance in time"
    );
    assert_eq!(second.arms[0].arm, "main");
    // The first 640x480 frame of a debug build can take a while on a loaded machine: poll for it. One frame,
    // not two: with nobody reading it, the camera may park after its first frame (see the next test).
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let status = watch.next().await.unwrap().unwrap();
        if status.cameras[0].frames_captured >= 1 && status.cameras[0].live {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the synthetic camera produced no frames"
        );
    }

    let started = Instant::now();
    server.shutdown().await.unwrap();
    assert!(
        started.elapsed() < Duration::from_secs(1),
        "shutdown took {:?}",
        started.elapsed()
    );
}

/// An idle server draws nothing: the rendered camera parks once nobody has read it for 2 s (status watchers
/// do not count), reports itself live, and the next observation wakes it and gets a frame drawn after the
/// request, never one from before the park.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unread_camera_parks_and_an_observation_wakes_it() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start_default(dir.path()).await.unwrap();
    let client = server.client().await.unwrap();
    let mut watch = client.system().watch_status(0.05).await.unwrap();

    // Parked: the count stands still for 1 s (30 frames at the camera's 30 fps). The park comes 2 s after
    // the start; the deadline allows for a debug build's slow 640x480 renders on a loaded machine.
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut still_since: Option<(u64, Instant)> = None;
    let parked = loop {
        let status = watch.next().await.unwrap().unwrap();
        let cam = &status.cameras[0];
        match still_since {
            Some((n, since)) if n == cam.frames_captured && cam.frames_captured > 0 => {
                if since.elapsed() >= Duration::from_secs(1) {
                    break status;
                }
            }
            _ => still_since = Some((cam.frames_captured, Instant::now())),
        }
        assert!(
            Instant::now() < deadline,
            "the unread camera never stopped drawing"
        );
    };
    let cam = &parked.cameras[0];
    assert!(cam.live, "a parked camera is idle, not dead: {cam:?}");
    assert!(cam.last_frame_age_s >= 1.0, "{cam:?}");

    let asked_ns = phone2act_clock::monotonic_ns();
    let observation = client
        .policy_raw()
        .get_observation(phone2act_proto::v1::GetObservationRequest {
            arms: Vec::new(),
            image_encoding: phone2act_proto::v1::ImageEncoding::Rgb8.into(),
            cameras: Vec::new(),
        })
        .await
        .unwrap()
        .into_inner();
    let frame = &observation.frames[0];
    assert_eq!(frame.data.len(), 640 * 480 * 3);
    assert!(
        frame.capture_time_ns >= asked_ns,
        "the observation got a frame from before the request ({:.3} s earlier)",
        (asked_ns - frame.capture_time_ns) as f64 * 1e-9
    );
    assert!(frame.frame_seq > 0);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_is_required_when_configured() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = phone2act_server::Config::from_toml_str(
        phone2act_server::config::EMBEDDED_DEFAULT,
        "embedded",
        Vec::new(),
    )
    .unwrap();
    config.recorder.root = dir.path().to_owned();
    config.server.token = Some("sesame".to_owned());
    let server = TestServer::start(config).await.unwrap();

    let anonymous = server.client().await.unwrap();
    let err = anonymous.system().list_arms().await.unwrap_err().to_string();
    assert!(err.contains("authorization"), "{err}");

    let wrong = phone2act_sdk::Client::connect(&server.url(), Some("nope"))
        .await
        .unwrap();
    let err = wrong.system().list_arms().await.unwrap_err().to_string();
    assert!(err.contains("wrong token"), "{err}");

    let right = phone2act_sdk::Client::connect(&server.url(), Some("sesame"))
        .await
        .unwrap();
    assert_eq!(right.system().list_arms().await.unwrap().len(), 1);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn port_in_use_is_a_one_line_error() {
    let taken = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = taken.local_addr().unwrap();
    let err = phone2act_server::bind(addr).await.unwrap_err().to_string();
    assert!(err.contains(&addr.to_string()), "{err}");
    assert!(err.contains("in use"), "{err}");
    assert!(!err.contains('\n'), "one line: {err}");
}

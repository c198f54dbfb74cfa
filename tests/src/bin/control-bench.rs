//! Control-path benchmark (issue 4): the latency the server adds between receiving a phone sample and
//! handing the gated command to the bridge, with two arms driven by 60 Hz phone streams and a third arm
//! driven by a policy session at the same time; then the highest sustained sample rate; then full load
//! (issue 17): 8 phones at 60 Hz, 4 policy sessions pushing chunks and 3 synthetic cameras recording an
//! episode, all on one server; then the same full load while the station's uploader sends a backlog to an S3
//! server on loopback as fast as it can (when `PHONE2ACT_MOTO_SERVER` names one).
//!
//! Run: `PHONE2ACT_MOTO_SERVER=$(tests/scripts/s3-server.sh) cargo run --release -p phone2act-tests --bin
//! control-bench [-- --seconds 10] [--cameras 640x480@20]`

use anyhow::Context as _;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions, buttons};
use phone2act_server::Config;
use phone2act_server::app::App;
use std::sync::Arc;
use std::time::{Duration, Instant};

const CONFIG: &str = r#"
[[arms]]
name = "left"
bridge = "sim"

[[arms]]
name = "right"
bridge = "sim"

[[arms]]
name = "aux"
bridge = "sim"

[recorder]
root = "/tmp/phone2act-control-bench"
"#;

fn percentile(sorted: &[u32], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    f64::from(sorted[i]) / 1000.0
}

fn phone_pose(t_s: f64, phase: f64) -> v1::Pose {
    // A slow 3 cm circle: inside every limit, never a jump.
    let a = 0.03;
    let w = 2.0 * std::f64::consts::PI * 0.5;
    v1::Pose::from_parts(
        [a * (w * t_s + phase).cos() - a, a * (w * t_s + phase).sin(), 0.0],
        [0.0, 0.0, 0.0, 1.0],
    )
}

/// The full-load server: `PHONES` phone arms, `POLICIES` policy arms, `CAMERAS` test-pattern cameras.
const PHONES: usize = 8;
const POLICIES: usize = 4;
const CAMERAS: usize = 3;

/// The full load's cameras: `--cameras WxH@FPS`, by default 320x240@30 (three streaming encoders that fit
/// next to everything else on a 2-core machine); `--cameras 640x480@20` is the recorder's documented load
/// (docs/benchmarks.md#recorder). The episode is recorded at the cameras' rate.
#[derive(Clone, Copy, Debug)]
struct CameraLoad {
    width: u32,
    height: u32,
    fps: u32,
}

static CAMERA_LOAD: std::sync::OnceLock<CameraLoad> = std::sync::OnceLock::new();

fn camera_load() -> CameraLoad {
    *CAMERA_LOAD.get_or_init(|| CameraLoad {
        width: 320,
        height: 240,
        fps: 30,
    })
}

fn parse_camera_load(s: &str) -> anyhow::Result<CameraLoad> {
    let parse = || -> Option<CameraLoad> {
        let (size, fps) = s.split_once('@')?;
        let (w, h) = size.split_once('x')?;
        Some(CameraLoad {
            width: w.parse().ok()?,
            height: h.parse().ok()?,
            fps: fps.parse().ok()?,
        })
    };
    parse()
        .filter(|c| c.width > 0 && c.height > 0 && (1..=120).contains(&c.fps))
        .with_context(|| format!("--cameras takes WxH@FPS, such as 640x480@20, not {s:?}"))
}

fn full_load_config(root: &std::path::Path, storage: &str) -> String {
    let arms = (0..PHONES)
        .map(|i| format!("phone{i}"))
        .chain((0..POLICIES).map(|i| format!("policy{i}")))
        .map(|name| format!("[[arms]]\nname = \"{name}\"\nbridge = \"sim\"\n\n"));
    let CameraLoad { width, height, fps } = camera_load();
    let cameras = (0..CAMERAS).map(|i| {
        format!(
            "[[cameras]]\nname = \"cam{i}\"\nkind = \"test_pattern\"\nwidth = {width}\nheight = {height}\nfps = \
             {fps}\n\n"
        )
    });
    arms.chain(cameras).collect::<String>()
        + &format!("[recorder]\nroot = \"{}\"\nfps = {fps}\n\n", root.display())
        + storage
}

async fn phone(client: Client, arm: String, rate_hz: f64, seconds: f64) -> anyhow::Result<u64> {
    // Feedback is not read: the server drops feedback a client does not take (latest wins), so an idle
    // reader never slows the control path.
    let mut session = client
        .teleop(
            &arm,
            TeleopOptions {
                client_name: "bench".into(),
                take_over: true,
            },
        )
        .await?;
    session
        .send_pose(phone_pose(0.0, 0.0), vec![buttons::clutch_engage()], 0)
        .await?;
    let start = Instant::now();
    let period = Duration::from_secs_f64(1.0 / rate_hz);
    let mut sent = 0u64;
    let mut next = Instant::now();
    while start.elapsed().as_secs_f64() < seconds {
        let t = start.elapsed().as_secs_f64();
        session.send_pose(phone_pose(t, 0.0), vec![], 0).await?;
        sent += 1;
        next += period;
        tokio::time::sleep_until(next.into()).await;
    }
    Ok(sent)
}

async fn policy(client: Client, arm: String, seconds: f64) -> anyhow::Result<u64> {
    // Not the common hello: 10 Hz observations, the load the benchmark's published numbers were measured under.
    let mut session = client
        .policy(v1::PolicyHello {
            arms: vec![arm.clone()],
            observation_rate_hz: 10.0,
            image_encoding: v1::ImageEncoding::None as i32,
            request_control: true,
            policy_name: "bench".into(),
            silence_timeout_s: 2.0,
            ..v1::PolicyHello::default()
        })
        .await?;
    let start = Instant::now();
    let mut chunks = 0u64;
    while start.elapsed().as_secs_f64() < seconds {
        let obs = session.next_observation().await?;
        let steps = (0..16)
            .map(|k| {
                let dx = 0.01 * (f64::from(k) * 0.3 + chunks as f64).sin();
                v1::ActionStep {
                    values: vec![dx, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                }
            })
            .collect();
        session
            .push_chunk(v1::ActionChunk {
                arm: arm.clone(),
                steps,
                step_period_s: 1.0 / 30.0,
                observation_id: obs.observation_id,
                mode: v1::ActionMode::DeltaEe as i32,
                blend_steps: 0,
                keep_steps: 0,
            })
            .await?;
        chunks += 1;
    }
    Ok(chunks)
}

/// Why the server ended a session whose sending side failed: the status at the end of its feedback stream.
async fn ended_because(session: &mut phone2act_sdk::TeleopSession, e: phone2act_sdk::Error) -> anyhow::Error {
    loop {
        match session.feedback().await {
            Ok(Some(_)) => {}
            Ok(None) => return anyhow::anyhow!("{e}: the server ended the stream without an error"),
            Err(status) => return anyhow::anyhow!("{e}: the server ended the stream with {status}"),
        }
    }
}

fn report<S: AsRef<str>>(name: &str, app: &App, arms: &[S]) {
    let mut all = Vec::new();
    for arm in arms {
        let (mut v, _) = app.arm(arm.as_ref()).expect("arm").stats().latencies_ns();
        all.append(&mut v);
    }
    all.sort_unstable();
    println!(
        "{name:<44} n={:<7} p50={:>7.1} µs  p99={:>7.1} µs  max={:>8.1} µs",
        all.len(),
        percentile(&all, 0.50),
        percentile(&all, 0.99),
        all.last().map_or(f64::NAN, |v| f64::from(*v) / 1000.0)
    );
}

fn main() -> anyhow::Result<()> {
    let seconds: f64 = std::env::args()
        .skip_while(|a| a != "--seconds")
        .nth(1)
        .map(|s| s.parse())
        .transpose()
        .context("--seconds takes a number")?
        .unwrap_or(10.0);
    if let Some(load) = std::env::args().skip_while(|a| a != "--cameras").nth(1) {
        let load = parse_camera_load(&load)?;
        CAMERA_LOAD.set(load).ok();
    }
    let server = BenchServer::start(CONFIG)?;
    let (app, url) = (Arc::clone(&server.app), server.url.clone());

    // Clients on their own current-thread runtime, as a separate process would be.
    let client_rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    println!(
        "phone2act control-path benchmark ({seconds} s per phase, release build expected; full load's cameras {:?})",
        camera_load()
    );
    let (sent_l, sent_r, chunks) = client_rt.block_on(async {
        let client = Client::connect(&url, None).await?;
        tokio::time::sleep(Duration::from_millis(300)).await;
        for arm in ["left", "right", "aux"] {
            app.arm(arm).expect("arm").stats().reset_latencies();
        }
        let (l, r, p) = tokio::join!(
            phone(client.clone(), "left".into(), 60.0, seconds),
            phone(client.clone(), "right".into(), 60.0, seconds),
            policy(client.clone(), "aux".into(), seconds)
        );
        anyhow::Ok((l?, r?, p?))
    })?;
    report(
        "sample → bridge, 2 arms × 60 Hz + 1 policy",
        &app,
        &["left", "right"],
    );
    println!("  phone samples sent: {sent_l} + {sent_r}; policy chunks pushed: {chunks}");

    // Throughput: one phone streaming as fast as the transport allows.
    app.arm("left").expect("arm").stats().reset_latencies();
    let before = app.arm("left").expect("arm").stats().samples_received();
    let started = Instant::now();
    let sent = client_rt.block_on(async {
        let client = Client::connect(&url, None).await?;
        let mut session = client
            .teleop(
                "left",
                TeleopOptions {
                    client_name: "flood".into(),
                    take_over: true,
                },
            )
            .await?;
        session
            .send_pose(phone_pose(0.0, 0.0), vec![buttons::clutch_engage()], 0)
            .await?;
        let mut sent = 0u64;
        let t0 = Instant::now();
        while t0.elapsed().as_secs_f64() < seconds.min(5.0) {
            let t = t0.elapsed().as_secs_f64();
            if let Err(e) = session.send_pose(phone_pose(t, 0.0), vec![], 0).await {
                // Reported, and the phases after this one still run.
                println!(
                    "  flood ended early after {sent} samples: {}",
                    ended_because(&mut session, e).await
                );
                break;
            }
            sent += 1;
        }
        anyhow::Ok(sent)
    })?;
    let elapsed = started.elapsed().as_secs_f64();
    let received = app.arm("left").expect("arm").stats().samples_received() - before;
    report("sample → bridge under flood (1 phone)", &app, &["left"]);
    println!(
        "  sustained: {:.0} samples/s received ({sent} sent), {:.0} planned commands/s",
        received as f64 / elapsed,
        app.arm("left").expect("arm").stats().latencies_ns().1 as f64 / elapsed
    );
    server.stop();
    let root = std::env::temp_dir().join("phone2act-control-bench-full");
    let _ = std::fs::remove_dir_all(&root);
    full_load(
        "sample → bridge, full load (8 phones + 4 policies + 3 cams)",
        &full_load_config(&root, ""),
        seconds,
        &client_rt,
        |_| {},
    )?;
    let _ = std::fs::remove_dir_all(&root);
    // The same load while an upload runs, when an S3 server is at hand (tests/scripts/s3-server.sh).
    match std::env::var_os("PHONE2ACT_MOTO_SERVER").map(std::path::PathBuf::from) {
        Some(moto) if moto.exists() => full_load_while_uploading(seconds, &client_rt, &moto),
        _ => {
            println!(
                "full load + upload: skipped (set PHONE2ACT_MOTO_SERVER=$(tests/scripts/s3-server.sh) to run it)"
            );
            Ok(())
        }
    }
}

/// A server on its own 2-thread runtime, with a handle on its `App` for the control-path counters.
struct BenchServer {
    rt: tokio::runtime::Runtime,
    app: Arc<App>,
    url: String,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), phone2act_server::ServerError>>,
}

impl BenchServer {
    fn start(config: &str) -> anyhow::Result<Self> {
        let config = Config::from_toml_str(config, "control-bench", Vec::new())?;
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        let app = Arc::new(App::start(config)?);
        let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
        let url = format!("http://{}", listener.local_addr()?);
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = rt.spawn(phone2act_server::serve_app(Arc::clone(&app), listener, async {
            let _ = stopped.await;
        }));
        Ok(Self {
            rt,
            app,
            url,
            stop,
            task,
        })
    }

    fn stop(self) {
        let _ = self.stop.send(());
        let _ = self.rt.block_on(self.task);
        self.app.stop();
    }
}

/// What one full-load window recorded, from the episode's status just before it is discarded.
struct Recorded {
    frames: u64,
    dropped: u64,
    late: u64,
}

/// 8 phones at 60 Hz + 4 policy sessions + 3 cameras recording, each client on its own connection as
/// separate devices would be, on a server configured by `config`; `during` runs once the load is on and again
/// at its end (the upload phase reads the uploader's counters there).
fn full_load(
    label: &str,
    config: &str,
    seconds: f64,
    client_rt: &tokio::runtime::Runtime,
    mut during: impl FnMut(&v1::ListEpisodesResponse),
) -> anyhow::Result<Recorded> {
    let server = BenchServer::start(config)?;
    let (app, url) = (Arc::clone(&server.app), server.url.clone());
    let phones: Vec<String> = (0..PHONES).map(|i| format!("phone{i}")).collect();
    let (sent, chunks, recorded) = client_rt.block_on(async {
        let control = Client::connect(&url, None).await?;
        control.episodes().start("control-bench full load").await?;
        tokio::time::sleep(Duration::from_millis(300)).await;
        for arm in &phones {
            app.arm(arm).expect("arm").stats().reset_latencies();
        }
        during(&control.episodes().list().await?);
        let mut clients = tokio::task::JoinSet::new();
        for arm in &phones {
            let client = Client::connect(&url, None).await?;
            clients.spawn(phone(client, arm.clone(), 60.0, seconds));
        }
        let mut policies = tokio::task::JoinSet::new();
        for i in 0..POLICIES {
            let client = Client::connect(&url, None).await?;
            policies.spawn(policy(client, format!("policy{i}"), seconds));
        }
        let (mut sent, mut chunks) = (0, 0);
        while let Some(done) = clients.join_next().await {
            sent += done??;
        }
        while let Some(done) = policies.join_next().await {
            chunks += done??;
        }
        during(&control.episodes().list().await?);
        let st = control.episodes().status().await?;
        control.episodes().discard().await?;
        let recorded = Recorded {
            frames: st.frames_recorded,
            dropped: st.dropped_frames,
            late: st.late_ticks,
        };
        anyhow::Ok((sent, chunks, recorded))
    })?;
    report(label, &app, &phones);
    println!(
        "  phone samples sent: {sent}; policy chunks pushed: {chunks}; frames recorded: {} ({CAMERAS} cameras), \
         dropped {}, late ticks {}",
        recorded.frames, recorded.dropped, recorded.late
    );
    server.stop();
    Ok(recorded)
}

/// Bytes the upload phase puts behind the recorded episode so the uploader is busy for the whole window:
/// about two minutes at loopback speed in a debug build, 20 s in a release one (78 MB/s measured at load 2-3).
const UPLOAD_PAD_BYTES: usize = 1536 << 20;

/// The full load again, on a dataset whose uploader is busy for the whole window: a station with `[storage]`
/// (a moto S3 server on loopback, no bandwidth cap) catching up on a committed episode plus
/// [`UPLOAD_PAD_BYTES`] of video-sized payload, hashing and putting 8 MiB parts flat out.
fn full_load_while_uploading(
    seconds: f64,
    client_rt: &tokio::runtime::Runtime,
    moto_bin: &std::path::Path,
) -> anyhow::Result<()> {
    let dir = std::env::temp_dir().join(format!("phone2act-control-bench-upload-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let r = upload_phase(seconds, client_rt, moto_bin, &dir);
    let _ = std::fs::remove_dir_all(&dir);
    r
}

fn upload_phase(
    seconds: f64,
    client_rt: &tokio::runtime::Runtime,
    moto_bin: &std::path::Path,
    dir: &std::path::Path,
) -> anyhow::Result<()> {
    let moto = phone2act_tests::s3::Moto::start(moto_bin, dir, false);
    moto.create_bucket("bench");
    let root = dir.join("ds");
    // A committed episode (the dataset the station resumes), then the payload beside it.
    let server = BenchServer::start(&full_load_config(&root, ""))?;
    client_rt.block_on(async {
        let control = Client::connect(&server.url, None).await?;
        control.episodes().start("control-bench seed").await?;
        tokio::time::sleep(Duration::from_millis(500)).await;
        control.episodes().stop().await?;
        anyhow::Ok(())
    })?;
    server.stop();
    let pad = root.join("videos/observation.images.pad/chunk-000");
    std::fs::create_dir_all(&pad)?;
    // Video-sized files of 4 MiB (one PUT each), so the uploader's byte counter advances during the window.
    let file = vec![0x5au8; 4 << 20];
    for i in 0..UPLOAD_PAD_BYTES / file.len() {
        std::fs::write(pad.join(format!("file-{i:03}.mp4")), &file)?;
    }
    let creds = moto.credentials_file(dir, None);
    let storage = format!(
        "[storage]\nurl = \"s3://bench/control\"\nendpoint = \"{}\"\ncredentials_file = \"{}\"\nstation_id = \"bench\"\n",
        moto.endpoint(),
        creds.display()
    );
    let mut marks = Vec::new();
    let started = Instant::now();
    full_load(
        "sample → bridge, full load + upload flat out",
        &full_load_config(&root, &storage),
        seconds,
        client_rt,
        |list| {
            if let Some(st) = &list.storage {
                marks.push((started.elapsed().as_secs_f64(), st.bytes_put, st.episodes_pending));
            }
        },
    )?;
    if let [(t0, b0, _), (t1, b1, pending)] = marks[..] {
        println!(
            "  upload during the window: {:.1} MB in {:.1} s ({:.1} MB/s put, after hashing); {}",
            (b1 - b0) as f64 / 1e6,
            t1 - t0,
            (b1 - b0) as f64 / 1e6 / (t1 - t0),
            if pending > 0 {
                "still uploading at the end of the window"
            } else {
                "the upload ended inside the window: raise UPLOAD_PAD_BYTES for a faster machine"
            }
        );
    }
    Ok(())
}

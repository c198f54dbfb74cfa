//! Soak benchmark (issue 13): the real `phone2act serve` process under sustained load, its resident memory
//! printed every 5 s. Load: 8 simulated arms, a phone at 60 Hz on each (4 of them engaged and driving), 4
//! policy sessions at 10 Hz observing with JPEG camera images and driving the other 4 arms with 16-step
//! chunks, one 640x480 camera, and 20 s episodes recorded back to back. At the end the dataset is checked
//! with `phone2act dataset verify` and, when the conformance venv exists, with the real lerobot.
//!
//! Run (release build of the server first):
//! `cargo build --release -p phone2act-cli --bin phone2act && cargo run --release -p phone2act-tests --bin soak -- --minutes 10`
//! Options: `--minutes M` (default 10), `--episode-s S` (default 20), `--bin PATH` (default
//! target/release/phone2act next to this binary), `--keep DIR` (dataset location, default a temp dir).

use anyhow::{Context as _, bail};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions, buttons};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

const ARMS: usize = 8;
const POLICIES: usize = 4;

fn arg<T: std::str::FromStr>(name: &str) -> anyhow::Result<Option<T>> {
    std::env::args()
        .skip_while(|a| a != name)
        .nth(1)
        .map(|s| {
            s.parse::<T>()
                .map_err(|_| anyhow::anyhow!("{name}: cannot parse {s:?}"))
        })
        .transpose()
}

fn config(root: &Path, listen: &str) -> String {
    use std::fmt::Write as _;
    let mut c = format!("[server]\nlisten = \"{listen}\"\n\n[gateway]\nenabled = false\n\n");
    for i in 0..ARMS {
        let _ = write!(c, "[[arms]]\nname = \"arm{i}\"\nbridge = \"sim\"\n\n");
    }
    let _ = write!(
        c,
        "[[cameras]]\nname = \"front\"\nkind = \"test_pattern\"\nwidth = 640\nheight = 480\nfps = 30\n\n\
         [recorder]\nroot = \"{}\"\nformat = \"v3.0\"\nfps = 20\n",
        root.display()
    );
    c
}

fn rss_mb(pid: u32) -> anyhow::Result<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let kb: f64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .context("no VmRSS")?;
    Ok(kb / 1024.0)
}

fn phone_pose(t_s: f64, phase: f64) -> v1::Pose {
    // A slow 3 cm circle: inside every limit, never a jump.
    let (a, w) = (0.03, std::f64::consts::PI);
    v1::Pose::from_parts(
        [a * (w * t_s + phase).cos() - a, a * (w * t_s + phase).sin(), 0.0],
        [0.0, 0.0, 0.0, 1.0],
    )
}

struct Counters {
    errors: AtomicU64,
    samples: AtomicU64,
    chunks: AtomicU64,
    stop: AtomicBool,
}

impl Counters {
    fn error(&self, what: &str, e: &dyn std::fmt::Display) {
        self.errors.fetch_add(1, Ordering::Relaxed);
        eprintln!("ERROR {what}: {e}");
    }
}

async fn phone(client: Client, arm: String, engage: bool, c: Arc<Counters>) {
    let r = async {
        let mut s = client
            .teleop(
                &arm,
                TeleopOptions {
                    client_name: format!("soak-{arm}"),
                    take_over: false,
                },
            )
            .await?;
        let first = if engage {
            vec![buttons::clutch_engage()]
        } else {
            vec![]
        };
        s.send_pose(phone_pose(0.0, 0.0), first, 0).await?;
        let start = Instant::now();
        let period = Duration::from_secs_f64(1.0 / 60.0);
        let mut next = Instant::now();
        while !c.stop.load(Ordering::Relaxed) {
            s.send_pose(phone_pose(start.elapsed().as_secs_f64(), 0.0), vec![], 0)
                .await?;
            c.samples.fetch_add(1, Ordering::Relaxed);
            // Read whatever feedback is there, as a phone does, without waiting for it.
            while let Ok(Some(fb)) = tokio::time::timeout(Duration::ZERO, s.feedback())
                .await
                .unwrap_or(Ok(None))
            {
                if !fb.error.is_empty() {
                    anyhow::bail!("feedback error: {}", fb.error);
                }
            }
            next += period;
            tokio::time::sleep_until(next.into()).await;
        }
        anyhow::Ok(())
    }
    .await;
    if let Err(e) = r {
        c.error(&format!("phone on {arm}"), &e);
    }
}

async fn policy(client: Client, arm: String, c: Arc<Counters>) {
    let r = async {
        // Not the common hello: JPEG images at 10 Hz, so the soak keeps the image path loaded.
        let mut s = client
            .policy(v1::PolicyHello {
                arms: vec![arm.clone()],
                observation_rate_hz: 10.0,
                image_encoding: v1::ImageEncoding::Jpeg as i32,
                request_control: true,
                policy_name: format!("soak-{arm}"),
                silence_timeout_s: 2.0,
                ..v1::PolicyHello::default()
            })
            .await?;
        let mut k = 0u64;
        while !c.stop.load(Ordering::Relaxed) {
            let obs = s.next_observation().await?;
            let steps = (0..16)
                .map(|i| v1::ActionStep {
                    values: vec![
                        0.005 * (f64::from(i) * 0.3 + k as f64 * 0.1).sin(),
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                    ],
                })
                .collect();
            s.push_chunk(v1::ActionChunk {
                arm: arm.clone(),
                steps,
                step_period_s: 1.0 / 30.0,
                observation_id: obs.observation_id,
                mode: v1::ActionMode::DeltaEe as i32,
                blend_steps: 0,
                keep_steps: 0,
            })
            .await?;
            c.chunks.fetch_add(1, Ordering::Relaxed);
            k += 1;
        }
        anyhow::Ok(())
    }
    .await;
    if let Err(e) = r {
        c.error(&format!("policy on {arm}"), &e);
    }
}

fn default_bin() -> PathBuf {
    let me = std::env::current_exe().unwrap_or_default();
    me.parent()
        .map_or_else(|| PathBuf::from("phone2act"), |d| d.join("phone2act"))
}

#[allow(clippy::too_many_lines)]
fn main() -> anyhow::Result<()> {
    let minutes: f64 = arg("--minutes")?.unwrap_or(10.0);
    let episode_s: f64 = arg("--episode-s")?.unwrap_or(20.0);
    let bin: PathBuf = arg("--bin")?.unwrap_or_else(default_bin);
    if !bin.exists() {
        bail!(
            "{} not found: cargo build --release -p phone2act-cli --bin phone2act (or --bin PATH)",
            bin.display()
        );
    }
    let tmp = std::env::temp_dir().join(format!("phone2act-soak-{}", std::process::id()));
    let root: PathBuf = arg("--keep")?.unwrap_or_else(|| tmp.join("dataset"));
    std::fs::create_dir_all(&tmp)?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
    let listen = format!("127.0.0.1:{port}");
    let cfg = tmp.join("soak.toml");
    std::fs::write(&cfg, config(&root, &listen))?;
    let mut server = std::process::Command::new(&bin)
        .args(["serve", "--config"])
        .arg(&cfg)
        .env("PHONE2ACT_LOG", "warn")
        .spawn()
        .with_context(|| format!("starting {}", bin.display()))?;
    let pid = server.id();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let c = Arc::new(Counters {
        errors: AtomicU64::new(0),
        samples: AtomicU64::new(0),
        chunks: AtomicU64::new(0),
        stop: AtomicBool::new(false),
    });
    let url = format!("http://{listen}");
    let trace = rt.block_on(async {
        let client = {
            let t0 = Instant::now();
            loop {
                match Client::connect(&url, None).await {
                    Ok(c) => break c,
                    Err(e) if t0.elapsed() < Duration::from_secs(30) => {
                        let _ = e;
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    Err(e) => return Err(anyhow::anyhow!("server did not come up: {e}")),
                }
            }
        };
        let mut tasks = Vec::new();
        for i in 0..ARMS {
            tasks.push(tokio::spawn(phone(
                client.clone(),
                format!("arm{i}"),
                i < ARMS - POLICIES,
                Arc::clone(&c),
            )));
        }
        // Let the phones attach first, then the policies take the arms no phone is engaged on.
        tokio::time::sleep(Duration::from_millis(500)).await;
        for i in ARMS - POLICIES..ARMS {
            tasks.push(tokio::spawn(policy(
                client.clone(),
                format!("arm{i}"),
                Arc::clone(&c),
            )));
        }
        let recorder = {
            let (client, c) = (client.clone(), Arc::clone(&c));
            tokio::spawn(async move {
                let mut episodes = client.episodes();
                let mut saved = 0u64;
                let mut n = 0u64;
                while !c.stop.load(Ordering::Relaxed) {
                    if let Err(e) = episodes.start(&format!("soak episode {n}")).await {
                        c.error("Start", &e);
                    }
                    let t = Instant::now();
                    while t.elapsed().as_secs_f64() < episode_s && !c.stop.load(Ordering::Relaxed) {
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    match episodes.stop().await {
                        Ok(_) => saved += 1,
                        Err(e) => c.error("Stop", &e),
                    }
                    n += 1;
                }
                saved
            })
        };
        let start = Instant::now();
        let mut trace: Vec<(f64, f64)> = Vec::new();
        println!(
            "{:>6} {:>8} {:>9} {:>8} {:>6}",
            "t_s", "rss_mb", "samples", "chunks", "errors"
        );
        while start.elapsed().as_secs_f64() < minutes * 60.0 {
            let t = start.elapsed().as_secs_f64();
            let rss = rss_mb(pid)?;
            trace.push((t, rss));
            println!(
                "{t:>6.0} {rss:>8.1} {:>9} {:>8} {:>6}",
                c.samples.load(Ordering::Relaxed),
                c.chunks.load(Ordering::Relaxed),
                c.errors.load(Ordering::Relaxed)
            );
            tokio::time::sleep_until((start + Duration::from_secs(trace.len() as u64 * 5)).into()).await;
        }
        c.stop.store(true, Ordering::Relaxed);
        let saved = recorder.await?;
        for t in tasks {
            let _ = t.await;
        }
        let list = client.episodes().list().await?;
        println!("episodes saved: {saved} (List says {})", list.episodes.len());
        anyhow::Ok(trace)
    })?;
    let _ = std::process::Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status();
    let status = server.wait()?;
    println!("server exit after SIGTERM: {status}");

    let window_start = trace.last().map_or(0.0, |l| l.0) - 8.0 * 60.0;
    let window: Vec<f64> = trace
        .iter()
        .filter(|(t, _)| *t >= window_start.max(0.0))
        .map(|p| p.1)
        .collect();
    let (lo, hi) = window
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(*v), hi.max(*v))
        });
    let first = window.first().copied().unwrap_or(f64::NAN);
    let last = window.last().copied().unwrap_or(f64::NAN);
    println!(
        "RSS over the last {:.0} s: first {first:.1} MB, last {last:.1} MB, drift {:+.1} MB, range {:.1} MB (min {lo:.1}, max {hi:.1}); peak overall {:.1} MB",
        (trace.last().map_or(0.0, |l| l.0) - window_start.max(0.0)),
        last - first,
        hi - lo,
        trace.iter().map(|p| p.1).fold(0.0, f64::max)
    );
    println!("errors: {}", c.errors.load(Ordering::Relaxed));

    let verify = std::process::Command::new(&bin)
        .args(["dataset", "verify"])
        .arg(&root)
        .output()?;
    println!(
        "phone2act dataset verify: {}\n{}{}",
        verify.status,
        String::from_utf8_lossy(&verify.stdout),
        String::from_utf8_lossy(&verify.stderr)
    );
    let mut ok = verify.status.success() && c.errors.load(Ordering::Relaxed) == 0;
    let cache = std::env::var_os("PHONE2ACT_CACHE_DIR").map_or_else(
        || {
            std::env::var_os("HOME")
                .map(PathBuf::from)
                .unwrap_or_default()
                .join(".cache/phone2act")
        },
        PathBuf::from,
    );
    let py = cache.join("lerobot-venv/bin/python");
    if py.exists() && cache.join("lerobot-venv/.phone2act-ready").exists() {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("conformance/check.py");
        let out = std::process::Command::new(py).arg(script).arg(&root).output()?;
        println!(
            "lerobot check: {}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout)
        );
        ok &= out.status.success();
    } else {
        println!(
            "lerobot check: skipped (no conformance venv in {})",
            cache.display()
        );
    }
    if arg::<PathBuf>("--keep")?.is_none() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    if !ok {
        bail!("soak failed: errors, or the dataset does not verify");
    }
    Ok(())
}

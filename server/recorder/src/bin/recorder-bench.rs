//! Recorder benchmark: the camera load recorded with zero dropped frames on this machine, peak RSS and
//! save latency for long episodes, and encode speed side by side with lerobot's own encoder.
//!
//! Run in release: `cargo run --release -p phone2act-recorder --bin recorder-bench -- [--quick]
//! [--long-s 600] [--load-s 10] [--only load,memory,encode,highlight]`. Cameras are FFmpeg `testsrc2` through
//! libavdevice (the V4L2 capture path), the robot is synthetic. Each memory run is a child process so its
//! peak RSS is its own.

use phone2act_capture::av::device::{AvCaptureConfig, spawn_av_capture};
use phone2act_capture::camera::{CaptureThread, FrameSlot};
use phone2act_dataset::{CameraSpec, DatasetSpec, Format, VideoSettings};
use phone2act_recorder::Recorder;
use phone2act_recorder::av::VideoEncoder;
use phone2act_recorder::synthetic::SyntheticRobot;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

type Res<T> = Result<T, Box<dyn std::error::Error>>;

fn main() {
    if let Err(e) = run() {
        eprintln!("recorder-bench: {e}");
        std::process::exit(1);
    }
}

struct Opts {
    quick: bool,
    long_s: u64,
    load_s: f64,
    /// Sections to run: `load`, `memory`, `encode` (all by default).
    only: Vec<String>,
    /// Busy threads at normal priority during the load steps: other work sharing the machine.
    contend: usize,
}

impl Opts {
    fn runs(&self, section: &str) -> bool {
        self.only.is_empty() || self.only.iter().any(|s| s == section)
    }
}

fn run() -> Res<()> {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--rss-episode") {
        let usage = "--rss-episode SECONDS CODEC CAMERAS FPS";
        let arg = |k: usize| args.get(i + k).ok_or(usage);
        return rss_child(arg(1)?.parse()?, arg(2)?, arg(3)?.parse()?, arg(4)?.parse()?);
    }
    if let Some(i) = args.iter().position(|a| a == "--rss-highlight") {
        let usage = "--rss-highlight KEEP_S IDLE_S CODEC CAMERAS FPS";
        let arg = |k: usize| args.get(i + k).ok_or(usage);
        return highlight_child(
            arg(1)?.parse()?,
            arg(2)?.parse()?,
            arg(3)?,
            arg(4)?.parse()?,
            arg(5)?.parse()?,
        );
    }
    let quick = args.iter().any(|a| a == "--quick");
    let val = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let opts = Opts {
        quick,
        long_s: val("--long-s").map_or(Ok(if quick { 30 } else { 600 }), |v| v.parse())?,
        load_s: val("--load-s").map_or(Ok(if quick { 4.0 } else { 10.0 }), |v| v.parse())?,
        contend: val("--contend").map_or(Ok(0), |v| v.parse())?,
        only: val("--only")
            .map(|v| v.split(',').map(str::to_owned).collect())
            .unwrap_or_default(),
    };
    if let Some(bad) = opts
        .only
        .iter()
        .find(|s| !["load", "memory", "encode", "highlight"].contains(&s.as_str()))
    {
        return Err(
            format!("--only takes load, memory, encode, highlight (comma-separated), not {bad:?}").into(),
        );
    }
    println!(
        "# phone2act recorder benchmark ({} cores, {} build)",
        std::thread::available_parallelism()?,
        if cfg!(debug_assertions) {
            "debug"
        } else {
            "release"
        }
    );
    if opts.runs("load") {
        load_ladder(&opts)?;
    }
    if opts.runs("memory") {
        memory_and_save(&opts)?;
    }
    if opts.runs("highlight") {
        highlight_memory(&opts)?;
    }
    if opts.runs("encode") {
        encode_speed(&opts)?;
    }
    Ok(())
}

type Cameras = (Vec<(String, Arc<FrameSlot>)>, Vec<CameraSpec>, Vec<CaptureThread>);

fn cameras(n: usize, w: u32, h: u32, fps: u32) -> Res<Cameras> {
    let mut slots = Vec::new();
    let mut specs = Vec::new();
    let mut threads = Vec::new();
    for i in 0..n {
        let name = format!("cam{i}");
        let slot = Arc::new(FrameSlot::default());
        threads.push(spawn_av_capture(
            &name,
            AvCaptureConfig::lavfi_testsrc(w, h, fps),
            Arc::clone(&slot),
        )?);
        slots.push((name.clone(), slot));
        specs.push(CameraSpec {
            name,
            width: w,
            height: h,
        });
    }
    Ok((slots, specs, threads))
}

struct Outcome {
    frames: u64,
    expected: u64,
    dropped: u64,
    late: u64,
    paused: u64,
    save_ms: f64,
}

/// One recording: `ncams` cameras of `size` at `fps` for `secs`.
struct Load<'a> {
    codec: &'a str,
    format: Format,
    ncams: usize,
    size: (u32, u32),
    fps: u32,
    secs: f64,
}

/// A recorder over `l`'s cameras (running) and the synthetic robot, its cameras' first frames delivered.
fn open_recorder(root: &Path, l: &Load) -> Res<(Recorder, Vec<CaptureThread>)> {
    let (format, codec, fps) = (l.format, l.codec, l.fps);
    let (slots, specs, threads) = cameras(l.ncams, l.size.0, l.size.1, fps)?;
    let spec = DatasetSpec {
        root: root.to_owned(),
        format,
        fps,
        robot_type: "bench".into(),
        video_codec: Some(codec.into()),
        state_names: SyntheticRobot::state_names(),
        action_names: SyntheticRobot::action_names(),
        cameras: specs,
        modality: SyntheticRobot::modality(),
        success: false,
        intervention: false,
        provenance: serde_json::json!({"bench": true}),
    };
    let rec = Recorder::open(spec, Arc::new(SyntheticRobot), slots)?;
    // Let the cameras deliver a first frame.
    std::thread::sleep(Duration::from_millis(300));
    Ok((rec, threads))
}

impl<'a> Load<'a> {
    /// `ncams` 640x480 cameras of `codec` (`av1` in a v3.0 dataset, others in v2.1) at `fps` for `secs`.
    fn vga(codec: &'a str, ncams: usize, fps: u32, secs: f64) -> Self {
        let format = if codec == "av1" { Format::V30 } else { Format::V21 };
        Load {
            codec,
            format,
            ncams,
            size: (640, 480),
            fps,
            secs,
        }
    }
}

fn record_once(root: &Path, l: &Load) -> Res<Outcome> {
    let (fps, secs) = (l.fps, l.secs);
    let (rec, threads) = open_recorder(root, l)?;
    rec.start_episode("benchmark")?;
    let t0 = Instant::now();
    std::thread::sleep(Duration::from_secs_f64(secs));
    let elapsed = t0.elapsed().as_secs_f64();
    let s = rec.stop_episode()?;
    rec.close()?;
    drop(threads);
    Ok(Outcome {
        frames: s.length_frames,
        expected: (elapsed * f64::from(fps)) as u64,
        dropped: s.dropped_frames,
        late: s.late_ticks,
        paused: s.paused_ticks,
        save_ms: s.save_latency_s * 1e3,
    })
}

fn load_ladder(o: &Opts) -> Res<()> {
    println!(
        "\n## camera load (640x480, {:.0} s per step; zero drops = every tick recorded, every frame encoded)",
        o.load_s
    );
    println!("competing busy threads: {}", o.contend);
    let _hogs = Hogs::start(o.contend);
    println!("| codec | cameras | fps | frames | dropped | late ticks | paused | save ms | zero drops |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let dir = tempfile_dir("load")?;
    for (codec, format, ladder) in [
        // Steps in order of total frame rate; climbs until one loses a frame or a tick, so the last
        // zero-drop step is the machine's capacity.
        (
            "h264",
            Format::V21,
            vec![
                (1, 30),
                (2, 30),
                (3, 30),
                (4, 30),
                (6, 30),
                (8, 30),
                (10, 30),
                (12, 30),
            ],
        ),
        (
            "av1",
            Format::V30,
            vec![(1, 20), (2, 20), (3, 20), (4, 20), (3, 30), (4, 30), (5, 30)],
        ),
    ] {
        let mut best = None;
        for (n, fps) in ladder {
            let root = dir.join(format!("{codec}-{n}x{fps}"));
            let load = Load {
                codec,
                format,
                ncams: n,
                size: (640, 480),
                fps,
                secs: o.load_s,
            };
            let r = record_once(&root, &load)?;
            let ok = r.dropped == 0 && r.late == 0 && r.paused == 0 && r.frames + 2 >= r.expected;
            println!(
                "| {codec} | {n} | {fps} | {}/{} | {} | {} | {} | {:.0} | {} |",
                r.frames,
                r.expected,
                r.dropped,
                r.late,
                r.paused,
                r.save_ms,
                if ok { "yes" } else { "no" }
            );
            let _ = std::fs::remove_dir_all(&root);
            if !ok {
                break;
            }
            best = Some((n, fps));
        }
        match best {
            Some((n, fps)) => println!("largest zero-drop load, {codec}: {n} cameras x 640x480 @ {fps} fps"),
            None => println!("largest zero-drop load, {codec}: none of the steps"),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Threads that spin until dropped, standing in for other work on the machine (a policy, a browser).
struct Hogs {
    stop: Arc<std::sync::atomic::AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Hogs {
    fn start(n: usize) -> Self {
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let threads = (0..n)
            .map(|_| {
                let stop = Arc::clone(&stop);
                std::thread::spawn(move || {
                    let mut x = 0u64;
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        x = std::hint::black_box(x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1));
                    }
                })
            })
            .collect();
        Hogs { stop, threads }
    }
}

impl Drop for Hogs {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

fn tempfile_dir(label: &str) -> Res<PathBuf> {
    let d = std::env::temp_dir().join(format!("phone2act-bench-{label}-{}", std::process::id()));
    std::fs::create_dir_all(&d)?;
    Ok(d)
}

fn peak_rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|kb| kb.parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

/// Child process: one episode of `secs` with 3 cameras 640x480 @ 20 fps AV1 (v3.0 defaults).
/// Child process: one episode of `secs` with `ncams` cameras 640x480 at `fps`.
fn rss_child(secs: f64, codec: &str, ncams: usize, fps: u32) -> Res<()> {
    let dir = tempfile_dir("rss")?;
    let load = Load::vga(codec, ncams, fps, secs);
    let r = record_once(&dir.join("ds"), &load)?;
    println!(
        "{}",
        serde_json::json!({"peak_rss_mb": peak_rss_mb(), "save_ms": r.save_ms, "frames": r.frames,
            "dropped": r.dropped, "late": r.late, "paused": r.paused})
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Runs this benchmark as a child with `args` and returns the JSON line it prints last, or what it said on
/// stderr when it printed none.
fn child_json(exe: &Path, args: &[&str]) -> Res<Result<serde_json::Value, String>> {
    let out = Command::new(exe).args(args).env("SVT_LOG", "1").output()?;
    let text = String::from_utf8_lossy(&out.stdout);
    Ok(text
        .lines()
        .last()
        .and_then(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .ok_or_else(|| String::from_utf8_lossy(&out.stderr).trim().to_owned()))
}

fn memory_and_save(o: &Opts) -> Res<()> {
    println!(
        "\n## memory and save latency (640x480 cameras; one process per episode, peak RSS of that process)"
    );
    println!("| load | episode | frames | dropped | peak RSS MB | save (stop -> committed) ms |");
    println!("|---|---|---|---|---|---|");
    let exe = std::env::current_exe()?;
    let long = o.long_s.to_string();
    let mut runs: Vec<(&str, usize, u32, Vec<&str>)> = vec![
        ("av1", 2, 20, vec!["10", "60", &long]),
        ("av1", 3, 20, vec!["60"]),
        ("h264", 3, 30, vec!["10", "60"]),
    ];
    if o.quick {
        runs = vec![("av1", 2, 20, vec!["10", &long]), ("h264", 3, 30, vec!["10"])];
    }
    for (codec, ncams, fps, lengths) in runs {
        for secs in lengths {
            let load = format!("{ncams} x {codec} @ {fps} fps");
            let v = match child_json(
                &exe,
                &["--rss-episode", secs, codec, &ncams.to_string(), &fps.to_string()],
            )? {
                Ok(v) => v,
                Err(e) => {
                    println!("| {load} | {secs} s | failed: {e} |");
                    continue;
                }
            };
            println!(
                "| {load} | {secs} s | {} | {} | {:.0} | {:.0} |",
                v["frames"],
                v["dropped"],
                v["peak_rss_mb"].as_f64().unwrap_or(0.0),
                v["save_ms"].as_f64().unwrap_or(0.0)
            );
        }
    }
    Ok(())
}

/// Child process: idle for `idle_s` with `[recorder] highlight_s = keep_s` (0: off), then (when on) the kept
/// seconds saved as an episode.
fn highlight_child(keep_s: f64, idle_s: f64, codec: &str, ncams: usize, fps: u32) -> Res<()> {
    let dir = tempfile_dir("highlight")?;
    let load = Load::vga(codec, ncams, fps, idle_s);
    let (rec, threads) = open_recorder(&dir.join("ds"), &load)?;
    rec.set_highlight((keep_s > 0.0).then_some(keep_s));
    std::thread::sleep(Duration::from_secs_f64(idle_s));
    let status = rec.status();
    let mut out = serde_json::json!({"kept_s": status.highlight_buffered_s,
        "kept_video_mb": status.highlight_video_bytes as f64 / 1e6});
    if keep_s > 0.0 {
        let t0 = Instant::now();
        let phone2act_recorder::Highlight::Saved(s) = rec.save_highlight("benchmark", "", false, None)?
        else {
            return Err("the kept seconds were not saved".into());
        };
        out["save_ms"] = serde_json::json!(t0.elapsed().as_secs_f64() * 1e3);
        out["frames"] = serde_json::json!(s.length_frames);
        out["dropped"] = serde_json::json!(s.dropped_frames);
        out["late"] = serde_json::json!(s.late_ticks);
        out["paused"] = serde_json::json!(s.paused_ticks);
    }
    out["peak_rss_mb"] = serde_json::json!(peak_rss_mb());
    rec.close()?;
    drop(threads);
    println!("{out}");
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Runs of the highlight section: codec, cameras, fps, and each run's `highlight_s` (0: off) and idle seconds.
type HighlightRuns = Vec<(&'static str, usize, u32, Vec<(f64, f64)>)>;

/// Peak RSS of an idle recorder with the last seconds kept (`highlight_s`) and without, and the episode saved
/// from them.
fn highlight_memory(o: &Opts) -> Res<()> {
    println!(
        "\n## keeping the last seconds while idle (640x480 cameras; one process per run, peak RSS of that process)"
    );
    println!(
        "| load | highlight_s | idle s | kept s | kept video MB | peak RSS MB | saved frames | dropped | late | paused | save ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let exe = std::env::current_exe()?;
    let mut runs: HighlightRuns = vec![
        ("av1", 2, 20, vec![(0.0, 20.0), (10.0, 20.0), (60.0, 70.0)]),
        ("av1", 3, 20, vec![(0.0, 20.0), (10.0, 20.0)]),
        ("h264", 3, 30, vec![(0.0, 20.0), (10.0, 20.0), (60.0, 70.0)]),
    ];
    if o.quick {
        runs = vec![("av1", 2, 20, vec![(0.0, 10.0), (5.0, 10.0)])];
    }
    for (codec, ncams, fps, keeps) in runs {
        let load = format!("{ncams} x {codec} @ {fps} fps");
        for (keep_s, idle_s) in keeps {
            let args = [
                "--rss-highlight",
                &keep_s.to_string(),
                &idle_s.to_string(),
                codec,
                &ncams.to_string(),
                &fps.to_string(),
            ];
            let v = match child_json(&exe, &args)? {
                Ok(v) => v,
                Err(e) => {
                    println!("| {load} | {keep_s} | {idle_s} | failed: {e} |");
                    continue;
                }
            };
            let num = |k: &str| v[k].as_f64().map_or("-".to_owned(), |x| format!("{x:.0}"));
            println!(
                "| {load} | {} | {idle_s} | {:.1} | {:.1} | {:.0} | {} | {} | {} | {} | {} |",
                if keep_s > 0.0 {
                    format!("{keep_s}")
                } else {
                    "off".into()
                },
                v["kept_s"].as_f64().unwrap_or(0.0),
                v["kept_video_mb"].as_f64().unwrap_or(0.0),
                v["peak_rss_mb"].as_f64().unwrap_or(0.0),
                num("frames"),
                num("dropped"),
                num("late"),
                num("paused"),
                num("save_ms"),
            );
        }
    }
    Ok(())
}

fn encode_speed(o: &Opts) -> Res<()> {
    let (w, h, fps) = (640u32, 480u32, 30u32);
    let n = if o.quick { 90 } else { 300 };
    println!(
        "\n## encode speed, same {n} frames (640x480 testsrc2), same settings (g=2, crf=30, yuv420p; SVT-AV1 preset 12; x264 default preset, B-frames as lerobot)"
    );
    // Capture the frames once from testsrc2 through the capture path.
    let slot = Arc::new(FrameSlot::default());
    let cam = spawn_av_capture(
        "src",
        AvCaptureConfig {
            pace_by_pts: false,
            ..AvCaptureConfig::lavfi_testsrc(w, h, fps)
        },
        Arc::clone(&slot),
    )?;
    let mut frames: Vec<Arc<Vec<u8>>> = Vec::new();
    let mut last_seq = None;
    let t0 = Instant::now();
    while frames.len() < n && t0.elapsed() < Duration::from_secs(30) {
        if let Some(f) = slot.latest()
            && last_seq != Some(f.seq)
        {
            last_seq = Some(f.seq);
            frames.push(Arc::clone(&f.rgb));
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    cam.stop();
    let dir = tempfile_dir("encode")?;
    let raw = dir.join("frames.rgb");
    {
        use std::io::Write;
        let mut f = std::io::BufWriter::new(std::fs::File::create(&raw)?);
        for fr in &frames {
            f.write_all(fr)?;
        }
    }
    let python = lerobot_python();
    println!(
        "| settings | phone2act fps (flush ms) | lerobot StreamingVideoEncoder fps | lerobot encode_video_frames (PNG dir) fps |"
    );
    println!("|---|---|---|---|");
    let rows = [
        ("av1, lerobot's settings", "av1:svtav1-params=", Some("libsvtav1")),
        (
            "h264, lerobot's settings (medium, B-frames)",
            "h264:preset=medium,bf=-1",
            Some("h264"),
        ),
        (
            "av1, phone2act default (+pred-struct=1:irefresh-type=2)",
            "av1",
            None,
        ),
        ("h264, phone2act default (veryfast, no B-frames)", "h264", None),
    ];
    for (label, ours, theirs) in rows {
        let settings = VideoSettings::parse(Some(ours), Format::V30)?;
        let t = Instant::now();
        let mut enc = VideoEncoder::create(&dir.join("ours.mp4"), w, h, fps, &settings)?;
        for f in &frames {
            enc.push_rgb(f, w, h)?;
        }
        let tf = Instant::now();
        enc.finish()?;
        let flush_ms = tf.elapsed().as_secs_f64() * 1e3;
        let ours_fps = frames.len() as f64 / t.elapsed().as_secs_f64();
        let (s_fps, p_fps) = match (&python, theirs) {
            (_, None) => ("-".to_owned(), "-".to_owned()),
            (None, Some(_)) => ("(lerobot venv not installed)".to_owned(), String::new()),
            (Some(py), Some(theirs)) => lerobot_encode(py, &raw, (w, h, fps), theirs)?,
        };
        println!("| {label} | {ours_fps:.0} ({flush_ms:.0}) | {s_fps} | {p_fps} |");
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Runs bench/lerobot_encode.py in the conformance venv; returns (streaming fps, PNG-path fps).
fn lerobot_encode(
    py: &Path,
    raw: &Path,
    (w, h, fps): (u32, u32, u32),
    vcodec: &str,
) -> Res<(String, String)> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("bench/lerobot_encode.py");
    let out = Command::new(py)
        .arg(script)
        .arg(raw)
        .args([w.to_string(), h.to_string(), fps.to_string(), vcodec.to_owned()])
        .env("HF_HUB_OFFLINE", "1")
        .env("SVT_LOG", "1")
        .output()?;
    let text = String::from_utf8_lossy(&out.stdout);
    let v: serde_json::Value = text
        .lines()
        .last()
        .and_then(|l| serde_json::from_str(l).ok())
        .unwrap_or_default();
    let fmt = |k: &str| {
        v[k].as_f64()
            .map_or_else(|| "n/a".to_owned(), |x| format!("{x:.0}"))
    };
    Ok((fmt("streaming_fps"), fmt("png_path_fps")))
}

fn lerobot_python() -> Option<PathBuf> {
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))?;
    let py = cache.join("phone2act/lerobot-venv/bin/python");
    py.exists().then_some(py)
}

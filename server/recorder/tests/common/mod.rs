//! Helpers shared by the recorder's integration tests.
#![allow(dead_code)] // each test binary uses a different subset

use parking_lot::Mutex;
use phone2act_clock::monotonic_ns;
use phone2act_dataset::{CameraSpec, DatasetSpec, Format};
use phone2act_recorder::synthetic::SyntheticRobot;
use phone2act_recorder::{Recorder, RecorderStatus, RobotSample, RobotSource};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A robot source the test controls: fresh samples (stamped now) unless silenced.
#[derive(Default)]
pub(crate) struct ManualRobot {
    pub silent: Mutex<bool>,
    pub frozen_at_ns: Mutex<Option<i64>>,
}

impl RobotSource for ManualRobot {
    fn sample(&self) -> Option<RobotSample> {
        if *self.silent.lock() {
            return None;
        }
        let mut s = SyntheticRobot.sample()?;
        if let Some(t) = *self.frozen_at_ns.lock() {
            s.capture_time_ns = t;
        }
        Some(s)
    }
}

impl ManualRobot {
    pub(crate) fn freeze(&self) {
        *self.frozen_at_ns.lock() = Some(monotonic_ns());
    }
}

pub(crate) fn spec(root: &Path, format: Format, cameras: &[&str], size: (u32, u32)) -> DatasetSpec {
    DatasetSpec {
        root: root.to_owned(),
        format,
        fps: 30,
        robot_type: "phone2act_sim".into(),
        video_codec: None,
        state_names: SyntheticRobot::state_names(),
        action_names: SyntheticRobot::action_names(),
        cameras: cameras
            .iter()
            .map(|n| CameraSpec {
                name: (*n).into(),
                width: size.0,
                height: size.1,
            })
            .collect(),
        modality: SyntheticRobot::modality(),
        success: false,
        intervention: false,
        provenance: serde_json::json!({"test": true}),
    }
}

/// Polls until `cond(status)` or panics after `timeout`.
pub(crate) fn wait_for(
    rec: &Recorder,
    timeout: Duration,
    what: &str,
    cond: impl Fn(&RecorderStatus) -> bool,
) -> RecorderStatus {
    let t0 = Instant::now();
    loop {
        let s = rec.status();
        if cond(&s) {
            return s;
        }
        assert!(
            t0.elapsed() < timeout,
            "timed out waiting for {what}; status {s:?}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

pub(crate) fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), to).unwrap();
        }
    }
}

/// Copies a finished dataset to `$PHONE2ACT_CONFORMANCE_DIR/<name>` (with what the test expects) so that
/// tests/conformance/run.sh loads it with the real lerobot. Returns the copy.
#[allow(clippy::needless_pass_by_value)] // callers build the JSON inline
pub(crate) fn publish_for_conformance(name: &str, root: &Path, expect: serde_json::Value) -> Option<PathBuf> {
    let dir = PathBuf::from(std::env::var_os("PHONE2ACT_CONFORMANCE_DIR")?);
    let dst = dir.join(name);
    let _ = std::fs::remove_dir_all(&dst);
    copy_dir(root, &dst);
    std::fs::write(dst.join("phone2act_expect.json"), expect.to_string()).unwrap();
    Some(dst)
}

pub(crate) fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

/// The cached lerobot venv's python, if the conformance venv was installed.
pub(crate) fn lerobot_python() -> Option<(PathBuf, PathBuf)> {
    let cache = std::env::var_os("PHONE2ACT_CACHE_DIR")
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("XDG_CACHE_HOME")
                .map(PathBuf::from)
                .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
                .map(|c| c.join("phone2act"))
        })?;
    let py = cache.join("lerobot-venv/bin/python");
    (py.exists() && cache.join("lerobot-venv/.phone2act-ready").exists())
        .then(|| (py, cache.join("lerobot-0.3.3")))
}

/// Runs tests/conformance/check.py on `dirs` with the real lerobot when the venv exists; returns None
/// when it does not (the datasets are still published for run.sh).
pub(crate) fn lerobot_check(dirs: &[PathBuf], v21: bool) -> Option<(bool, String)> {
    let (py, v21_dir) = lerobot_python()?;
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/conformance/check.py");
    let cache = tempfile::tempdir().unwrap();
    let mut cmd = std::process::Command::new(py);
    cmd.arg(script)
        .args(dirs)
        .env("HF_HUB_OFFLINE", "1")
        .env("HF_DATASETS_CACHE", cache.path());
    if v21 {
        cmd.env("PYTHONPATH", v21_dir);
    }
    let out = cmd.output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    Some((out.status.success(), text))
}

/// A camera three times faster than a recorder at `fps` whose frames differ everywhere: the grey level steps
/// by 37 per frame and a bar moves, so a reader that returns a neighbouring frame differs in every pixel.
pub(crate) fn distinct_camera(
    slot: &std::sync::Arc<phone2act_capture::camera::FrameSlot>,
    size: (u32, u32),
    fps: u32,
) -> phone2act_capture::camera::CaptureThread {
    phone2act_capture::camera::spawn_generated(
        "pairing",
        size.0,
        size.1,
        f64::from(fps * 3),
        move |seq, buf| {
            let (w, h) = (size.0 as usize, size.1 as usize);
            let grey = ((seq * 37) % 200 + 28) as u8;
            buf.clear();
            buf.resize(w * h * 3, grey);
            let bar = (seq as usize * 7) % w;
            for y in 0..h {
                for x in bar..(bar + 6).min(w) {
                    buf[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[255, 0, 0]);
                }
            }
        },
        std::sync::Arc::clone(slot),
    )
    .unwrap()
}

/// The parquet files under `dir`, recursively.
pub(crate) fn parquet_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        if e.file_type().unwrap().is_dir() {
            parquet_files(&e.path(), out);
        } else if e.path().extension().is_some_and(|x| x == "parquet") {
            out.push(e.path());
        }
    }
}

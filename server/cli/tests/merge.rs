//! `phone2act dataset merge` and `dataset compact` on datasets recorded by the real recorder (test-pattern
//! cameras, AV1), read back by phone2act's own verifier and, where the lerobot 0.6 venv exists
//! (tests/lerobot_plugins/setup-venv.sh), by lerobot itself: `LeRobotDataset` loads the result with every
//! frame pixel-equal to its input's, and lerobot's own `aggregate_datasets` on the same inputs gives the same
//! frames, tasks and statistics (tests/conformance/check_merge.py).
//!
//! Timing: recording sleeps for the episodes' length (real time at the dataset fps); nothing here asserts a
//! duration, so a loaded machine makes these tests slower, not red.

use phone2act_capture::camera::{FrameSlot, spawn_test_pattern};
use phone2act_dataset::{CameraSpec, DatasetSpec, Format};
use phone2act_recorder::Recorder;
use phone2act_recorder::synthetic::SyntheticRobot;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;
use std::time::Duration;

const BIN: &str = env!("CARGO_BIN_EXE_phone2act");

/// Records `tasks.len()` episodes of about `seconds` each into a new dataset at `root`, as station `station`.
fn record(root: &Path, station: &str, fps: u32, cameras: &[&str], tasks: &[&str], seconds: f64) {
    record_as(Format::V30, root, station, fps, cameras, tasks, seconds);
}

fn record_as(
    format: Format,
    root: &Path,
    station: &str,
    fps: u32,
    cameras: &[&str],
    tasks: &[&str],
    seconds: f64,
) {
    let mut slots = Vec::new();
    let mut threads = Vec::new();
    let mut specs = Vec::new();
    for name in cameras {
        let slot = Arc::new(FrameSlot::default());
        threads.push(spawn_test_pattern(name, 64, 64, f64::from(fps), Arc::clone(&slot)).unwrap());
        slots.push(((*name).to_owned(), slot));
        specs.push(CameraSpec {
            name: (*name).to_owned(),
            width: 64,
            height: 64,
        });
    }
    let spec = DatasetSpec {
        root: root.to_owned(),
        format,
        fps,
        robot_type: "phone2act_sim".into(),
        video_codec: None,
        state_names: SyntheticRobot::state_names(),
        action_names: SyntheticRobot::action_names(),
        cameras: specs,
        modality: SyntheticRobot::modality(),
        success: false,
        intervention: false,
        provenance: serde_json::json!({"station_id": station}),
    };
    let rec = Recorder::open(spec, Arc::new(SyntheticRobot), slots).unwrap();
    for task in tasks {
        rec.start_episode_by(task, &format!("operator-of-{station}"))
            .unwrap();
        std::thread::sleep(Duration::from_secs_f64(seconds));
        rec.stop_episode().unwrap();
    }
    rec.close().unwrap();
}

fn phone2act(args: &[&str]) -> Output {
    Command::new(BIN).args(args).env("SVT_LOG", "1").output().unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn read_json(p: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        if e.path().is_dir() {
            out.extend(files_under(&e.path()));
        } else {
            out.push(e.path());
        }
    }
    out.sort();
    out
}

/// The lerobot 0.6 venv's python, if it was installed (tests/lerobot_plugins/setup-venv.sh).
fn lerobot06_python() -> Option<PathBuf> {
    let cache = std::env::var_os("PHONE2ACT_CACHE_DIR")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/phone2act")))?;
    let venv = cache.join("lerobot06-venv");
    (venv.join(".phone2act-ready").exists()).then(|| venv.join("bin/python"))
}

/// Runs tests/conformance/check_merge.py; `None` (and a loud SKIPPED) without the lerobot venv.
fn lerobot_check(args: &[&Path]) -> Option<(bool, String)> {
    lerobot_check_with(args, None)
}

/// The same with lerobot 0.3.3 (v2.1) first on the path, as tests/conformance/run.sh runs it.
fn lerobot_check_with(args: &[&Path], pythonpath: Option<&Path>) -> Option<(bool, String)> {
    let Some(py) = lerobot06_python() else {
        eprintln!("lerobot check SKIPPED: no lerobot 0.6 venv (run tests/lerobot_plugins/setup-venv.sh)");
        return None;
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/conformance/check_merge.py");
    let cache = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(py);
    if let Some(p) = pythonpath {
        cmd.env("PYTHONPATH", p);
    }
    let out = cmd
        .arg(script)
        .args(args)
        .env("HF_HUB_OFFLINE", "1")
        .env("HF_DATASETS_OFFLINE", "1")
        .env("HF_DATASETS_CACHE", cache.path())
        .env("SVT_LOG", "1")
        .output()
        .unwrap();
    Some((out.status.success(), text(&out)))
}

#[test]
fn three_stations_merge_into_one_dataset_that_lerobot_loads_and_its_own_aggregate_agrees_with() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, c) = (
        dir.path().join("st-a"),
        dir.path().join("st-b"),
        dir.path().join("st-c"),
    );
    let cams = ["front", "wrist"];
    // A task shared by two stations, and one of each station's own: the merged task table has four.
    record(&a, "st-a", 20, &cams, &["pick the cube", "stack"], 0.5);
    record(&b, "st-b", 20, &cams, &["pick the cube", "pour"], 0.5);
    record(&c, "st-c", 20, &cams, &["wipe"], 0.5);
    let merged = dir.path().join("fleet");
    let out = phone2act(&["dataset", "merge", s(&a), s(&b), s(&c), "--out", s(&merged)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("5 episodes"), "{}", text(&out));
    let verify = phone2act(&["dataset", "verify", s(&merged)]);
    assert!(verify.status.success(), "{}", text(&verify));

    let info = read_json(&merged.join("meta/info.json"));
    assert_eq!(info["total_episodes"], 5);
    assert_eq!(info["total_tasks"], 4);
    // One data file, one metadata file and one video per camera: the inputs' 5 + 5 + 10 files compacted.
    let count = |sub: &str| files_under(&merged.join(sub)).len();
    assert_eq!(
        (count("data"), count("meta/episodes"), count("videos")),
        (1, 1, 2)
    );
    let prov = read_json(&merged.join("meta/phone2act_provenance.json"));
    let who: Vec<(String, String, String, u64)> = prov["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["station_id"].as_str().unwrap_or_default().to_owned(),
                e["operator"].as_str().unwrap_or_default().to_owned(),
                e["merged_from"]["dataset"]
                    .as_str()
                    .unwrap_or_default()
                    .to_owned(),
                e["merged_from"]["episode_index"].as_u64().unwrap(),
            )
        })
        .collect();
    let expect: Vec<(String, String, String, u64)> =
        [("st-a", 0), ("st-a", 1), ("st-b", 0), ("st-b", 1), ("st-c", 0)]
            .iter()
            .map(|(st, i)| {
                (
                    (*st).to_owned(),
                    format!("operator-of-{st}"),
                    dir.path().join(st).display().to_string(),
                    *i,
                )
            })
            .collect();
    assert_eq!(who, expect, "each episode keeps its station, operator and source");
    assert_eq!(
        std::fs::read(merged.join("meta/modality.json")).unwrap(),
        std::fs::read(a.join("meta/modality.json")).unwrap(),
        "GR00T's modality.json, the same in every input, carried over"
    );

    let agg = dir.path().join("lerobot-aggregate");
    if let Some((ok, report)) = lerobot_check(&[&merged, &a, &b, &c, Path::new("--lerobot-aggregate"), &agg])
    {
        assert!(ok, "{report}");
    }
}

#[test]
fn inputs_that_differ_are_refused_by_name_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let base = dir.path().join("base");
    let slow = dir.path().join("slow");
    let one_cam = dir.path().join("one-cam");
    record(&base, "st-a", 20, &["front", "wrist"], &["pick"], 0.3);
    record(&slow, "st-b", 10, &["front", "wrist"], &["pick"], 0.3);
    record(&one_cam, "st-c", 20, &["front"], &["pick"], 0.3);
    // GR00T's modality.json must be the same in every input: a station configured with other groups (here its
    // gripper named apart) is refused, and so is one without the file, each with what to do.
    let regrouped = dir.path().join("regrouped");
    record(&regrouped, "st-d", 20, &["front", "wrist"], &["pick"], 0.3);
    let path = regrouped.join("meta/modality.json");
    let mut m = read_json(&path);
    let g = m["action"]["main_gripper"].clone();
    m["action"].as_object_mut().unwrap().remove("main_gripper");
    m["action"]["gripper"] = g;
    std::fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let without = dir.path().join("without");
    record(&without, "st-e", 20, &["front", "wrist"], &["pick"], 0.3);
    std::fs::remove_file(without.join("meta/modality.json")).unwrap();
    let out = dir.path().join("out");
    let before = files_under(dir.path());
    for (other, needle) in [
        (&slow, "fps"),
        (&one_cam, "observation.images.wrist"),
        (&regrouped, "their meta/modality.json differ"),
        (&without, "only one of them has a meta/modality.json"),
    ] {
        let o = phone2act(&["dataset", "merge", s(&base), s(other), "--out", s(&out)]);
        assert!(!o.status.success(), "{}", text(&o));
        assert!(
            text(&o).contains("cannot be merged") && text(&o).contains(needle),
            "names the difference ({needle}): {}",
            text(&o)
        );
        assert!(!out.exists(), "a refused merge leaves no output");
        assert_eq!(files_under(dir.path()), before, "and no scratch files");
    }
    // An output that already holds something is never written into.
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("keep.txt"), b"mine").unwrap();
    let o = phone2act(&["dataset", "merge", s(&base), "--out", s(&out)]);
    assert!(
        !o.status.success() && text(&o).contains("already exists"),
        "{}",
        text(&o)
    );
    assert_eq!(std::fs::read(out.join("keep.txt")).unwrap(), b"mine");
    assert_eq!(files_under(&out).len(), 1);
}

#[test]
fn compact_repacks_one_file_per_episode_into_files_within_the_size_limits() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("station");
    let tasks = ["a", "b", "a", "b", "a", "b"];
    record(&src, "st-a", 20, &["front"], &tasks, 0.4);
    let videos_in = files_under(&src.join("videos"));
    assert_eq!(
        videos_in.len(),
        6,
        "the recorder writes one video file per episode"
    );
    let sizes: Vec<u64> = videos_in
        .iter()
        .map(|p| std::fs::metadata(p).unwrap().len())
        .collect();
    // A limit of two and a half of the largest episode's video: at least two episodes a file, never all six.
    let limit_mb = 2.5 * *sizes.iter().max().unwrap() as f64 / 1e6;
    let out = dir.path().join("compact");
    let o = phone2act(&[
        "dataset",
        "compact",
        s(&src),
        "--out",
        s(&out),
        "--video-file-size-mb",
        &format!("{limit_mb}"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let verify = phone2act(&["dataset", "verify", s(&out)]);
    assert!(verify.status.success(), "{}", text(&verify));
    let videos_out = files_under(&out.join("videos"));
    assert!(
        (2..=3).contains(&videos_out.len()),
        "6 episode videos into files of at most {limit_mb} MB: {videos_out:?}"
    );
    assert_eq!(files_under(&out.join("data")).len(), 1);
    assert_eq!(files_under(&out.join("meta/episodes")).len(), 1);
    let info = read_json(&out.join("meta/info.json"));
    assert_eq!(info["total_episodes"], 6);
    assert_eq!(info["total_tasks"], 2);
    if let Some((ok, report)) = lerobot_check(&[&out, &src]) {
        assert!(ok, "{report}");
    }
}

#[test]
fn v21_gr00t_datasets_merge_into_one_that_lerobot_0_3_3_loads() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("st-a"), dir.path().join("st-b"));
    record_as(Format::V21, &a, "st-a", 20, &["front"], &["pick", "place"], 0.4);
    record_as(Format::V21, &b, "st-b", 20, &["front"], &["place", "wipe"], 0.4);
    let merged = dir.path().join("fleet");
    let out = phone2act(&["dataset", "merge", s(&a), s(&b), "--out", s(&merged)]);
    assert!(out.status.success(), "{}", text(&out));
    let verify = phone2act(&["dataset", "verify", s(&merged)]);
    assert!(verify.status.success(), "{}", text(&verify));
    let info = read_json(&merged.join("meta/info.json"));
    assert_eq!(
        (info["total_episodes"].as_u64(), info["total_tasks"].as_u64()),
        (Some(4), Some(3))
    );
    assert_eq!(info["total_videos"], 4);
    assert_eq!(
        std::fs::read(merged.join("meta/modality.json")).unwrap(),
        std::fs::read(a.join("meta/modality.json")).unwrap(),
        "GR00T's modality.json carried over"
    );
    let lines: Vec<Value> = std::fs::read_to_string(merged.join("meta/episodes_stats.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines[3]["episode_index"], 3);
    assert_eq!(
        lines[3]["stats"]["episode_index"]["min"],
        serde_json::json!([3]),
        "renumbered stats"
    );
    // A v3.0 input among v2.1 ones is refused by name.
    let v30 = dir.path().join("v30");
    record(&v30, "st-c", 20, &["front"], &["pick"], 0.3);
    let o = phone2act(&[
        "dataset",
        "merge",
        s(&a),
        s(&v30),
        "--out",
        s(&dir.path().join("mixed")),
    ]);
    assert!(!o.status.success() && text(&o).contains("v3.0"), "{}", text(&o));
    assert!(!dir.path().join("mixed").exists());
    let cache =
        lerobot06_python().and_then(|py| Some(py.parent()?.parent()?.parent()?.join("lerobot-0.3.3")));
    if let Some(v21) = cache.filter(|p| p.exists()) {
        if let Some((ok, report)) = lerobot_check_with(&[&merged, &a, &b], Some(&v21)) {
            assert!(ok, "{report}");
        }
    } else {
        eprintln!("lerobot 0.3.3 check SKIPPED: no lerobot-0.3.3 beside the lerobot 0.6 venv");
    }
}

fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap().flatten() {
        let to = dst.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), to).unwrap();
        }
    }
}

/// Datasets lerobot itself wrote (tests/fixtures/lerobot_sample_v30: several episodes per video file, a
/// `next.done` column, lerobot's own tasks table) merge as its `aggregate_datasets` merges them.
#[test]
fn datasets_lerobot_wrote_merge_as_its_own_aggregate_does() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/lerobot_sample_v30");
    let (a, b) = (dir.path().join("x"), dir.path().join("y"));
    copy_dir(&fixture, &a);
    copy_dir(&fixture, &b);
    let merged = dir.path().join("m");
    let out = phone2act(&["dataset", "merge", s(&a), s(&b), "--out", s(&merged)]);
    assert!(out.status.success(), "{}", text(&out));
    let verify = phone2act(&["dataset", "verify", s(&merged)]);
    assert!(verify.status.success(), "{}", text(&verify));
    let info = read_json(&merged.join("meta/info.json"));
    assert_eq!(
        (info["total_episodes"].as_u64(), info["total_frames"].as_u64()),
        (Some(6), Some(60))
    );
    // The fixture's three episodes share one video file a camera; the merge appends the two files.
    assert_eq!(files_under(&merged.join("videos")).len(), 2);
    let agg = dir.path().join("lerobot-aggregate");
    if let Some((ok, report)) = lerobot_check(&[&merged, &a, &b, Path::new("--lerobot-aggregate"), &agg]) {
        assert!(ok, "{report}");
    }
}

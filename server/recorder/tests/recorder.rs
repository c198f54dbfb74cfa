//! End-to-end recorder tests: real cameras threads, real encoders, the datasets read back from disk, and
//! published for the lerobot conformance run.

mod common;

use common::{ManualRobot, publish_for_conformance, read_json, spec, wait_for};
use phone2act_capture::camera::{FrameSlot, spawn_generated, spawn_test_pattern};
use phone2act_dataset::events::EventKind;
use phone2act_dataset::parquet_io::read_rows;
use phone2act_dataset::{Format, RecorderError};
use phone2act_recorder::{Phase, Recorder};
use serde_json::json;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

const T: Duration = Duration::from_secs(20);

struct Rig {
    robot: Arc<ManualRobot>,
    slots: Vec<(String, Arc<FrameSlot>)>,
    cams: Vec<phone2act_capture::camera::CaptureThread>,
}

fn rig(names: &[&str], size: (u32, u32), cam_fps: f64) -> Rig {
    let mut slots = Vec::new();
    let mut cams = Vec::new();
    for n in names {
        let slot = Arc::new(FrameSlot::default());
        cams.push(spawn_test_pattern(n, size.0, size.1, cam_fps, Arc::clone(&slot)).unwrap());
        slots.push(((*n).to_owned(), slot));
    }
    Rig {
        robot: Arc::new(ManualRobot::default()),
        slots,
        cams,
    }
}

fn open(root: &Path, format: Format, rig: &Rig, size: (u32, u32)) -> Recorder {
    let names: Vec<&str> = rig.slots.iter().map(|(n, _)| n.as_str()).collect();
    Recorder::open(
        spec(root, format, &names, size),
        rig.robot.clone(),
        rig.slots.clone(),
    )
    .unwrap()
}

fn record(rec: &Recorder, task: &str, frames: u64) -> phone2act_dataset::EpisodeSummary {
    rec.start_episode(task).unwrap();
    wait_for(rec, T, "frames", |s| s.frames_recorded >= frames);
    rec.stop_episode().unwrap()
}

/// Checks the data rows of every episode: contiguous index, timestamps by the rule of `timestamp_s`.
#[allow(clippy::float_cmp)] // exactness is the point
fn check_v30_rows(root: &Path, fps: u32) -> u64 {
    let info = read_json(&root.join("meta/info.json"));
    let mut files: Vec<_> = walk(&root.join("data"))
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .collect();
    files.sort();
    let mut index = 0i64;
    let mut last_ep = -1i64;
    let mut fi_expected = 0i64;
    for f in files {
        for r in read_rows(&f).unwrap() {
            assert_eq!(r.index, index, "{}", f.display());
            if r.episode_index != last_ep {
                assert_eq!(r.episode_index, last_ep + 1);
                last_ep = r.episode_index;
                fi_expected = 0;
            }
            assert_eq!(r.frame_index, fi_expected);
            assert_eq!(
                r.timestamp,
                phone2act_dataset::dataset::timestamp_s(r.frame_index as u64, fps)
            );
            fi_expected += 1;
            index += 1;
        }
    }
    assert_eq!(info["total_frames"].as_i64().unwrap(), index);
    assert_eq!(info["total_episodes"].as_i64().unwrap(), last_ep + 1);
    index as u64
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            if e.file_type().unwrap().is_dir() {
                out.extend(walk(&e.path()));
            } else {
                out.push(e.path());
            }
        }
    }
    out
}

/// GR00T's `meta/modality.json` of the test spec's one arm (`main`: 12 state values, 6 delta axes and a gripper).
fn check_modality(root: &Path, camera: &str) {
    let modality = read_json(&root.join("meta/modality.json"));
    assert_eq!(modality["state"]["main_arm"], json!({"start": 0, "end": 12}));
    assert_eq!(
        modality["action"]["main_gripper"],
        json!({"start": 6, "end": 7, "absolute": true})
    );
    assert_eq!(
        modality["action"]["main_arm"],
        json!({"start": 0, "end": 6, "absolute": false}),
        "a delta group is relative: GR00T pads it with zero past the episode's end"
    );
    assert_eq!(
        modality["video"][camera]["original_key"],
        format!("observation.images.{camera}")
    );
    assert_eq!(
        modality["annotation"]["human.task_description"]["original_key"],
        "task_index"
    );
}

#[test]
fn v30_records_resumes_and_appends() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("v30");
    let size = (64, 64);
    let rig = rig(&["front", "wrist"], size, 30.0);
    let rec = open(&root, Format::V30, &rig, size);
    let a = record(&rec, "pick the red cube", 12);
    let b = record(&rec, "place it in the bowl", 9);
    assert_eq!((a.index, b.index), (0, 1));
    assert!(a.length_frames >= 12 && b.length_frames >= 9);
    assert_eq!(a.dropped_frames + b.dropped_frames, 0);
    assert!((a.duration_s - a.length_frames as f64 / 30.0).abs() < 1e-12);
    let st = rec.status();
    assert_eq!(
        (st.phase, st.episodes_saved, st.episode_index),
        (Phase::Idle, 2, 2)
    );
    rec.close().unwrap();

    // Resume: same spec appends.
    let rec = open(&root, Format::V30, &rig, size);
    assert_eq!(rec.status().episodes_saved, 2);
    assert_eq!(rec.episodes().len(), 2);
    let c = record(&rec, "pick the red cube", 6);
    assert_eq!(c.index, 2);
    rec.close().unwrap();

    let frames = check_v30_rows(&root, 30);
    assert_eq!(frames, a.length_frames + b.length_frames + c.length_frames);
    let info = read_json(&root.join("meta/info.json"));
    assert_eq!(info["total_tasks"], 2);
    assert_eq!(
        info["features"]["observation.images.front"]["info"]["video.codec"],
        "av1"
    );
    let stats = read_json(&root.join("meta/stats.json"));
    assert_eq!(stats["index"]["count"], json!([frames]));
    assert_eq!(
        stats["observation.images.wrist"]["mean"]
            .as_array()
            .unwrap()
            .len(),
        3
    );
    let prov = read_json(&root.join("meta/phone2act_provenance.json"));
    assert_eq!(prov["episodes"].as_array().unwrap().len(), 3);
    assert_eq!(prov["config"]["test"], true);
    // GR00T's layout file rides along in v3.0 too, the same as v2.1 writes it.
    check_modality(&root, "wrist");
    let report = phone2act_dataset::verify::verify(&root);
    assert!(report.problems.is_empty(), "{:?}", report.problems);
    assert!(!root.join(".phone2act-staging").exists());
    publish_for_conformance(
        "recorder-v30-resume",
        &root,
        json!({"episodes": 3, "tasks": ["pick the red cube", "place it in the bowl"]}),
    );
}

#[test]
fn v21_gr00t_dataset_has_modality_and_stats() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("v21");
    let size = (48, 32);
    let rig = rig(&["webcam"], size, 30.0);
    let rec = open(&root, Format::V21, &rig, size);
    let a = record(&rec, "stack the blocks", 10);
    let b = record(&rec, "stack the blocks", 7);
    rec.close().unwrap();
    let info = read_json(&root.join("meta/info.json"));
    assert_eq!(info["codebase_version"], "v2.1");
    assert_eq!(info["total_videos"], 2);
    assert_eq!(
        info["features"]["observation.images.webcam"]["info"]["video.codec"],
        "h264"
    );
    check_modality(&root, "webcam");
    let stats = read_json(&root.join("meta/stats.json"));
    for col in [
        "observation.state",
        "action",
        "timestamp",
        "frame_index",
        "episode_index",
        "index",
        "task_index",
    ] {
        let keys: Vec<&String> = stats[col].as_object().unwrap().keys().collect();
        assert_eq!(keys.len(), 6, "{col}: {keys:?}");
    }
    let rows = read_rows(&root.join("data/chunk-000/episode_000001.parquet")).unwrap();
    assert_eq!(rows.len() as u64, b.length_frames);
    assert_eq!(rows[0].index as u64, a.length_frames);
    let episodes = std::fs::read_to_string(root.join("meta/episodes.jsonl")).unwrap();
    assert_eq!(episodes.lines().count(), 2);
    publish_for_conformance(
        "recorder-v21-gr00t",
        &root,
        json!({"episodes": 2, "tasks": ["stack the blocks"]}),
    );
}

#[test]
fn resuming_with_a_different_config_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let size = (64, 64);
    let rig = rig(&["front"], size, 30.0);
    let rec = open(&root, Format::V30, &rig, size);
    record(&rec, "task", 3);
    rec.close().unwrap();
    let mut s = spec(&root, Format::V30, &["front"], size);
    s.fps = 20;
    let e = Recorder::open(s, rig.robot.clone(), rig.slots.clone())
        .err()
        .unwrap();
    assert!(
        e.to_string().contains("was recorded at 30 fps, config says 20"),
        "{e}"
    );
    let mut s = spec(&root, Format::V30, &["front"], size);
    s.state_names.push("extra_joint".into());
    let e = Recorder::open(s, rig.robot.clone(), rig.slots.clone())
        .err()
        .unwrap();
    assert!(matches!(e, RecorderError::FeatureMismatch { .. }), "{e}");
    assert!(e.to_string().contains("observation.state"), "{e}");
    let e = Recorder::open(
        spec(&root, Format::V21, &["front"], size),
        rig.robot.clone(),
        rig.slots.clone(),
    )
    .err()
    .unwrap();
    assert!(matches!(e, RecorderError::FormatMismatch { .. }), "{e}");
    let e = Recorder::open(
        spec(&root, Format::V30, &["front", "side"], size),
        rig.robot.clone(),
        rig.slots.clone(),
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("side"), "{e}");
    // The dataset is untouched by the refused opens.
    let info = read_json(&root.join("meta/info.json"));
    assert_eq!(info["total_episodes"], 1);
}

#[test]
fn bad_input_gets_a_clear_status_and_leaves_the_dataset_intact() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("bad");
    let size = (64, 64);
    let rig = rig(&["front"], size, 30.0);
    let rec = open(&root, Format::V30, &rig, size);
    record(&rec, "good episode", 5);

    // A 10 kB task text.
    let long = "x".repeat(10 * 1024);
    let e = rec.start_episode(&long).unwrap_err();
    assert!(matches!(e, RecorderError::TaskTooLong { len: 10240, .. }), "{e}");
    assert_eq!(rec.status().phase, Phase::Idle);
    assert!(matches!(
        rec.start_episode("   ").unwrap_err(),
        RecorderError::EmptyTask
    ));
    assert!(matches!(
        rec.stop_episode().unwrap_err(),
        RecorderError::NotRecording
    ));

    // An episode with no frames: the robot never reports, so every tick is paused.
    *rig.robot.silent.lock() = true;
    rec.start_episode("nothing").unwrap();
    let s = wait_for(&rec, T, "pause", |s| s.phase == Phase::Paused);
    assert!(s.warning.as_deref().unwrap().contains("robot"), "{s:?}");
    assert!(matches!(
        rec.start_episode("again").unwrap_err(),
        RecorderError::AlreadyRecording(1)
    ));
    let e = rec.stop_episode().unwrap_err();
    assert!(matches!(e, RecorderError::EmptyEpisode(1)), "{e}");
    let s = rec.status();
    assert_eq!(s.phase, Phase::Idle);
    assert!(s.warning.unwrap().contains("no frames"));
    *rig.robot.silent.lock() = false;

    // Discard.
    rec.start_episode("discard me").unwrap();
    wait_for(&rec, T, "frames", |s| s.frames_recorded >= 3);
    assert!(rec.discard_episode().unwrap() >= 3);
    let last = record(&rec, "good episode", 4);
    assert_eq!(last.index, 1, "empty and discarded episodes take no index");
    rec.close().unwrap();
    check_v30_rows(&root, 30);
    publish_for_conformance(
        "recorder-bad-input",
        &root,
        json!({"episodes": 2, "tasks": ["good episode"]}),
    );
}

#[test]
fn a_camera_that_dies_pauses_the_episode_and_a_slow_one_is_held() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("cam");
    let size = (64, 64);
    let mut rig = rig(&["front", "slow"], size, 30.0);
    // Replace "slow" with a 10 fps camera: the 30 fps recorder holds its frames (counted, not paused).
    let slow = Arc::new(FrameSlot::default());
    rig.cams[1] = spawn_test_pattern("slow", size.0, size.1, 10.0, Arc::clone(&slow)).unwrap();
    rig.slots[1].1 = slow;
    let rec = open(&root, Format::V30, &rig, size);
    rec.start_episode("camera test").unwrap();
    let s = wait_for(&rec, T, "frames", |s| s.frames_recorded >= 15);
    assert!(s.held_ticks >= 5, "{s:?}");
    assert_eq!(s.paused_ticks, 0, "{s:?}");
    let front = rig.cams.remove(0);
    front.stop();
    let s = wait_for(&rec, T, "pause", |s| s.phase == Phase::Paused);
    assert!(s.warning.as_deref().unwrap().contains("camera front"), "{s:?}");
    let frozen = s.frames_recorded;
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(rec.status().frames_recorded, frozen, "no frames while paused");
    let saved = rec.stop_episode().unwrap();
    assert_eq!(saved.length_frames, frozen);
    assert!(saved.paused_ticks > 0 && saved.held_ticks >= 5);
    rec.close().unwrap();
    check_v30_rows(&root, 30);
    let prov = read_json(&root.join("meta/phone2act_provenance.json"));
    assert!(prov["episodes"][0]["paused_ticks"].as_u64().unwrap() > 0);
    publish_for_conformance("recorder-camera-dies", &root, json!({"episodes": 1}));
}

#[test]
fn a_stale_robot_is_held_then_pauses() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("stale");
    let size = (64, 64);
    let rig = rig(&["front"], size, 30.0);
    let rec = open(&root, Format::V30, &rig, size);
    rec.start_episode("stale robot").unwrap();
    wait_for(&rec, T, "frames", |s| s.frames_recorded >= 3);
    rig.robot.freeze();
    let s = wait_for(&rec, T, "pause", |s| s.phase == Phase::Paused);
    assert!(s.held_ticks >= 3, "held within the 0.25 s tolerance first: {s:?}");
    // Frozen for more than 0.1 s (the sample tolerance) and up to 0.25 s: recorded, but counted as late.
    assert!(s.late_ticks >= 1, "{s:?}");
    assert!(s.warning.unwrap().contains("robot sample has sent nothing for"));
    *rig.robot.frozen_at_ns.lock() = None;
    let s = wait_for(&rec, T, "resume", |s| s.phase == Phase::Recording);
    assert!(s.warning.unwrap().contains("resumed"));
    wait_for(&rec, T, "a frame after the pause", |t| {
        t.frames_recorded > s.frames_recorded
    });
    let saved = rec.stop_episode().unwrap();
    // The sidecar says where the episode's time jumps, by how many ticks, and which frames were late.
    let events = phone2act_dataset::events::read_events(&root, 0).unwrap().unwrap();
    let kinds = |k| events.iter().filter(move |e| e.kind == k);
    let paused: Vec<_> = kinds(EventKind::Paused).collect();
    assert_eq!(paused.len(), 1, "{events:?}");
    assert_eq!(paused[0].count, saved.paused_ticks);
    assert!(
        paused[0].detail.contains("robot sample has sent nothing"),
        "{events:?}"
    );
    assert_eq!(kinds(EventKind::LateTick).count() as u64, saved.late_ticks);
}

#[test]
fn rerecord_restarts_the_take_and_never_deletes_saved_work() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("rr");
    let size = (64, 64);
    let rig = rig(&["front"], size, 30.0);
    for format in [Format::V30, Format::V21] {
        let root = root.join(format.codebase_version());
        let rec = open(&root, format, &rig, size);
        record(&rec, "first", 4);
        record(&rec, "second", 8);
        // While idle: refused, and both saved episodes stay.
        let e = rec.rerecord(None).unwrap_err();
        assert!(matches!(e, RecorderError::NothingToRerecord), "{e}");
        assert_eq!(rec.episodes().len(), 2);
        rec.start_episode("third").unwrap();
        wait_for(&rec, T, "frames", |s| s.frames_recorded >= 3);
        // A task that is refused discards nothing.
        let e = rec.rerecord(Some(&"x".repeat(1 << 20))).unwrap_err();
        assert!(matches!(e, RecorderError::TaskTooLong { .. }), "{e}");
        let st = rec.status();
        assert_eq!((st.phase, st.task.as_str()), (Phase::Recording, "third"));
        assert!(st.frames_recorded >= 3);
        // While recording: restarts the take, same index, same task unless given.
        let st = rec.rerecord(None).unwrap();
        assert_eq!((st.episode_index, st.task.as_str()), (2, "third"));
        let st = rec.rerecord(Some("third, take 3")).unwrap();
        assert_eq!(st.episode_index, 2);
        wait_for(&rec, T, "frames", |s| s.frames_recorded >= 5);
        let s = rec.stop_episode().unwrap();
        assert_eq!((s.index, s.task.as_str()), (2, "third, take 3"));
        assert_eq!(rec.episodes().len(), 3);
        rec.close().unwrap();
        let info = read_json(&root.join("meta/info.json"));
        assert_eq!(info["total_episodes"], 3);
        if format == Format::V30 {
            check_v30_rows(&root, 30);
        } else {
            let lines = std::fs::read_to_string(root.join("meta/episodes.jsonl")).unwrap();
            assert_eq!(lines.lines().count(), 3);
            assert!(lines.contains("third, take 3") && !lines.contains("\"third\""));
        }
        publish_for_conformance(
            &format!("recorder-rerecord-{}", format.codebase_version()),
            &root,
            json!({"episodes": 3, "tasks": ["first", "second", "third, take 3"]}),
        );
    }
}

#[test]
fn watch_reports_phase_changes() {
    let dir = tempfile::tempdir().unwrap();
    let size = (64, 64);
    let rig = rig(&["front"], size, 30.0);
    let rec = open(&dir.path().join("w"), Format::V30, &rig, size);
    let v0 = rec.status().version;
    let r = &rec;
    std::thread::scope(|s| {
        let h = s.spawn(move || r.watch(v0, Duration::from_secs(5)));
        std::thread::sleep(Duration::from_millis(50));
        r.start_episode("watch").unwrap();
        let st = h.join().unwrap();
        assert!(st.version > v0);
        assert_eq!(st.phase, Phase::Recording);
    });
    wait_for(&rec, T, "frames", |s| s.frames_recorded >= 2);
    rec.stop_episode().unwrap();
}

#[test]
fn a_full_disk_fails_the_episode_and_keeps_the_dataset() {
    struct Unmount(std::path::PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(&self.0).status();
        }
    }
    // Needs a small filesystem: a 4 MB tmpfs (root only; skipped with a note elsewhere).
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("mnt");
    std::fs::create_dir_all(&mnt).unwrap();
    let ok = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=4m", "tmpfs"])
        .arg(&mnt)
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        eprintln!("SKIPPED: cannot mount a tmpfs here (needs root) to simulate a full disk");
        return;
    }
    let _guard = Unmount(mnt.clone());
    let root = mnt.join("ds");
    let size = (160, 120);
    let mut rig = rig(&[], size, 30.0);
    // Noise does not compress: lossless H.264 of it fills the disk within a couple of seconds.
    let slot = Arc::new(FrameSlot::default());
    let mut x = 0x2545_f491_u32;
    rig.cams.push(
        spawn_generated(
            "front",
            size.0,
            size.1,
            30.0,
            move |_, buf| {
                buf.clear();
                buf.extend((0..size.0 * size.1 * 3).map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    x as u8
                }));
            },
            Arc::clone(&slot),
        )
        .unwrap(),
    );
    rig.slots.push(("front".into(), slot));
    let mut s = spec(&root, Format::V30, &["front"], size);
    s.video_codec = Some("h264:crf=0,preset=ultrafast".into());
    let rec = Recorder::open(s, rig.robot.clone(), rig.slots.clone()).unwrap();
    let good = record(&rec, "fits", 3);
    rec.start_episode("does not fit").unwrap();
    let st = wait_for(&rec, Duration::from_mins(1), "disk full", |s| {
        s.warning.as_deref().is_some_and(|w| w.contains("failed"))
    });
    assert!(st.warning.unwrap().contains("cannot be saved"));
    let e = rec.stop_episode().unwrap_err();
    assert!(matches!(e, RecorderError::DiskFull { .. }), "{e}");
    assert!(e.to_string().contains("disk full"), "{e}");
    let s = rec.status();
    assert_eq!(s.phase, Phase::Idle);
    assert!(s.warning.unwrap().contains("not saved"));
    // The staging files are gone, so the next episode has room again.
    let again = record(&rec, "fits again", 3);
    assert_eq!((good.index, again.index), (0, 1));
    rec.close().unwrap();
    check_v30_rows(&root, 30);
    publish_for_conformance(
        "recorder-disk-full",
        &root,
        json!({"episodes": 2, "tasks": ["fits", "fits again"]}),
    );
}

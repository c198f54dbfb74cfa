//! "Save the last N seconds" (`Recorder::save_highlight`, LeRobot's `highlight`): while idle the recorder keeps
//! the newest ticks and their video encoded; on demand they become an episode like any other. Every episode
//! here is checked by `verify` (timestamps from 0 paired with the video's frames, one video frame per row) and
//! published for the conformance suite (the real lerobot reads it, every step paired with its frame).

mod common;

use common::{ManualRobot, distinct_camera, publish_for_conformance, spec, wait_for};
use phone2act_capture::camera::FrameSlot;
use phone2act_dataset::dataset::timestamp_s;
use phone2act_dataset::readback::read_episode;
use phone2act_dataset::{Format, RecorderError};
use phone2act_recorder::{Highlight, Recorder};
use serde_json::json;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

const SIZE: (u32, u32) = (96, 64);
const FPS: u32 = 20;
/// Seconds kept: 40 frames at 20 fps.
const KEEP_S: f64 = 2.0;
/// Generous bound for waits on a loaded 2-core machine: each wait is for a few seconds of ticks, which the
/// recorder writes late but never skips (see `recorder`), so only a stalled recorder takes this long.
const WAIT: Duration = Duration::from_mins(1);

/// Frames of the first video stream of `path`, counted packet by packet.
fn video_frames(path: &Path) -> u64 {
    ffmpeg_next::init().unwrap();
    let mut input = ffmpeg_next::format::input(&path).unwrap();
    let stream = input
        .streams()
        .best(ffmpeg_next::media::Type::Video)
        .unwrap()
        .index();
    input.packets().filter(|(s, _)| s.index() == stream).count() as u64
}

/// Episode `index` read back: its frame indices are 0..n, its timestamps `timestamp_s(k)`, and its video (the
/// whole file in v2.1; its span in v3.0, where this test writes one episode per file) has n frames.
fn check_episode(root: &Path, index: u64) -> u64 {
    let ep = read_episode(root, index).unwrap();
    let n = ep.frame_index.len() as u64;
    let want: Vec<i64> = (0..n as i64).collect();
    assert_eq!(ep.frame_index, want, "episode {index}: frame indices");
    for v in &ep.videos {
        assert_eq!(video_frames(&v.path), n, "episode {index}: {}", v.path.display());
    }
    let mut data = Vec::new();
    common::parquet_files(&root.join("data"), &mut data);
    for file in data {
        for row in phone2act_dataset::parquet_io::read_rows(&file).unwrap() {
            if row.episode_index == index as i64 {
                let k = u64::try_from(row.frame_index).unwrap();
                assert_eq!(
                    row.timestamp.to_bits(),
                    timestamp_s(k, FPS).to_bits(),
                    "frame {k}"
                );
            }
        }
    }
    n
}

fn saved(h: Highlight) -> phone2act_dataset::EpisodeSummary {
    match h {
        Highlight::Saved(s) => s,
        Highlight::Recording(s) => panic!("expected a saved episode, got a recording: {s:?}"),
    }
}

fn highlights(format: Format, codec: Option<&str>, name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let slot = Arc::new(FrameSlot::default());
    let cam = distinct_camera(&slot, SIZE, FPS);
    let mut s = spec(&root, format, &["pairing"], SIZE);
    s.fps = FPS;
    s.success = true;
    s.video_codec = codec.map(str::to_owned);
    let robot = Arc::new(ManualRobot::default());
    let rec = Recorder::open(s, Arc::clone(&robot) as _, vec![("pairing".into(), slot)]).unwrap();
    assert!(matches!(
        rec.save_highlight("too early", "", false, None),
        Err(RecorderError::HighlightOff)
    ));
    rec.set_highlight(Some(KEEP_S));
    assert!((rec.status().highlight_s - KEEP_S).abs() < 1e-9);
    let keep = (KEEP_S * f64::from(FPS)) as u64;
    wait_for(&rec, WAIT, "the ring to fill", |s| {
        s.highlight_buffered_s >= KEEP_S
    });
    // Past full: the oldest ticks are evicted from here on (the episode must still start at a key frame).
    std::thread::sleep(Duration::from_millis(700));
    let status = rec.status();
    assert!(status.highlight_video_bytes > 0, "{status:?}");

    // 1. Saved at once, with the operator's outcome.
    let first = saved(
        rec.save_highlight("the last two seconds", "ana", false, Some(true))
            .unwrap(),
    );
    assert_eq!(first.index, 0);
    // From the oldest kept tick at a multiple of the GOP (2): N·fps frames, or one more.
    assert!(
        (keep..=keep + 1).contains(&first.length_frames),
        "{} frames",
        first.length_frames
    );
    assert_eq!(first.operator, "ana");
    assert_eq!(first.success, Some(true));
    assert_eq!(check_episode(&root, 0), first.length_frames);

    // 2. The ring starts again; kept and then recorded on (LeRobot's behaviour) until Stop.
    wait_for(&rec, WAIT, "the ring to fill again", |s| {
        s.highlight_buffered_s >= KEEP_S
    });
    let Highlight::Recording(status) = rec
        .save_highlight("kept and recorded on", "", true, None)
        .unwrap()
    else {
        panic!("expected a recording");
    };
    assert!(status.frames_recorded >= keep, "{status:?}");
    assert!(
        status.highlight_buffered_s.abs() < 1e-9,
        "no ring while recording"
    );
    // Refused while recording: the episode in progress holds these seconds.
    assert!(matches!(
        rec.save_highlight("again", "", false, None),
        Err(RecorderError::HighlightWhileRecording(1))
    ));
    wait_for(&rec, WAIT, "frames past the kept ones", |s| {
        s.frames_recorded >= keep + 30
    });
    let second = rec.stop_episode().unwrap();
    assert!(second.length_frames >= keep + 30);
    assert_eq!(check_episode(&root, 1), second.length_frames);

    // 3. A stale source empties the ring: a saved episode never spans a gap.
    wait_for(&rec, WAIT, "the ring after the stop", |s| {
        s.highlight_buffered_s > 0.0
    });
    *robot.silent.lock() = true;
    wait_for(&rec, WAIT, "the ring to empty", |s| {
        s.highlight_buffered_s.abs() < 1e-9
    });
    assert!(matches!(
        rec.save_highlight("nothing", "", false, None),
        Err(RecorderError::NothingBuffered)
    ));
    *robot.silent.lock() = false;
    wait_for(&rec, WAIT, "a second kept", |s| s.highlight_buffered_s >= 1.0);
    // Less than N seconds kept: all of it is saved.
    let third = saved(rec.save_highlight("what there is", "", false, None).unwrap());
    assert!(
        third.length_frames >= u64::from(FPS) - 1 && third.length_frames < keep + 2,
        "{} frames",
        third.length_frames
    );
    assert_eq!(check_episode(&root, 2), third.length_frames);

    // 4. A normal episode after the highlights is as before.
    rec.start_episode("a normal one").unwrap();
    wait_for(&rec, WAIT, "frames", |s| s.frames_recorded >= 10);
    let fourth = rec.stop_episode().unwrap();
    assert_eq!(check_episode(&root, 3), fourth.length_frames);

    rec.set_highlight(None);
    assert!(rec.status().highlight_s.abs() < 1e-9);
    assert!(matches!(
        rec.save_highlight("off", "", false, None),
        Err(RecorderError::HighlightOff)
    ));
    rec.close().unwrap();
    cam.stop();

    let report = phone2act_dataset::verify::verify(&root);
    assert!(report.ok(), "{}", report.problems.join("\n"));
    assert!(report.warnings.is_empty(), "{:?}", report.warnings);
    let frames = first.length_frames + second.length_frames + third.length_frames + fourth.length_frames;
    publish_for_conformance(
        name,
        &root,
        json!({
            "episodes": 4,
            "tasks": ["the last two seconds", "kept and recorded on", "what there is", "a normal one"],
            "frames": frames,
            "distinct_frames": true,
        }),
    );
}

#[test]
fn v30_av1_saves_the_last_seconds() {
    highlights(Format::V30, None, "highlight-v30-av1");
}

#[test]
fn v30_h264_saves_the_last_seconds() {
    highlights(Format::V30, Some("h264"), "highlight-v30-h264");
}

#[test]
fn v21_saves_the_last_seconds() {
    highlights(Format::V21, None, "highlight-v21");
}

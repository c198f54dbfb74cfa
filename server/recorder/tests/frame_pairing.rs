//! Datasets whose every recorded frame differs from its neighbours, in both formats and both codecs, for the
//! conformance suite's frame-pairing check (tests/conformance/check.py decodes step k with each reader and
//! compares it with frame k). Here: the timestamps and the video's presentation times pass `verify`.

mod common;

use common::{ManualRobot, publish_for_conformance, spec, wait_for};
use phone2act_capture::camera::FrameSlot;
use phone2act_dataset::Format;
use phone2act_dataset::dataset::{timestamp_pairs, timestamp_s};
use phone2act_dataset::parquet_io::read_rows;
use phone2act_recorder::Recorder;
use serde_json::json;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

const SIZE: (u32, u32) = (96, 64);
/// 20 fps: the rate at which the nearest float32 to k/fps falls below it most often (39 % of frames).
const FPS: u32 = 20;

fn distinct_camera(slot: &Arc<FrameSlot>) -> phone2act_capture::camera::CaptureThread {
    common::distinct_camera(slot, SIZE, FPS)
}

fn record(root: &Path, format: Format, codec: Option<&str>, episodes: &[u64]) -> u64 {
    record_at(root, format, codec, episodes, FPS)
}

fn record_at(root: &Path, format: Format, codec: Option<&str>, episodes: &[u64], fps: u32) -> u64 {
    let slot = Arc::new(FrameSlot::default());
    let cam = distinct_camera(&slot);
    let mut s = spec(root, format, &["pairing"], SIZE);
    s.fps = fps;
    s.video_codec = codec.map(str::to_owned);
    let rec = Recorder::open(
        s,
        Arc::new(ManualRobot::default()),
        vec![("pairing".into(), slot)],
    )
    .unwrap();
    let mut total = 0;
    for &frames in episodes {
        rec.start_episode("pair every frame").unwrap();
        wait_for(&rec, Duration::from_mins(1), "frames", |s| {
            s.frames_recorded >= frames
        });
        total += rec.stop_episode().unwrap().length_frames;
    }
    rec.close().unwrap();
    cam.stop();
    total
}

fn check(root: &Path) {
    let report = phone2act_dataset::verify::verify(root);
    assert!(report.ok(), "{}", report.problems.join("\n"));
    assert!(report.warnings.is_empty(), "{:?}", report.warnings);
    let mut data = Vec::new();
    common::parquet_files(&root.join("data"), &mut data);
    assert!(!data.is_empty());
    for file in data {
        for row in read_rows(&file).unwrap() {
            let k = u64::try_from(row.frame_index).unwrap();
            assert_eq!(
                row.timestamp.to_bits(),
                timestamp_s(k, FPS).to_bits(),
                "frame {k}"
            );
            timestamp_pairs(row.timestamp, k, FPS).unwrap();
        }
    }
}

#[test]
fn v30_av1_frames_pair_with_their_timestamps() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let frames = record(&root, Format::V30, None, &[50, 30]);
    check(&root);
    publish_for_conformance(
        "frame-pairing-v30-av1",
        &root,
        json!({"episodes": 2, "tasks": ["pair every frame"], "frames": frames, "distinct_frames": true}),
    );
}

#[test]
fn v30_h264_frames_pair_with_their_timestamps() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let frames = record(&root, Format::V30, Some("h264"), &[45]);
    check(&root);
    publish_for_conformance(
        "frame-pairing-v30-h264",
        &root,
        json!({"episodes": 1, "tasks": ["pair every frame"], "frames": frames, "distinct_frames": true}),
    );
}

#[test]
fn v21_frames_pair_with_their_timestamps() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let frames = record(&root, Format::V21, None, &[50, 25]);
    check(&root);
    publish_for_conformance(
        "frame-pairing-v21",
        &root,
        json!({"episodes": 2, "tasks": ["pair every frame"], "frames": frames, "distinct_frames": true}),
    );
}

/// A video whose frames are not presented at k / fps (here: a 30 fps recording under a 20 fps dataset's
/// name) pairs its timestamps with other frames: `verify` says which frame is presented when.
#[test]
fn verify_refuses_a_video_whose_frames_are_not_at_k_over_fps() {
    let dir = tempfile::tempdir().unwrap();
    let at_20 = dir.path().join("at20");
    let at_30 = dir.path().join("at30");
    record(&at_20, Format::V21, None, &[12]);
    record_at(&at_30, Format::V21, None, &[40], 30);
    check(&at_20);
    let video = "videos/chunk-000/observation.images.pairing/episode_000000.mp4";
    std::fs::copy(at_30.join(video), at_20.join(video)).unwrap();
    let report = phone2act_dataset::verify::verify(&at_20);
    let text = report.problems.join("\n");
    assert!(
        text.contains(
            "episode 0 observation.images.pairing: frame 1 is presented at 512 * 1/15360 s, not at 1/20 s"
        ),
        "{text}"
    );
}

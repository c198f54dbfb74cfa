//! Dataset statistics against an independent computation: datasets of 1, 4 and 20 episodes in both formats,
//! written through the dataset API (with a resume and a lost quantile file on the way), then
//! checked by tests/conformance/check.py with numpy over every frame read with pyarrow, here when the
//! lerobot venv exists and in `make test`'s conformance run (the datasets are published to it).

mod common;

use common::{lerobot_check, publish_for_conformance, read_json, spec};
use phone2act_dataset::dataset::FrameFlags;
use phone2act_dataset::quantiles::{QUANTILES_FILE, QuantileStore};
use phone2act_dataset::{Dataset, EpisodeSummary, Format};
use serde_json::json;
use std::path::{Path, PathBuf};

const TASKS: [&str; 2] = ["pick the ball", "put it in the basket"];

/// xorshift64: reproducible values without a dependency.
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Frames per episode: uneven, so that per-episode quantiles averaged by count differ from the dataset's.
fn episode_len(e: u64, long: bool) -> u64 {
    if long {
        150 + (e * 97) % 300
    } else {
        8 + (e * 37) % 60
    }
}

/// One episode whose columns have the shapes that broke the old aggregation: a gripper that is 0, 0.5 or 1
/// for whole stretches, per-episode offsets, a heavy tail, and constant dimensions.
fn record_episode(ds: &mut Dataset, e: u64, long: bool, rng: &mut Rng) {
    let frames = episode_len(e, long);
    let mut ep = ds.begin_episode(TASKS[(e % 2) as usize]).unwrap();
    let offset = (e as f64 * 0.7).sin();
    for i in 0..frames {
        let t = i as f64 / frames as f64;
        let gripper = if t < 0.4 {
            0.0
        } else if t < 0.6 {
            0.5
        } else {
            1.0
        };
        let mut state: Vec<f64> = (0..12)
            .map(|d| offset * f64::from(d) + (t * 6.0 + f64::from(d)).sin() + 0.01 * rng.unit())
            .collect();
        state[5] = 0.3; // a constant dimension
        state[9] = rng.unit().max(1e-6).ln(); // heavy lower tail
        state.push(gripper);
        let mut action: Vec<f64> = (0..6)
            .map(|d| 0.002 * (t * 9.0 + f64::from(d)).cos() * (1.0 + offset))
            .collect();
        action.push(if e.is_multiple_of(3) {
            1.0 - gripper
        } else {
            gripper
        });
        ep.push_row(&state, &action, FrameFlags::default()).unwrap();
    }
    ds.commit_episode(ep, EpisodeSummary::default(), || Ok(Vec::new()))
        .unwrap();
}

/// Writes `episodes` episodes: the first half, a reopen (the persisted sketches resume), a reopen without
/// the quantile file (rebuilt from the data), then the rest.
fn write_dataset(root: &Path, format: Format, episodes: u64, long: bool) {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15 ^ episodes);
    let open = || Dataset::open(spec(root, format, &[], (64, 64))).unwrap();
    let mut ds = open();
    let half = episodes / 2;
    for e in 0..half {
        record_episode(&mut ds, e, long, &mut rng);
    }
    drop(ds);
    let mut ds = open();
    if half > 0 {
        assert!(root.join(QUANTILES_FILE).exists());
        record_episode(&mut ds, half, long, &mut rng);
    }
    drop(ds);
    // As a dataset from an older phone2act: no quantile file, averaged quantiles in stats.json.
    std::fs::remove_file(root.join(QUANTILES_FILE)).ok();
    let stats_path = root.join("meta/stats.json");
    let tampered = half > 0;
    if tampered {
        let mut stats = read_json(&stats_path);
        stats["index"]["q01"] = json!([-1.0]);
        std::fs::write(&stats_path, stats.to_string()).unwrap();
    }
    let mut ds = open();
    if tampered {
        assert!(root.join(QUANTILES_FILE).exists(), "rebuilt at open");
        let q01 = read_json(&stats_path)["index"]["q01"].clone();
        assert_ne!(q01, json!([-1.0]), "stats.json corrected at open");
    }
    let start = if half > 0 { half + 1 } else { 0 };
    for e in start..episodes {
        record_episode(&mut ds, e, long, &mut rng);
    }
    assert_eq!(ds.total_episodes(), episodes);
    let frames = ds.total_frames();
    drop(ds);
    // The sketches saves built one episode at a time are exactly those a rebuild from the data gives.
    let persisted = QuantileStore::load(root, episodes, frames).expect("quantile file of the last save");
    let rebuilt = QuantileStore::rebuild(root, episodes).unwrap();
    assert_eq!(persisted.current, rebuilt.current);
}

fn check(format: Format, name: &str, episodes: u64, long: bool, dir: &Path) -> PathBuf {
    let root = dir.join(name);
    write_dataset(&root, format, episodes, long);
    let info = read_json(&root.join("meta/info.json"));
    assert_eq!(info["total_episodes"], episodes);
    let stats = read_json(&root.join("meta/stats.json"));
    let q99 = stats["action"]["q99"].as_array().unwrap();
    assert!(
        (q99[6].as_f64().unwrap() - 1.0).abs() < 1e-9,
        "the gripper is closed for 40 % of every episode: its q99 is 1, got {}",
        q99[6]
    );
    let expect = json!({"episodes": episodes, "tasks": TASKS[..episodes.min(2) as usize]});
    std::fs::write(root.join("phone2act_expect.json"), expect.to_string()).unwrap();
    publish_for_conformance(name, &root, expect);
    root
}

/// 1, 4 and 20 episodes (the last two under the sketch's exact range), then 20 long episodes (6 130
/// frames, beyond it), checked by numpy.
fn write_and_verify(format: Format) {
    let dir = tempfile::tempdir().unwrap();
    let tag = format.codebase_version().replace('.', "");
    let roots: Vec<PathBuf> = [
        (1, false, "1ep"),
        (4, false, "4ep"),
        (20, false, "20ep"),
        (20, true, "20ep-long"),
    ]
    .into_iter()
    .map(|(n, long, label)| check(format, &format!("stats-{tag}-{label}"), n, long, dir.path()))
    .collect();
    match lerobot_check(&roots, format == Format::V21) {
        Some((ok, out)) => {
            println!("{out}");
            assert!(ok, "stats differ from numpy over the data:\n{out}");
        }
        None => eprintln!("note: lerobot venv not installed; tests/conformance/run.sh checks these datasets"),
    }
}

#[test]
fn v21_stats_equal_numpy_over_all_frames() {
    write_and_verify(Format::V21);
}

#[test]
fn v30_stats_equal_numpy_over_all_frames() {
    write_and_verify(Format::V30);
}

/// A station that removes uploaded episodes' data files (`retain_local = false`) keeps only their metadata:
/// reopened, the dataset continues after the last file the metadata names, never reusing an index whose
/// file is in storage.
#[test]
fn a_reopened_dataset_never_reuses_the_index_of_a_removed_data_file() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let open = || Dataset::open(spec(root, Format::V30, &[], (64, 64))).unwrap();
    let mut rng = Rng(7);
    let mut ds = open();
    for e in 0..2 {
        record_episode(&mut ds, e, false, &mut rng);
    }
    drop(ds);
    let data = root.join("data/chunk-000");
    for f in ["file-000.parquet", "file-001.parquet"] {
        std::fs::remove_file(data.join(f)).unwrap();
    }
    let mut ds = open();
    record_episode(&mut ds, 2, false, &mut rng);
    drop(ds);
    let names: Vec<String> = std::fs::read_dir(&data)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["file-002.parquet"]);
    assert_eq!(read_json(&root.join("meta/info.json"))["total_episodes"], 3);
}

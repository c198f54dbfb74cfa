//! What the dataset statistics cost a save as a dataset grows: episodes of synthetic rows (no cameras, so
//! the numbers are the parquet close, the stats and the commit), saved one after another, with the save
//! latency, the part of it spent merging and encoding the quantile sketches, and the size of the persisted
//! sketch file at checkpoints; then the cost of rebuilding the sketches from the data (what an open does
//! when the file is missing).
//!
//! Run in release: `cargo run --release -p phone2act-recorder --bin stats-bench -- [--episodes N]
//! [--frames N] [--format v21|v30] [--dir PATH]`.

use phone2act_dataset::dataset::FrameFlags;
use phone2act_dataset::quantiles::{QUANTILES_FILE, QuantileStore};
use phone2act_dataset::stats::{ColumnStats, StatKind};
use phone2act_dataset::{Dataset, DatasetSpec, EpisodeSummary, Format};
use phone2act_recorder::synthetic::SyntheticRobot;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut episodes = 1000u64;
    let mut frames = 900u64;
    let mut format = Format::V21;
    let mut dir: Option<std::path::PathBuf> = None;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        let mut val = || args.next().ok_or_else(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--episodes" => episodes = val()?.parse()?,
            "--frames" => frames = val()?.parse()?,
            "--format" => {
                format = match val()?.as_str() {
                    "v21" => Format::V21,
                    "v30" => Format::V30,
                    other => return Err(format!("unknown format {other}").into()),
                }
            }
            "--dir" => dir = Some(val()?.into()),
            other => return Err(format!("unknown flag {other}").into()),
        }
    }
    let tmp = tempfile_dir(dir)?;
    let root = tmp.join("stats-bench");
    let _ = std::fs::remove_dir_all(&root);
    let spec = DatasetSpec {
        root: root.clone(),
        format,
        fps: 30,
        robot_type: "bench".into(),
        video_codec: None,
        state_names: SyntheticRobot::state_names(),
        action_names: SyntheticRobot::action_names(),
        cameras: Vec::new(),
        modality: SyntheticRobot::modality(),
        success: false,
        intervention: false,
        provenance: serde_json::json!({}),
    };
    let mut ds = Dataset::open(spec)?;
    // A second store fed the same columns, to time the sketch work on its own.
    let mut shadow = QuantileStore::default();
    let mut save_ms = Vec::new();
    let mut sketch_ms = Vec::new();
    println!(
        "sketch_ms (merge, quantile query, encode) and the shadow store: observation.state and action only \
         (20 of the 25 sketched dimensions)"
    );
    println!("episodes  frames      save_ms(median/max of last 10)  sketch_ms(median)  quantile_file_kB");
    for e in 0..episodes {
        let mut ep = ds.begin_episode("bench")?;
        let mut state_c = ColumnStats::new(StatKind::Float, 13);
        let mut action_c = ColumnStats::new(StatKind::Float, 7);
        for i in 0..frames {
            let t = (e * frames + i) as f64 / 30.0;
            let state: Vec<f64> = (0..13)
                .map(|d| (t * (0.3 + 0.1 * f64::from(d))).sin() + f64::from(d))
                .collect();
            let action: Vec<f64> = (0..7)
                .map(|d| 0.01 * (t * (0.5 + 0.1 * f64::from(d))).cos())
                .collect();
            // As the recorder does: the parquet holds float32, and so do the sketches.
            state_c.push_f32(&state.iter().map(|v| *v as f32).collect::<Vec<_>>());
            action_c.push_f32(&action.iter().map(|v| *v as f32).collect::<Vec<_>>());
            ep.push_row(&state, &action, FrameFlags::default())?;
        }
        let t0 = Instant::now();
        ds.commit_episode(ep, EpisodeSummary::default(), || Ok(Vec::new()))?;
        save_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        let (mut state_s, mut action_s) = (state_c.finish(), action_c.finish());
        let t1 = Instant::now();
        shadow.add_episode(frames, &[("observation.state", &state_c), ("action", &action_c)]);
        // The episode's stats count only its frames, so apply() would skip them: count the dataset's.
        state_s.count = shadow.current.frames;
        action_s.count = shadow.current.frames;
        shadow.apply("observation.state", &mut state_s);
        shadow.apply("action", &mut action_s);
        let bytes = shadow.encode().len();
        sketch_ms.push(t1.elapsed().as_secs_f64() * 1e3);
        let n = e + 1;
        if n == 1 || n == episodes || [10, 100, 300, 1000, 3000].contains(&n) {
            let last = |v: &[f64]| {
                let mut w: Vec<f64> = v[v.len().saturating_sub(10)..].to_vec();
                w.sort_by(f64::total_cmp);
                (w[w.len() / 2], w[w.len() - 1])
            };
            let (med, max) = last(&save_ms);
            let file_kb = std::fs::metadata(root.join(QUANTILES_FILE)).map_or(0, |m| m.len()) / 1024;
            println!(
                "{n:>8}  {:>10}  {med:>10.1} / {max:<10.1}          {:>8.2}           {file_kb:>8}   (shadow store {} kB)",
                n * frames,
                last(&sketch_ms).0,
                bytes / 1024
            );
        }
    }
    drop(ds);
    let t0 = Instant::now();
    let rebuilt = QuantileStore::rebuild(&root, episodes)?;
    println!(
        "rebuild from the data ({} frames): {:.0} ms",
        rebuilt.current.frames,
        t0.elapsed().as_secs_f64() * 1e3
    );
    let _ = std::fs::remove_dir_all(&root);
    Ok(())
}

fn tempfile_dir(dir: Option<std::path::PathBuf>) -> std::io::Result<std::path::PathBuf> {
    let d = dir.unwrap_or_else(std::env::temp_dir);
    std::fs::create_dir_all(&d)?;
    Ok(d)
}

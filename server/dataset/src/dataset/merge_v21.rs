//! Merging LeRobot v2.1 (GR00T) datasets: one data file and one video per episode, so a merge renames
//! rather than repacks. Each episode's parquet is rewritten with its new `episode_index`, `index` and
//! `task_index`; its videos are hard-linked (copied across file systems) under the new episode number;
//! `episodes.jsonl`, `episodes_stats.jsonl` (the renumbered columns' stats recomputed) and `tasks.jsonl`
//! are rebuilt, `modality.json` must be the same in every input, and GR00T's `stats.json` comes from the
//! rows (exact mean, std, min, max; q01 and q99 from merged sketches).

use super::merge::{
    MergeError, MergeInput, MergeReport, MergedStats, carry_episode, column_stats, columns, data_schema_of,
    feature_difference, numeric_columns, renumber_rows, write_info, write_stats_and_provenance,
};
use super::{CHUNKS_SIZE, PROVENANCE_FILE, Provenance, meta::pretty};
use crate::error::RecorderError;
use crate::parquet_io::{self, props};
use crate::quantiles::QuantileStore;
use crate::stats::{Aggregate, ColumnStats, FeatureStats};
use arrow_array::RecordBatch;
use indexmap::IndexMap;
use parquet::arrow::ArrowWriter;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::fs::{self, File};
use std::path::{Path, PathBuf};

pub(super) struct InputV21 {
    label: String,
    root: PathBuf,
    info: IndexMap<String, Value>,
    chunks: u64,
    tasks: Vec<String>,
    /// `episodes.jsonl` lines, by episode index.
    episodes: Vec<Value>,
    /// `episodes_stats.jsonl`'s `stats` per episode index (absent for an episode without a line).
    episode_stats: BTreeMap<u64, Value>,
    modality: Option<Value>,
    provenance: Option<Provenance>,
}

fn bad(input: &str, detail: impl Into<String>) -> MergeError {
    MergeError::BadInput(input.to_owned(), detail.into())
}

fn jsonl(root: &Path, rel: &str, label: &str) -> Result<Vec<Value>, MergeError> {
    let path = root.join(rel);
    let text = fs::read_to_string(&path).map_err(|e| RecorderError::io(&path, e))?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).map_err(|e| bad(label, format!("{rel}: {e}"))))
        .collect()
}

impl InputV21 {
    fn open(input: &MergeInput) -> Result<Self, MergeError> {
        let (label, root) = (input.label.clone(), input.root.clone());
        let info_path = root.join("meta/info.json");
        let info: IndexMap<String, Value> =
            serde_json::from_slice(&fs::read(&info_path).map_err(|e| RecorderError::io(&info_path, e))?)
                .map_err(|e| bad(&label, format!("meta/info.json: {e}")))?;
        let version = info
            .get("codebase_version")
            .and_then(Value::as_str)
            .unwrap_or("?");
        if version != "v2.1" {
            return Err(MergeError::Incompatible(format!(
                "{label} is a {version} dataset, the first input a v2.1 one"
            )));
        }
        let chunks = info
            .get("chunks_size")
            .and_then(Value::as_u64)
            .unwrap_or(CHUNKS_SIZE)
            .max(1);
        let mut tasks: Vec<(u64, String)> = jsonl(&root, "meta/tasks.jsonl", &label)?
            .iter()
            .map(|v| {
                (
                    v["task_index"].as_u64().unwrap_or(0),
                    v["task"].as_str().unwrap_or("").to_owned(),
                )
            })
            .collect();
        tasks.sort();
        let mut episodes = jsonl(&root, "meta/episodes.jsonl", &label)?;
        episodes.sort_by_key(|v| v["episode_index"].as_u64().unwrap_or(u64::MAX));
        for (i, e) in episodes.iter().enumerate() {
            if e["episode_index"].as_u64() != Some(i as u64) {
                return Err(bad(
                    &label,
                    format!("meta/episodes.jsonl does not number episodes 0..n (line {i}: {e})"),
                ));
            }
        }
        let total = info.get("total_episodes").and_then(Value::as_u64).unwrap_or(0);
        if episodes.len() as u64 != total {
            return Err(bad(
                &label,
                format!(
                    "info.json counts {total} episodes, meta/episodes.jsonl lists {}",
                    episodes.len()
                ),
            ));
        }
        let episode_stats = jsonl(&root, "meta/episodes_stats.jsonl", &label)
            .unwrap_or_default()
            .into_iter()
            .filter_map(|v| Some((v["episode_index"].as_u64()?, v["stats"].clone())))
            .collect();
        let modality = fs::read(root.join("meta/modality.json"))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok());
        let provenance = fs::read(root.join(PROVENANCE_FILE))
            .ok()
            .and_then(|b| serde_json::from_slice::<Provenance>(&b).ok());
        Ok(InputV21 {
            label,
            root,
            info,
            chunks,
            tasks: tasks.into_iter().map(|t| t.1).collect(),
            episodes,
            episode_stats,
            modality,
            provenance,
        })
    }

    fn data_path(&self, e: u64) -> PathBuf {
        self.root.join(format!(
            "data/chunk-{:03}/episode_{e:06}.parquet",
            e / self.chunks
        ))
    }

    fn video_path(&self, key: &str, e: u64) -> PathBuf {
        self.root.join(format!(
            "videos/chunk-{:03}/{key}/episode_{e:06}.mp4",
            e / self.chunks
        ))
    }

    fn length(&self, e: usize) -> u64 {
        self.episodes[e]["length"].as_u64().unwrap_or(0)
    }

    fn frames(&self) -> u64 {
        (0..self.episodes.len()).map(|e| self.length(e)).sum()
    }
}

/// Opens and checks every input against the first (before anything is written).
pub(super) fn open_all(inputs: &[MergeInput]) -> Result<Vec<InputV21>, MergeError> {
    let opened: Vec<InputV21> = inputs.iter().map(InputV21::open).collect::<Result<_, _>>()?;
    let first = &opened[0];
    let Some(first_file) = (!first.episodes.is_empty()).then(|| first.data_path(0)) else {
        return Err(bad(&first.label, "no episodes"));
    };
    let first_columns = columns(&*data_schema_of(&first_file)?);
    for other in &opened {
        let version = other
            .info
            .get("codebase_version")
            .and_then(Value::as_str)
            .unwrap_or("?");
        if version != "v2.1" {
            return Err(MergeError::Incompatible(format!(
                "{} is a {version} dataset, {} a v2.1 one",
                other.label, first.label
            )));
        }
        for key in ["fps", "robot_type"] {
            let (a, b) = (
                first.info.get(key).unwrap_or(&Value::Null),
                other.info.get(key).unwrap_or(&Value::Null),
            );
            if a != b {
                return Err(MergeError::Incompatible(format!(
                    "{} has {key} {b}, {} has {a}",
                    other.label, first.label
                )));
            }
        }
        if let Some(d) = feature_difference(
            first.info.get("features").unwrap_or(&Value::Null),
            other.info.get("features").unwrap_or(&Value::Null),
        ) {
            return Err(MergeError::Incompatible(format!(
                "{} differs from {}: {d}",
                other.label, first.label
            )));
        }
        if let Some(d) = super::merge::modality_difference(first.modality.as_ref(), other.modality.as_ref()) {
            return Err(MergeError::Incompatible(format!(
                "{} and {}: {d}",
                other.label, first.label
            )));
        }
        for e in 0..other.episodes.len() as u64 {
            let cols = columns(&*data_schema_of(&other.data_path(e))?);
            if cols != first_columns {
                return Err(MergeError::Incompatible(format!(
                    "{} episode {e} has columns {cols:?}, {} has {first_columns:?}",
                    other.label, first.label
                )));
            }
        }
    }
    Ok(opened)
}

fn link_or_copy(from: &Path, to: &Path) -> Result<(), RecorderError> {
    if let Some(p) = to.parent() {
        fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
    }
    // The inputs are never modified, so sharing the bytes is safe; a copy where a link cannot be made.
    if fs::hard_link(from, to).is_err() {
        fs::copy(from, to).map_err(|e| RecorderError::io(to, e))?;
    }
    Ok(())
}

fn write_json_lines(path: &Path, lines: &[Value]) -> Result<(), RecorderError> {
    let mut text = String::new();
    for l in lines {
        text.push_str(&serde_json::to_string(l).expect("JSON values always serialise"));
        text.push('\n');
    }
    fs::write(path, text).map_err(|e| RecorderError::io(path, e))
}

#[allow(clippy::too_many_lines)] // one pass over the inputs' episodes
pub(super) fn write(inputs: &[InputV21], dst: &Path) -> Result<MergeReport, MergeError> {
    let first = &inputs[0];
    let fps = u32::try_from(first.info.get("fps").and_then(Value::as_u64).unwrap_or(0)).unwrap_or(0);
    let chunks = first.chunks;
    let keys: Vec<String> = first
        .info
        .get("features")
        .and_then(Value::as_object)
        .map(|f| {
            f.iter()
                .filter(|(_, v)| v["dtype"] == "video")
                .map(|(k, _)| k.clone())
                .collect()
        })
        .unwrap_or_default();
    let mut report = MergeReport::default();
    let mut tasks: Vec<String> = Vec::new();
    let mut aggregates: BTreeMap<String, Aggregate> = BTreeMap::new();
    let mut quantiles = QuantileStore::default();
    let (mut episodes_jsonl, mut stats_jsonl, mut provenance) = (Vec::new(), Vec::new(), Vec::new());
    let (mut episode_offset, mut frame_offset) = (0u64, 0u64);
    fs::create_dir_all(dst.join("meta")).map_err(|e| RecorderError::io(dst.join("meta"), e))?;
    for input in inputs {
        let map: Vec<i64> = input
            .tasks
            .iter()
            .map(|t| {
                tasks.iter().position(|x| x == t).unwrap_or_else(|| {
                    tasks.push(t.clone());
                    tasks.len() - 1
                }) as i64
            })
            .collect();
        for e in 0..input.episodes.len() {
            let old = e as u64;
            let new = episode_offset + old;
            let src = input.data_path(old);
            let batches = parquet_io::read_batches(&src)?;
            let schema = batches
                .first()
                .map(RecordBatch::schema)
                .ok_or_else(|| bad(&input.label, format!("episode {e} has no rows")))?;
            let batch = arrow_select::concat::concat_batches(&schema, &batches).map_err(|err| {
                RecorderError::Parquet {
                    path: src.clone(),
                    detail: err.to_string(),
                }
            })?;
            let n = batch.num_rows();
            let rows = renumber_rows(&batch, new, frame_offset, &map).ok_or_else(|| {
                bad(
                    &input.label,
                    format!("episode {e} has a task_index tasks.jsonl lacks"),
                )
            })?;
            let to = dst.join(format!("data/chunk-{:03}/episode_{new:06}.parquet", new / chunks));
            if let Some(p) = to.parent() {
                fs::create_dir_all(p).map_err(|err| RecorderError::io(p, err))?;
            }
            let file = File::create(&to).map_err(|err| RecorderError::io(&to, err))?;
            let mut w = ArrowWriter::try_new(file, rows.schema(), Some(props(&rows.schema())))
                .map_err(|err| RecorderError::parquet(&to, &err))?;
            w.write(&rows).map_err(|err| RecorderError::parquet(&to, &err))?;
            w.close().map_err(|err| RecorderError::parquet(&to, &err))?;
            report.files_in += 1;
            report.files_out += 1;

            let mut cols: Vec<(String, ColumnStats)> = Vec::new();
            for c in numeric_columns(&rows.schema()) {
                cols.push((c.name.clone(), column_stats(&c, rows.column(c.index))));
            }
            let refs: Vec<(&str, &ColumnStats)> = cols.iter().map(|(k, c)| (k.as_str(), c)).collect();
            quantiles.add_episode(n as u64, &refs);
            let mut stats = input
                .episode_stats
                .get(&old)
                .cloned()
                .unwrap_or_else(|| json!({}));
            for (k, c) in &cols {
                let s = c.finish();
                aggregates.entry(k.clone()).or_default().add(&s);
                if ["episode_index", "index", "task_index"].contains(&k.as_str()) {
                    stats[k.as_str()] = s.to_json_v21();
                }
            }
            stats_jsonl.push(json!({"episode_index": new, "stats": stats}));
            let mut line = input.episodes[e].clone();
            line["episode_index"] = json!(new);
            episodes_jsonl.push(line);

            for key in &keys {
                let from = input.video_path(key, old);
                let to = dst.join(format!(
                    "videos/chunk-{:03}/{key}/episode_{new:06}.mp4",
                    new / chunks
                ));
                link_or_copy(&from, &to)?;
                report.files_in += 1;
                report.files_out += 1;
            }
            let task = input.episodes[e]["tasks"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(Value::as_str)
                .collect::<Vec<_>>()
                .join("; ");
            provenance.push(carry_episode(
                &input.label,
                &input.root,
                input.provenance.as_ref(),
                (old, input.length(e), task, new),
                fps,
                dst,
            )?);
        }
        episode_offset += input.episodes.len() as u64;
        frame_offset += input.frames();
    }
    report.episodes = episode_offset;
    report.frames = frame_offset;
    report.tasks = tasks.len();

    let task_lines: Vec<Value> = tasks
        .iter()
        .enumerate()
        .map(|(i, t)| json!({"task_index": i, "task": t}))
        .collect();
    write_json_lines(&dst.join("meta/tasks.jsonl"), &task_lines)?;
    write_json_lines(&dst.join("meta/episodes.jsonl"), &episodes_jsonl)?;
    write_json_lines(&dst.join("meta/episodes_stats.jsonl"), &stats_jsonl)?;
    if let Some(m) = &first.modality {
        fs::write(dst.join("meta/modality.json"), pretty(m))
            .map_err(|e| RecorderError::io(dst.join("meta/modality.json"), e))?;
    }
    let sources: Vec<Value> = inputs
        .iter()
        .map(|i| json!({"dataset": i.label, "episodes": i.episodes.len(), "frames": i.frames()}))
        .collect();
    // GR00T's stats.json: mean, std, min, max, q01, q99 of every numeric column.
    write_stats_and_provenance(
        dst,
        MergedStats {
            aggregates,
            quantiles: &quantiles,
            stats_json: FeatureStats::to_json_gr00t,
        },
        first.provenance.as_ref(),
        &sources,
        "v2.1",
        provenance,
    )?;

    let mut info = first.info.clone();
    let n = report.episodes;
    info.insert("total_episodes".into(), json!(n));
    info.insert("total_frames".into(), json!(report.frames));
    info.insert("total_tasks".into(), json!(report.tasks));
    info.insert("total_videos".into(), json!(n * keys.len() as u64));
    info.insert("total_chunks".into(), json!(n.div_ceil(chunks)));
    info.insert("splits".into(), json!({"train": format!("0:{n}")}));
    write_info(dst, &info)?;
    Ok(report)
}

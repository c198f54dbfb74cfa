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
use super::merge_stream::{InputProvenance, JsonLines, ProvenanceSpool};
use super::{CHUNKS_SIZE, PROVENANCE_FILE, meta::pretty};
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
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// An input dataset. Its episode lines are not held: `episodes.jsonl` and `episodes_stats.jsonl` are checked
/// once at open and read again, a line at a time, as the merge reaches each episode.
pub(super) struct InputV21 {
    label: String,
    root: PathBuf,
    info: IndexMap<String, Value>,
    chunks: u64,
    tasks: Vec<String>,
    episode_count: u64,
    frame_count: u64,
    episode_stats: EpisodeStats,
    modality: Option<Value>,
    provenance: Option<InputProvenance>,
}

/// `episodes_stats.jsonl`'s `stats` per episode index. A file that is missing or has a line that is not JSON
/// gives none (every episode's stats then start empty).
enum EpisodeStats {
    None,
    /// One line per episode in index order: read along with the episodes. `next` is the line it gives next.
    InOrder {
        path: PathBuf,
        lines: Option<JsonLines>,
        next: u64,
    },
    /// Any other file (no lerobot writer makes one) is read whole, as a map.
    Unordered(BTreeMap<u64, Value>),
}

impl EpisodeStats {
    fn open(path: &Path) -> Result<Self, MergeError> {
        let Ok(mut lines) = JsonLines::open(path) else {
            return Ok(EpisodeStats::None);
        };
        let mut in_order = true;
        let mut position = 0u64;
        while let Some(v) = lines.next_value()? {
            let Ok(v) = v else {
                return Ok(EpisodeStats::None);
            };
            in_order &= v["episode_index"].as_u64() == Some(position);
            position += 1;
        }
        if in_order {
            return Ok(EpisodeStats::InOrder {
                path: path.to_owned(),
                lines: None,
                next: 0,
            });
        }
        let mut map = BTreeMap::new();
        let mut lines = JsonLines::open(path)?;
        while let Some(v) = lines.next_value()? {
            let Ok(v) = v else {
                return Ok(EpisodeStats::None);
            };
            if let Some(i) = v["episode_index"].as_u64() {
                map.insert(i, v["stats"].clone());
            }
        }
        Ok(EpisodeStats::Unordered(map))
    }

    /// The stats of episode `e` (asked in index order), `{}` when the file has none for it.
    fn take(&mut self, e: u64) -> Result<Value, MergeError> {
        let found = match self {
            EpisodeStats::None => None,
            EpisodeStats::Unordered(map) => map.get(&e).cloned(),
            EpisodeStats::InOrder { path, lines, next } => {
                if e < *next {
                    *lines = None;
                    *next = 0;
                }
                if lines.is_none() {
                    *lines = Some(JsonLines::open(path)?);
                }
                let lines = lines.as_mut().expect("just opened");
                let mut found = None;
                while *next <= e {
                    let Some(v) = lines.next_value()? else { break };
                    if *next == e {
                        found = v.ok().map(|v| v["stats"].clone());
                    }
                    *next += 1;
                }
                found
            }
        };
        Ok(found.unwrap_or_else(|| json!({})))
    }
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

/// The next line of `meta/episodes.jsonl`, parsed (`rel` names it in errors).
fn next_episode_line(lines: &mut JsonLines, label: &str) -> Result<Option<Value>, MergeError> {
    match lines.next_value()? {
        Some(Ok(v)) => Ok(Some(v)),
        Some(Err(e)) => Err(bad(label, format!("meta/episodes.jsonl: {e}"))),
        None => Ok(None),
    }
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
        // Every episode line is checked here, before anything is written, and only counted: the merge reads
        // each line again when it reaches the episode.
        let mut lines = JsonLines::open(&root.join("meta/episodes.jsonl"))?;
        let (mut episode_count, mut frame_count) = (0u64, 0u64);
        while let Some(e) = next_episode_line(&mut lines, &label)? {
            if e["episode_index"].as_u64() != Some(episode_count) {
                return Err(bad(
                    &label,
                    format!("meta/episodes.jsonl does not number episodes 0..n (line {episode_count}: {e})"),
                ));
            }
            episode_count += 1;
            frame_count += e["length"].as_u64().unwrap_or(0);
        }
        let total = info.get("total_episodes").and_then(Value::as_u64).unwrap_or(0);
        if episode_count != total {
            return Err(bad(
                &label,
                format!("info.json counts {total} episodes, meta/episodes.jsonl lists {episode_count}"),
            ));
        }
        let episode_stats = EpisodeStats::open(&root.join("meta/episodes_stats.jsonl"))?;
        let modality = fs::read(root.join("meta/modality.json"))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok());
        let provenance = InputProvenance::open(&root.join(PROVENANCE_FILE));
        Ok(InputV21 {
            label,
            root,
            info,
            chunks,
            tasks: tasks.into_iter().map(|t| t.1).collect(),
            episode_count,
            frame_count,
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
}

/// Opens and checks every input against the first (before anything is written).
pub(super) fn open_all(inputs: &[MergeInput]) -> Result<Vec<InputV21>, MergeError> {
    let opened: Vec<InputV21> = inputs.iter().map(InputV21::open).collect::<Result<_, _>>()?;
    let first = &opened[0];
    let Some(first_file) = (first.episode_count > 0).then(|| first.data_path(0)) else {
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
        for e in 0..other.episode_count {
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

/// A JSON-lines file of the output, written a line at a time.
struct LinesOut {
    path: PathBuf,
    out: BufWriter<File>,
}

impl LinesOut {
    fn create(path: PathBuf) -> Result<Self, RecorderError> {
        let file = File::create(&path).map_err(|e| RecorderError::io(&path, e))?;
        Ok(LinesOut {
            path,
            out: BufWriter::new(file),
        })
    }

    fn push(&mut self, v: &Value) -> Result<(), RecorderError> {
        serde_json::to_writer(&mut self.out, v)
            .map_err(std::io::Error::other)
            .and_then(|()| self.out.write_all(b"\n"))
            .map_err(|e| RecorderError::io(&self.path, e))
    }

    fn close(mut self) -> Result<(), RecorderError> {
        self.out.flush().map_err(|e| RecorderError::io(&self.path, e))
    }
}

/// The output, in one pass over the inputs' episodes. Held in memory, whatever the number of episodes: the
/// task table, one episode's rows and lines, the statistics (a few numbers per column, and quantile sketches
/// that grow with the logarithm of the frame count). `episodes.jsonl` and `episodes_stats.jsonl` are written
/// a line at a time; each episode's provenance entry goes to a spool file in the output directory.
#[allow(clippy::too_many_lines)] // one pass over the inputs' episodes
pub(super) fn write(inputs: &mut [InputV21], dst: &Path) -> Result<MergeReport, MergeError> {
    let fps = u32::try_from(inputs[0].info.get("fps").and_then(Value::as_u64).unwrap_or(0)).unwrap_or(0);
    let chunks = inputs[0].chunks;
    let keys: Vec<String> = inputs[0]
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
    let (mut episode_offset, mut frame_offset) = (0u64, 0u64);
    fs::create_dir_all(dst.join("meta")).map_err(|e| RecorderError::io(dst.join("meta"), e))?;
    let mut episodes_jsonl = LinesOut::create(dst.join("meta/episodes.jsonl"))?;
    let mut stats_jsonl = LinesOut::create(dst.join("meta/episodes_stats.jsonl"))?;
    let mut provenance = ProvenanceSpool::create(dst)?;
    for input in inputs.iter_mut() {
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
        let mut lines = JsonLines::open(&input.root.join("meta/episodes.jsonl"))?;
        for old in 0..input.episode_count {
            let e = old;
            let new = episode_offset + old;
            let mut line = next_episode_line(&mut lines, &input.label)?
                .filter(|l| l["episode_index"].as_u64() == Some(old))
                .ok_or_else(|| bad(&input.label, "meta/episodes.jsonl changed during the merge"))?;
            let length = line["length"].as_u64().unwrap_or(0);
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
            let mut stats = input.episode_stats.take(old)?;
            for (k, c) in &cols {
                let s = c.finish();
                aggregates.entry(k.clone()).or_default().add(&s);
                if ["episode_index", "index", "task_index"].contains(&k.as_str()) {
                    stats[k.as_str()] = s.to_json_v21();
                }
            }
            stats_jsonl.push(&json!({"episode_index": new, "stats": stats}))?;
            let task = line["tasks"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(Value::as_str)
                .collect::<Vec<_>>()
                .join("; ");
            line["episode_index"] = json!(new);
            episodes_jsonl.push(&line)?;

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
            let known = match &mut input.provenance {
                Some(p) => p.episode(old, length)?,
                None => None,
            };
            let station = input.provenance.as_ref().map(InputProvenance::station);
            provenance.push(&carry_episode(
                &input.label,
                &input.root,
                (known, station),
                (old, length, task, new),
                fps,
                dst,
            )?)?;
        }
        episode_offset += input.episode_count;
        frame_offset += input.frame_count;
    }
    episodes_jsonl.close()?;
    stats_jsonl.close()?;
    report.episodes = episode_offset;
    report.frames = frame_offset;
    report.tasks = tasks.len();

    let first = &inputs[0];
    let task_lines: Vec<Value> = tasks
        .iter()
        .enumerate()
        .map(|(i, t)| json!({"task_index": i, "task": t}))
        .collect();
    write_json_lines(&dst.join("meta/tasks.jsonl"), &task_lines)?;
    if let Some(m) = &first.modality {
        fs::write(dst.join("meta/modality.json"), pretty(m))
            .map_err(|e| RecorderError::io(dst.join("meta/modality.json"), e))?;
    }
    let sources: Vec<Value> = inputs
        .iter()
        .map(|i| json!({"dataset": i.label, "episodes": i.episode_count, "frames": i.frame_count}))
        .collect();
    // GR00T's stats.json: mean, std, min, max, q01, q99 of every numeric column.
    write_stats_and_provenance(
        dst,
        MergedStats {
            aggregates,
            quantiles: &quantiles,
            stats_json: FeatureStats::to_json_gr00t,
        },
        first.provenance.as_ref().map(|p| &p.head),
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

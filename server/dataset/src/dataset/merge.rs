//! Merging LeRobot v3.0 datasets (several stations' recordings) into one, and compacting one dataset's many
//! small files into lerobot's shard sizes: the same operation, with one input for a compact.
//!
//! What lerobot's `aggregate_datasets` does, done in one streaming pass: episodes renumbered in input order,
//! `index` shifted by the frames before, tasks unified (first appearance wins its index, every `task_index`
//! relabelled), data rows copied into files of at most `data_file_size_mb`, videos appended whole into files
//! of at most `video_file_size_mb` by stream copy (never re-encoded), each episode's `from_timestamp` moved by
//! where its source file landed. Statistics: the numeric columns are recomputed from the rows as they pass
//! (exact min, max, mean, std; quantiles from per-dimension sketches merged episode by episode, so the
//! merged quantiles are the data's, not an average), the per-episode stats of the renumbered columns
//! (`episode_index`, `index`, `task_index`) are recomputed, and camera statistics are aggregated the way
//! lerobot does (count-weighted). Provenance keeps each episode's station, operator and where it came from.
//!
//! Nothing is written until every input has been checked against the first (format, fps, robot type, every
//! feature, the data files' columns); the output is assembled in a hidden sibling directory and renamed into
//! place at the end, so a refused or failed merge leaves no output at all.

use super::merge_stream::{InputProvenance, ParquetRows, ProvenanceHead, ProvenanceSpool, parquet_files};
use super::{CHUNKS_SIZE, MergedFrom, PROVENANCE_FILE, Provenance, meta::pretty};
use crate::av::remux::Concat;
use crate::error::RecorderError;
use crate::events::events_path;
use crate::parquet_io::{self, float_values, int_column, props, stat_list};
use crate::quantiles::{QUANTILES_FILE, QuantileStore};
use crate::stats::{Aggregate, ColumnStats, FeatureStats, QUANTILES, StatKind};
use arrow_array::cast::AsArray;
use arrow_array::{Array, ArrayRef, BooleanArray, Float64Array, Int64Array, RecordBatch};
use arrow_schema::{DataType, Field, Schema, SchemaRef};
use indexmap::IndexMap;
use parquet::arrow::ArrowWriter;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// lerobot's default data file size limit (`DEFAULT_DATA_FILE_SIZE_IN_MB`).
pub const DEFAULT_DATA_FILE_SIZE_MB: f64 = 100.0;
/// lerobot's default video file size limit (`DEFAULT_VIDEO_FILE_SIZE_IN_MB`).
pub const DEFAULT_VIDEO_FILE_SIZE_MB: f64 = 200.0;

/// Why a merge did not happen. Nothing is left at the output in any case.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    #[error("the inputs cannot be merged: {0}")]
    Incompatible(String),
    #[error("{0} is not a LeRobot dataset this merge reads: {1}")]
    BadInput(String, String),
    #[error("{} already exists and is not empty; choose a new output directory", .0.display())]
    OutputExists(PathBuf),
    #[error("nothing to merge: no input given")]
    NoInput,
    #[error(transparent)]
    Recorder(#[from] RecorderError),
}

/// One dataset to merge: where it is on disk, and the name provenance records for it (a path or a URL).
#[derive(Clone, Debug)]
pub struct MergeInput {
    pub root: PathBuf,
    pub label: String,
}

#[derive(Clone, Debug)]
pub struct MergeOptions {
    pub data_file_size_mb: f64,
    pub video_file_size_mb: f64,
}

impl Default for MergeOptions {
    fn default() -> Self {
        MergeOptions {
            data_file_size_mb: DEFAULT_DATA_FILE_SIZE_MB,
            video_file_size_mb: DEFAULT_VIDEO_FILE_SIZE_MB,
        }
    }
}

/// What a merge wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MergeReport {
    pub episodes: u64,
    pub frames: u64,
    pub tasks: usize,
    /// Files (data, episode metadata, videos) in the inputs and in the output.
    pub files_in: u64,
    pub files_out: u64,
}

/// Where one episode's files are in its source dataset (one episode's worth, read from its metadata row).
struct SourceEpisode {
    index: u64,
    length: u64,
    from: u64,
    /// Per camera: chunk * CHUNKS + file, from_timestamp, to_timestamp.
    videos: BTreeMap<String, (u64, f64, f64)>,
}

impl SourceEpisode {
    /// The episode of row `r` of a `meta/episodes` batch.
    fn of_row(
        b: &RecordBatch,
        r: usize,
        keys: &[String],
        chunks: u64,
        label: &str,
    ) -> Result<Self, MergeError> {
        let int = |name: &str| -> Option<i64> {
            b.column_by_name(name)?
                .as_primitive_opt::<arrow_array::types::Int64Type>()
                .map(|a| if a.is_null(r) { -1 } else { a.value(r) })
        };
        let idx = int("episode_index").ok_or_else(|| bad(label, "meta/episodes has no episode_index"))?;
        let len = int("length").ok_or_else(|| bad(label, "meta/episodes has no length"))?;
        let from =
            int("dataset_from_index").ok_or_else(|| bad(label, "meta/episodes has no dataset_from_index"))?;
        let mut videos = BTreeMap::new();
        for k in keys {
            let chunk = int(&format!("videos/{k}/chunk_index"));
            let file = int(&format!("videos/{k}/file_index"));
            let (Some(chunk), Some(file)) = (chunk, file) else {
                return Err(bad(label, format!("meta/episodes has no videos/{k} columns")));
            };
            let from_s = float_at(b, &format!("videos/{k}/from_timestamp"), r).unwrap_or(0.0);
            let to_s = float_at(b, &format!("videos/{k}/to_timestamp"), r).unwrap_or(0.0);
            let n = u64::try_from(chunk).unwrap_or(0) * chunks + u64::try_from(file).unwrap_or(0);
            videos.insert(k.clone(), (n, from_s, to_s));
        }
        Ok(SourceEpisode {
            index: u64::try_from(idx).map_err(|_| bad(label, "negative episode_index"))?,
            length: u64::try_from(len).map_err(|_| bad(label, "negative length"))?,
            from: u64::try_from(from).map_err(|_| bad(label, "negative dataset_from_index"))?,
            videos,
        })
    }
}

/// An input dataset. Its episodes are not held: `meta/episodes` is checked once at open and read again, a
/// batch at a time, as the merge reaches each episode.
struct Input {
    label: String,
    root: PathBuf,
    info: IndexMap<String, Value>,
    chunks: u64,
    tasks: Vec<String>,
    episode_count: u64,
    frame_count: u64,
    provenance: Option<InputProvenance>,
    stats: Value,
    /// GR00T's `meta/modality.json`, when the input carries one.
    modality: Option<Value>,
}

fn bad(input: &str, detail: impl Into<String>) -> MergeError {
    MergeError::BadInput(input.to_owned(), detail.into())
}

fn read_json(path: &Path) -> Result<Value, RecorderError> {
    let bytes = fs::read(path).map_err(|e| RecorderError::io(path, e))?;
    serde_json::from_slice(&bytes).map_err(|e| RecorderError::CorruptDataset {
        root: path.to_owned(),
        detail: e.to_string(),
    })
}

fn float_at(batch: &RecordBatch, name: &str, row: usize) -> Option<f64> {
    let col = batch.column_by_name(name)?;
    float_values(&col.slice(row, 1)).and_then(|v| v.first().copied())
}

impl Input {
    fn open(input: &MergeInput) -> Result<Self, MergeError> {
        let label = input.label.clone();
        let root = input.root.clone();
        let info_path = root.join("meta/info.json");
        if !info_path.exists() {
            return Err(bad(&label, "no meta/info.json"));
        }
        let info: IndexMap<String, Value> =
            serde_json::from_slice(&fs::read(&info_path).map_err(|e| RecorderError::io(&info_path, e))?)
                .map_err(|e| bad(&label, format!("meta/info.json: {e}")))?;
        let version = info
            .get("codebase_version")
            .and_then(Value::as_str)
            .unwrap_or("?");
        if version != "v3.0" {
            return Err(bad(
                &label,
                format!(
                    "a {version} dataset cannot be merged with v3.0 ones (convert it first with lerobot's convert_dataset_v21_to_v30)"
                ),
            ));
        }
        let chunks = info
            .get("chunks_size")
            .and_then(Value::as_u64)
            .unwrap_or(CHUNKS_SIZE)
            .max(1);
        let tasks = parquet_io::read_tasks(&root.join("meta/tasks.parquet"))?;
        // Every row of meta/episodes is checked here, before anything is written, and only counted: the
        // merge reads each row again when it reaches the episode.
        let keys: Vec<String> = video_keys(&info);
        let mut rows = ParquetRows::new(parquet_files(&root.join("meta/episodes")));
        let (mut episode_count, mut frame_count) = (0u64, 0u64);
        while let Some((b, r)) = rows.next_row()? {
            let e = SourceEpisode::of_row(&b, r, &keys, chunks, &label)?;
            if e.index != episode_count || e.from != frame_count {
                return Err(bad(
                    &label,
                    format!(
                        "episodes are not numbered 0..n with contiguous rows (episode {} at position {episode_count}, rows from {} where {frame_count} was expected)",
                        e.index, e.from
                    ),
                ));
            }
            episode_count += 1;
            frame_count += e.length;
        }
        let total = info.get("total_episodes").and_then(Value::as_u64).unwrap_or(0);
        if episode_count != total {
            return Err(bad(
                &label,
                format!("info.json counts {total} episodes, meta/episodes lists {episode_count}"),
            ));
        }
        let provenance = InputProvenance::open(&root.join(PROVENANCE_FILE));
        let stats = read_json(&root.join("meta/stats.json")).unwrap_or(Value::Null);
        let modality_path = root.join("meta/modality.json");
        let modality = if modality_path.exists() {
            Some(read_json(&modality_path).map_err(|e| bad(&label, format!("meta/modality.json: {e}")))?)
        } else {
            None
        };
        Ok(Input {
            label,
            root,
            info,
            chunks,
            tasks,
            episode_count,
            frame_count,
            provenance,
            stats,
            modality,
        })
    }

    fn fps(&self) -> u64 {
        self.info.get("fps").and_then(Value::as_u64).unwrap_or(0)
    }

    fn data_files(&self) -> impl Iterator<Item = PathBuf> + use<> {
        parquet_files(&self.root.join("data"))
    }

    /// The rows of `meta/episodes`, in file order (which [`Input::open`] checked is episode order).
    fn meta_rows(&self) -> ParquetRows<impl Iterator<Item = PathBuf> + use<>> {
        ParquetRows::new(parquet_files(&self.root.join("meta/episodes")))
    }

    fn video_path(&self, key: &str, n: u64) -> PathBuf {
        self.root
            .join(file_rel(&format!("videos/{key}"), n, self.chunks, "mp4"))
    }
}

fn video_keys(info: &IndexMap<String, Value>) -> Vec<String> {
    info.get("features")
        .and_then(Value::as_object)
        .map(|f| {
            f.iter()
                .filter(|(_, v)| v["dtype"] == "video")
                .map(|(k, _)| k.clone())
                .collect()
        })
        .unwrap_or_default()
}

fn file_rel(top: &str, n: u64, chunks: u64, ext: &str) -> String {
    format!("{top}/chunk-{:03}/file-{:03}.{ext}", n / chunks, n % chunks)
}

/// The first difference between two inputs' features that a single dataset cannot hold, if any.
pub(super) fn feature_difference(a: &Value, b: &Value) -> Option<String> {
    let (Some(a), Some(b)) = (a.as_object(), b.as_object()) else {
        return Some("info.json has no features".into());
    };
    let mut ka: Vec<&String> = a.keys().collect();
    let mut kb: Vec<&String> = b.keys().collect();
    ka.sort();
    kb.sort();
    if ka != kb {
        return Some(format!("features {kb:?} instead of {ka:?}"));
    }
    for (k, fa) in a {
        let fb = &b[k];
        for field in ["dtype", "shape", "names"] {
            if fa[field] != fb[field] {
                return Some(format!(
                    "feature {k}: {field} {} instead of {}",
                    fb[field], fa[field]
                ));
            }
        }
        if fa["dtype"] == "video" {
            for field in ["video.codec", "video.height", "video.width", "video.pix_fmt"] {
                if fa["info"][field] != fb["info"][field] {
                    return Some(format!(
                        "camera {k}: {field} {} instead of {} (videos are never re-encoded)",
                        fb["info"][field], fa["info"][field]
                    ));
                }
            }
        }
    }
    None
}

pub(super) fn data_schema_of(path: &Path) -> Result<SchemaRef, RecorderError> {
    let file = File::open(path).map_err(|e| RecorderError::io(path, e))?;
    let b = ParquetRecordBatchReaderBuilder::try_new(file).map_err(|e| RecorderError::parquet(path, &e))?;
    Ok(Arc::clone(b.schema()))
}

/// The columns of a data file as `name: type`, metadata left out.
pub(super) fn columns(schema: &Schema) -> Vec<String> {
    schema
        .fields()
        .iter()
        .map(|f| format!("{}: {}", f.name(), f.data_type()))
        .collect()
}

fn check_compatible(inputs: &[Input]) -> Result<SchemaRef, MergeError> {
    let first = &inputs[0];
    let first_schema = match first.data_files().next() {
        Some(f) => data_schema_of(&f)?,
        None => return Err(bad(&first.label, "no data files")),
    };
    for other in inputs {
        let differ = |what: &str, a: &Value, b: &Value| {
            MergeError::Incompatible(format!("{} has {what} {b}, {} has {a}", other.label, first.label))
        };
        for key in ["fps", "robot_type"] {
            let (a, b) = (
                first.info.get(key).unwrap_or(&Value::Null),
                other.info.get(key).unwrap_or(&Value::Null),
            );
            if a != b {
                return Err(differ(key, a, b));
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
        if let Some(d) = modality_difference(first.modality.as_ref(), other.modality.as_ref()) {
            return Err(MergeError::Incompatible(format!(
                "{} and {}: {d}",
                other.label, first.label
            )));
        }
        for f in other.data_files() {
            let s = data_schema_of(&f)?;
            if columns(&s) != columns(&first_schema) {
                return Err(MergeError::Incompatible(format!(
                    "{} ({}) has columns {:?}, {} has {:?}",
                    other.label,
                    f.display(),
                    columns(&s),
                    first.label,
                    columns(&first_schema)
                )));
            }
        }
    }
    Ok(first_schema)
}

/// Why two inputs' `meta/modality.json` cannot be one output's, or None when they agree (both the same, or
/// both absent). Equal features do not make equal modality files (the body-part groups and which action
/// slices are absolute come from each station's configuration), so a merge never guesses one for all.
pub(super) fn modality_difference(first: Option<&Value>, other: Option<&Value>) -> Option<String> {
    match (first, other) {
        (Some(a), Some(b)) if a != b => Some(
            "their meta/modality.json differ (GR00T reads one layout of state and action per dataset; \
             merge datasets recorded with the same arm and modality configuration)"
                .into(),
        ),
        (Some(_), None) | (None, Some(_)) => Some(
            "only one of them has a meta/modality.json (GR00T's loader needs it for every episode; copy \
             the other's meta/modality.json into it if both were recorded with the same configuration)"
                .into(),
        ),
        _ => None,
    }
}

/// A numeric column of the data files whose statistics the merge recomputes.
pub(super) struct NumericColumn {
    pub(super) index: usize,
    pub(super) name: String,
    kind: StatKind,
    dims: usize,
}

pub(super) fn numeric_columns(schema: &Schema) -> Vec<NumericColumn> {
    schema
        .fields()
        .iter()
        .enumerate()
        .filter_map(|(index, f)| {
            let (kind, dims) = match f.data_type() {
                DataType::FixedSizeList(inner, n) if inner.data_type().is_floating() => {
                    (StatKind::Float, usize::try_from(*n).ok()?)
                }
                DataType::Float32 | DataType::Float64 => (StatKind::Float, 1),
                DataType::Int64 => (StatKind::Int, 1),
                DataType::Boolean => (StatKind::Bool, 1),
                _ => return None,
            };
            Some(NumericColumn {
                index,
                name: f.name().clone(),
                kind,
                dims,
            })
        })
        .collect()
}

/// One episode's values of `col` (a slice of the data batch).
pub(super) fn column_stats(col: &NumericColumn, array: &ArrayRef) -> ColumnStats {
    let mut s = ColumnStats::new(col.kind, col.dims);
    match array.data_type() {
        DataType::FixedSizeList(..) => {
            let l = array.as_fixed_size_list();
            for i in 0..l.len() {
                s.push(&float_values(&l.value(i)).unwrap_or_default());
            }
        }
        DataType::Int64 => {
            for v in array.as_primitive::<arrow_array::types::Int64Type>() {
                s.push(&[v.unwrap_or(0) as f64]);
            }
        }
        DataType::Boolean => {
            let b: &BooleanArray = array.as_boolean();
            for v in b {
                s.push(&[f64::from(u8::from(v.unwrap_or(false)))]);
            }
        }
        _ => {
            for v in float_values(array).unwrap_or_default() {
                s.push(&[v]);
            }
        }
    }
    s
}

/// A parquet file of the output, rolled over at a size limit.
struct RollingWriter {
    dir: PathBuf,
    top: &'static str,
    chunks: u64,
    limit_bytes: f64,
    schema: SchemaRef,
    current: Option<(u64, ArrowWriter<File>, f64, SchemaRef)>,
    next: u64,
    /// Rows per row group: 1 writes each batch as its own row group.
    group_rows: usize,
    /// Rows written to the current file since its last row group ended.
    pending_rows: usize,
}

/// Rows per row group of the merged `meta/episodes` files. An open Parquet writer keeps every finished row
/// group's column metadata until the file closes, about 45 kB for an episode row with its hundred-odd stats
/// columns: a row group per episode would make the merge's memory grow with the number of episodes.
const META_GROUP_ROWS: usize = 1000;

impl RollingWriter {
    fn new(
        dir: &Path,
        top: &'static str,
        chunks: u64,
        limit_mb: f64,
        schema: SchemaRef,
        group_rows: usize,
    ) -> Self {
        RollingWriter {
            dir: dir.to_owned(),
            top,
            chunks,
            limit_bytes: limit_mb * 1e6,
            schema,
            current: None,
            next: 0,
            group_rows: group_rows.max(1),
            pending_rows: 0,
        }
    }

    /// The file `estimated_bytes` more will go into (a new one if the current would reach the limit, or if
    /// the rows' schema differs from the file's).
    fn file_for(&mut self, estimated_bytes: f64, schema: &SchemaRef) -> Result<u64, RecorderError> {
        let roll = match &self.current {
            None => true,
            Some((_, _, written, file_schema)) => {
                (*written > 0.0 && written + estimated_bytes >= self.limit_bytes)
                    || file_schema.fields() != schema.fields()
            }
        };
        if roll {
            self.close()?;
            let n = self.next;
            self.next += 1;
            let path = self.dir.join(file_rel(self.top, n, self.chunks, "parquet"));
            if let Some(p) = path.parent() {
                fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
            }
            let file = File::create(&path).map_err(|e| RecorderError::io(&path, e))?;
            let mut s = Schema::new(schema.fields().clone());
            s.metadata.clone_from(self.schema.metadata());
            let s = Arc::new(s);
            let w = ArrowWriter::try_new(file, Arc::clone(&s), Some(props(&s)))
                .map_err(|e| RecorderError::parquet(&path, &e))?;
            self.current = Some((n, w, 0.0, s));
            self.pending_rows = 0;
        }
        Ok(self.current.as_ref().map_or(0, |c| c.0))
    }

    /// Writes `batch`, ending the row group once it holds `group_rows` rows (data: 1, each episode its own
    /// row group, as lerobot writes them).
    fn write(&mut self, batch: &RecordBatch, estimated_bytes: f64) -> Result<(), RecorderError> {
        let path = self.dir.join(self.top);
        if let Some((_, w, written, file_schema)) = &mut self.current {
            let batch =
                RecordBatch::try_new(Arc::clone(file_schema), batch.columns().to_vec()).map_err(|e| {
                    RecorderError::Parquet {
                        path: path.clone(),
                        detail: e.to_string(),
                    }
                })?;
            w.write(&batch).map_err(|e| RecorderError::parquet(&path, &e))?;
            self.pending_rows += batch.num_rows();
            if self.pending_rows >= self.group_rows {
                w.flush().map_err(|e| RecorderError::parquet(&path, &e))?;
                self.pending_rows = 0;
            }
            *written += estimated_bytes;
        }
        Ok(())
    }

    fn close(&mut self) -> Result<(), RecorderError> {
        if let Some((_, w, _, _)) = self.current.take() {
            let path = self.dir.join(self.top);
            let file = w.into_inner().map_err(|e| RecorderError::parquet(&path, &e))?;
            file.sync_all().map_err(|e| RecorderError::io(&path, e))?;
        }
        Ok(())
    }
}

/// Replaces (or appends) column `name` of a one-or-more-row batch.
/// One episode's rows as they are in the merged dataset: its new `episode_index`, `index` shifted by the
/// frames before it, `task_index` through `task_map` (old index → new); `None` if a task index is not in it.
pub(super) fn renumber_rows(
    rows: &RecordBatch,
    episode_index: u64,
    frame_offset: u64,
    task_map: &[i64],
) -> Option<RecordBatch> {
    let n = rows.num_rows();
    let old_index = int_column(rows, "index").unwrap_or_default();
    let tasks: Vec<i64> = int_column(rows, "task_index")
        .unwrap_or_default()
        .iter()
        .map(|t| usize::try_from(*t).ok().and_then(|t| task_map.get(t).copied()))
        .collect::<Option<_>>()?;
    let mut rows = set_column(
        rows,
        "episode_index",
        Arc::new(Int64Array::from(vec![episode_index as i64; n])),
    );
    rows = set_column(
        &rows,
        "index",
        Arc::new(Int64Array::from_iter_values(
            old_index.iter().map(|x| x + frame_offset as i64),
        )),
    );
    Some(set_column(&rows, "task_index", Arc::new(Int64Array::from(tasks))))
}

pub(super) fn set_column(batch: &RecordBatch, name: &str, array: ArrayRef) -> RecordBatch {
    let schema = batch.schema();
    let mut fields: Vec<Field> = schema.fields().iter().map(|f| f.as_ref().clone()).collect();
    let mut cols = batch.columns().to_vec();
    let field = Field::new(name, array.data_type().clone(), true);
    if let Some(i) = fields.iter().position(|f| f.name() == name) {
        fields[i] = field;
        cols[i] = array;
    } else {
        fields.push(field);
        cols.push(array);
    }
    let schema = Arc::new(Schema::new_with_metadata(fields, schema.metadata().clone()));
    RecordBatch::try_new(schema, cols).expect("same row count, field types from the arrays")
}

fn one_int(v: u64) -> ArrayRef {
    Arc::new(Int64Array::from(vec![v as i64]))
}

/// The per-episode stats columns of feature `name` in a metadata row, replaced by `s`.
fn set_stats(row: &RecordBatch, name: &str, s: &FeatureStats) -> RecordBatch {
    if row.column_by_name(&format!("stats/{name}/min")).is_none() {
        return row.clone();
    }
    let mut row = row.clone();
    let mut put = |stat: &str, kind: StatKind, values: &[f64], keep_int: bool| {
        let (_, a) = stat_list(kind, values, keep_int);
        row = set_column(&row, &format!("stats/{name}/{stat}"), a);
    };
    put("min", s.kind, &s.min, true);
    put("max", s.kind, &s.max, true);
    put("mean", StatKind::Float, &s.mean, false);
    put("std", StatKind::Float, &s.std, false);
    #[allow(clippy::cast_precision_loss)]
    put("count", StatKind::Int, &[s.count as f64], true);
    for ((_, q), v) in QUANTILES.iter().zip(&s.quantiles) {
        put(q, StatKind::Float, v, false);
    }
    row
}

/// A camera's `stats.json` entry (nested (3,1,1) lists flattened) as stats, for aggregation.
fn image_stats_from_json(v: &Value) -> Option<FeatureStats> {
    fn flat(v: &Value, out: &mut Vec<f64>) {
        match v {
            Value::Array(a) => a.iter().for_each(|x| flat(x, out)),
            Value::Number(n) => out.push(n.as_f64().unwrap_or(0.0)),
            _ => {}
        }
    }
    let get = |k: &str| {
        let mut out = Vec::new();
        flat(&v[k], &mut out);
        out
    };
    let count = get("count").first().copied()? as u64;
    let quantiles: Vec<Vec<f64>> = QUANTILES.iter().map(|(_, q)| get(q)).collect();
    let mean = get("mean");
    Some(FeatureStats {
        kind: StatKind::Image,
        min: get("min"),
        max: get("max"),
        std: get("std"),
        count,
        quantiles: if quantiles.iter().all(|q| q.len() == mean.len()) {
            quantiles
        } else {
            vec![mean.clone(); QUANTILES.len()]
        },
        mean,
    })
}

/// The `codebase_version` of a dataset.
fn version_of(input: &MergeInput) -> Result<String, MergeError> {
    let path = input.root.join("meta/info.json");
    if !path.exists() {
        return Err(bad(&input.label, "no meta/info.json"));
    }
    let info = read_json(&path)?;
    Ok(info["codebase_version"].as_str().unwrap_or("?").to_owned())
}

/// One camera's videos in the output: each source file appended whole, in input and episode order, into the
/// open output file, and a new one started when it would reach the size limit (lerobot's rule). What it holds
/// is one open output file (whose muxer index is bounded by the size limit) and the last source file's place.
struct VideoOut {
    key: String,
    limit_bytes: f64,
    /// Output file number, its muxer, bytes appended.
    current: Option<(u64, Concat, f64)>,
    next: u64,
    /// The source file appended last ((input, file number)) and where it went (output file, its offset in s).
    last: Option<((usize, u64), (u64, f64))>,
}

impl VideoOut {
    /// Where source file `n` of input `i` is in the output (output file, offset in s), appending it if the
    /// previous episode was in another file.
    fn place(
        &mut self,
        (i, input): (usize, &Input),
        n: u64,
        dst: &Path,
        fps: u32,
        report: &mut MergeReport,
    ) -> Result<(u64, f64), MergeError> {
        if let Some((source, place)) = self.last
            && source == (i, n)
        {
            return Ok(place);
        }
        let src = input.video_path(&self.key, n);
        let size = fs::metadata(&src).map_err(|e| RecorderError::io(&src, e))?.len() as f64;
        report.files_in += 1;
        let roll = self
            .current
            .as_ref()
            .is_none_or(|(_, _, bytes)| *bytes > 0.0 && bytes + size >= self.limit_bytes);
        if roll {
            self.finish()?;
            let path = dst.join(file_rel(
                &format!("videos/{}", self.key),
                self.next,
                input.chunks,
                "mp4",
            ));
            if let Some(p) = path.parent() {
                fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
            }
            self.current = Some((self.next, Concat::create(&path, &src, fps)?, 0.0));
            self.next += 1;
            report.files_out += 1;
        }
        let (out_n, concat, bytes) = self.current.as_mut().expect("a file is open");
        let offset_s = concat.append(&src)?;
        *bytes += size;
        let place = (*out_n, offset_s);
        self.last = Some(((i, n), place));
        Ok(place)
    }

    fn finish(&mut self) -> Result<(), MergeError> {
        if let Some((_, c, _)) = self.current.take() {
            c.finish()?;
        }
        Ok(())
    }
}

/// Merges `inputs` into a new dataset at `out` (which must not exist, or be empty). With one input this is
/// a compact. See the [module doc](self).
pub fn merge(inputs: &[MergeInput], out: &Path, opts: &MergeOptions) -> Result<MergeReport, MergeError> {
    if inputs.is_empty() {
        return Err(MergeError::NoInput);
    }
    if out.exists() && fs::read_dir(out).map_or(true, |mut d| d.next().is_some()) {
        return Err(MergeError::OutputExists(out.to_owned()));
    }
    // Every input is read and checked before anything is written.
    let v21 = version_of(&inputs[0])? == "v2.1";
    let (mut opened, mut opened_v21) = if v21 {
        (Vec::new(), super::merge_v21::open_all(inputs)?)
    } else {
        let opened: Vec<Input> = inputs.iter().map(Input::open).collect::<Result<_, _>>()?;
        (opened, Vec::new())
    };
    let data_schema = if v21 {
        None
    } else {
        Some(check_compatible(&opened)?)
    };
    let name = out
        .file_name()
        .map_or_else(|| "merged".into(), |n| n.to_string_lossy().into_owned());
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    fs::create_dir_all(parent).map_err(|e| RecorderError::io(parent, e))?;
    let tmp = parent.join(format!(".{name}.merging-{}", std::process::id()));
    let _ = fs::remove_dir_all(&tmp);
    let result = match &data_schema {
        Some(schema) => write_merged(&mut opened, &tmp, schema, opts),
        None => super::merge_v21::write(&mut opened_v21, &tmp),
    };
    match result {
        Ok(report) => {
            if out.exists() {
                fs::remove_dir(out).map_err(|e| RecorderError::io(out, e))?;
            }
            fs::rename(&tmp, out).map_err(|e| RecorderError::io(out, e))?;
            Ok(report)
        }
        Err(e) => {
            let _ = fs::remove_dir_all(&tmp);
            Err(e)
        }
    }
}

/// The output's files, written in one pass over the inputs' episodes. Held in memory, whatever the number of
/// episodes: the task table, one data file of each input (bounded by the input's data file size limit), one
/// `meta/episodes` record batch of each input (the reader's batch), the open output files (data and metadata
/// writers, which keep their row groups' metadata until they close: bounded by the output's file size limits
/// and by `META_GROUP_ROWS`; one video muxer per camera), the statistics (a few numbers per column, and
/// quantile sketches that grow with the logarithm of the frame count). Each episode's provenance entry goes to
/// a spool file in the output directory.
#[allow(clippy::too_many_lines)] // one pass over the inputs, in the order the output's files need
fn write_merged(
    inputs: &mut [Input],
    dst: &Path,
    data_schema: &SchemaRef,
    opts: &MergeOptions,
) -> Result<MergeReport, MergeError> {
    let fps = u32::try_from(inputs[0].fps()).unwrap_or(0);
    let chunks = inputs[0].chunks;
    let keys = video_keys(&inputs[0].info);
    let mut report = MergeReport::default();
    fs::create_dir_all(dst.join("meta")).map_err(|e| RecorderError::io(dst.join("meta"), e))?;

    // Tasks: first appearance wins its index.
    let mut tasks: Vec<String> = Vec::new();
    let mut task_maps: Vec<Vec<i64>> = Vec::new();
    for input in inputs.iter() {
        let map = input
            .tasks
            .iter()
            .map(|t| {
                let i = tasks.iter().position(|x| x == t).unwrap_or_else(|| {
                    tasks.push(t.clone());
                    tasks.len() - 1
                });
                i as i64
            })
            .collect();
        task_maps.push(map);
    }

    // Per episode, in input and episode order: its data rows copied with episode_index, index and task_index
    // rewritten (statistics of every numeric column gathered on the way), its videos' source files appended,
    // its metadata row written with its locations, indices and renumbered stats replaced, its provenance
    // entry spooled.
    let mut videos: Vec<VideoOut> = keys
        .iter()
        .map(|key| VideoOut {
            key: key.clone(),
            limit_bytes: opts.video_file_size_mb * 1e6,
            current: None,
            next: 0,
            last: None,
        })
        .collect();
    let numeric = numeric_columns(data_schema);
    let mut data = RollingWriter::new(
        dst,
        "data",
        chunks,
        opts.data_file_size_mb,
        Arc::clone(data_schema),
        1,
    );
    let mut meta: Option<RollingWriter> = None;
    let mut spool = ProvenanceSpool::create(dst)?;
    let mut aggregates: BTreeMap<String, Aggregate> = BTreeMap::new();
    let mut quantiles = QuantileStore::default();
    let (mut episode_offset, mut frame_offset) = (0u64, 0u64);
    for (i, input) in inputs.iter_mut().enumerate() {
        report.files_in += parquet_files(&input.root.join("meta/episodes")).count() as u64;
        let mut meta_rows = input.meta_rows();
        let mut next_episode = 0u64;
        for f in input.data_files() {
            report.files_in += 1;
            let file_bytes = fs::metadata(&f).map_err(|e| RecorderError::io(&f, e))?.len() as f64;
            let batches = parquet_io::read_batches(&f)?;
            let file_rows: usize = batches.iter().map(RecordBatch::num_rows).sum();
            let batch =
                arrow_select::concat::concat_batches(&batches[0].schema(), &batches).map_err(|e| {
                    RecorderError::Parquet {
                        path: f.clone(),
                        detail: e.to_string(),
                    }
                })?;
            drop(batches);
            let episodes = int_column(&batch, "episode_index")
                .ok_or_else(|| bad(&input.label, "a data file has no episode_index"))?;
            let mut start = 0;
            while start < batch.num_rows() {
                let old = episodes[start];
                let end = episodes[start..]
                    .iter()
                    .position(|e| *e != old)
                    .map_or(episodes.len(), |p| start + p);
                let old_index = u64::try_from(old).unwrap_or(u64::MAX);
                if old_index >= input.episode_count {
                    return Err(bad(
                        &input.label,
                        format!("rows of episode {old}, which meta/episodes does not list"),
                    ));
                }
                if old_index < next_episode {
                    return Err(bad(
                        &input.label,
                        format!("the rows of episode {old} are not contiguous"),
                    ));
                }
                if old_index > next_episode {
                    // The merge writes each episode's metadata as its rows pass, so the rows must come in
                    // episode order (as every lerobot writer puts them).
                    return Err(bad(
                        &input.label,
                        format!(
                            "episode {next_episode} has no rows before episode {old}'s (the data files must hold the episodes in order)"
                        ),
                    ));
                }
                let (source_batch, r) = meta_rows
                    .next_row()?
                    .ok_or_else(|| bad(&input.label, "meta/episodes changed during the merge"))?;
                let src = SourceEpisode::of_row(&source_batch, r, &keys, chunks, &input.label)?;
                if src.index != old_index {
                    return Err(bad(&input.label, "meta/episodes changed during the merge"));
                }
                let source_row = source_batch.slice(r, 1);
                drop(source_batch);

                let new_ep = episode_offset + src.index;
                let rows = batch.slice(start, end - start);
                let n = rows.num_rows();
                let rows = renumber_rows(&rows, new_ep, frame_offset, &task_maps[i]).ok_or_else(|| {
                    bad(
                        &input.label,
                        format!("episode {old} has a task_index tasks.parquet lacks"),
                    )
                })?;
                let estimate = file_bytes * n as f64 / file_rows.max(1) as f64;
                let data_file = data.file_for(estimate, data_schema)?;
                data.write(&rows, estimate)?;
                let mut cols: Vec<(String, ColumnStats)> = Vec::new();
                for c in &numeric {
                    cols.push((c.name.clone(), column_stats(c, rows.column(c.index))));
                }
                let refs: Vec<(&str, &ColumnStats)> = cols.iter().map(|(k, c)| (k.as_str(), c)).collect();
                quantiles.add_episode(n as u64, &refs);
                let mut renumbered = Vec::new();
                for (k, c) in &cols {
                    let s = c.finish();
                    aggregates.entry(k.clone()).or_default().add(&s);
                    if ["episode_index", "index", "task_index"].contains(&k.as_str()) {
                        renumbered.push((k.clone(), s));
                    }
                }

                let from = frame_offset + src.from;
                let mut row = source_row.clone();
                row = set_column(&row, "episode_index", one_int(new_ep));
                row = set_column(&row, "data/chunk_index", one_int(data_file / chunks));
                row = set_column(&row, "data/file_index", one_int(data_file % chunks));
                row = set_column(&row, "dataset_from_index", one_int(from));
                row = set_column(&row, "dataset_to_index", one_int(from + src.length));
                for (k, (source_n, from_s, to_s)) in &src.videos {
                    let video = videos
                        .iter_mut()
                        .find(|v| &v.key == k)
                        .expect("the episode's cameras are the features' videos");
                    let (vn, offset_s) = video.place((i, &*input), *source_n, dst, fps, &mut report)?;
                    row = set_column(&row, &format!("videos/{k}/chunk_index"), one_int(vn / chunks));
                    row = set_column(&row, &format!("videos/{k}/file_index"), one_int(vn % chunks));
                    row = set_column(
                        &row,
                        &format!("videos/{k}/from_timestamp"),
                        Arc::new(Float64Array::from(vec![offset_s + from_s])),
                    );
                    row = set_column(
                        &row,
                        &format!("videos/{k}/to_timestamp"),
                        Arc::new(Float64Array::from(vec![offset_s + to_s])),
                    );
                }
                for (name, s) in &renumbered {
                    row = set_stats(&row, name, s);
                }
                let meta = meta.get_or_insert_with(|| {
                    RollingWriter::new(
                        dst,
                        "meta/episodes",
                        chunks,
                        opts.data_file_size_mb,
                        source_row.schema(),
                        META_GROUP_ROWS,
                    )
                });
                // 2 kB a row is generous for the metadata of one episode; only the roll-over uses it.
                let estimate = 2e3 + row.get_array_memory_size() as f64 / 8.0;
                let mn = meta.file_for(estimate, &row.schema())?;
                row = set_column(&row, "meta/episodes/chunk_index", one_int(mn / chunks));
                row = set_column(&row, "meta/episodes/file_index", one_int(mn % chunks));
                meta.write(&row, estimate)?;

                let task = parquet_io::episode_task(&source_row, 0);
                let known = match &mut input.provenance {
                    Some(p) => p.episode(src.index, src.length)?,
                    None => None,
                };
                let station = input.provenance.as_ref().map(InputProvenance::station);
                spool.push(&carry_episode(
                    &input.label,
                    &input.root,
                    (known, station),
                    (src.index, src.length, task, new_ep),
                    fps,
                    dst,
                )?)?;
                next_episode += 1;
                start = end;
            }
        }
        if next_episode < input.episode_count {
            return Err(bad(&input.label, format!("episode {next_episode} has no rows")));
        }
        episode_offset += input.episode_count;
        frame_offset += input.frame_count;
    }
    for v in &mut videos {
        v.finish()?;
    }
    data.close()?;
    report.files_out += data.next;
    if let Some(mut meta) = meta {
        meta.close()?;
        report.files_out += meta.next;
    }
    report.episodes = episode_offset;
    report.frames = frame_offset;
    report.tasks = tasks.len();

    let first = &inputs[0];
    parquet_io::write_tasks(&dst.join("meta/tasks.parquet"), &tasks)?;
    if let Some(m) = &first.modality {
        let path = dst.join("meta/modality.json");
        fs::write(&path, pretty(m)).map_err(|e| RecorderError::io(&path, e))?;
    }

    // Cameras: lerobot's count-weighted aggregate of each input's dataset stats.
    for key in &keys {
        let mut agg = Aggregate::default();
        let mut all = true;
        for input in inputs.iter() {
            match image_stats_from_json(&input.stats[key]) {
                Some(s) => agg.add(&s),
                None => all = false,
            }
        }
        if all {
            aggregates.insert(key.clone(), agg);
        }
    }
    let sources: Vec<Value> = inputs
        .iter()
        .map(|i| json!({"dataset": i.label, "episodes": i.episode_count, "frames": i.frame_count}))
        .collect();
    write_stats_and_provenance(
        dst,
        MergedStats {
            aggregates,
            quantiles: &quantiles,
            stats_json: FeatureStats::to_json_v30,
        },
        first.provenance.as_ref().map(|p| &p.head),
        &sources,
        "v3.0",
        spool,
    )?;

    // info.json last, from the first input's, with the totals and the shard sizes of the output.
    let mut info = first.info.clone();
    info.insert("total_episodes".into(), json!(report.episodes));
    info.insert("total_frames".into(), json!(report.frames));
    info.insert("total_tasks".into(), json!(report.tasks));
    info.insert("data_files_size_in_mb".into(), size_json(opts.data_file_size_mb));
    info.insert(
        "video_files_size_in_mb".into(),
        size_json(opts.video_file_size_mb),
    );
    info.insert(
        "splits".into(),
        json!({"train": format!("0:{}", report.episodes)}),
    );
    write_info(dst, &info)?;
    Ok(report)
}

/// Writes `meta/info.json`, which a merge writes last: a reader that sees it sees a whole dataset.
pub(super) fn write_info(dst: &Path, info: &IndexMap<String, Value>) -> Result<(), RecorderError> {
    let mut bytes = pretty(info);
    bytes.push(b'\n');
    let path = dst.join("meta/info.json");
    fs::write(&path, bytes).map_err(|e| RecorderError::io(&path, e))
}

/// A size in MB as lerobot writes it: an integer when it is one.
fn size_json(mb: f64) -> Value {
    if mb.fract() == 0.0 && (0.0..1e15).contains(&mb) {
        json!(mb as u64)
    } else {
        json!(mb)
    }
}

/// An input episode's provenance entry in the output (its station, operator and source kept), and its events
/// sidecar copied under the new index. `known` is the input's own entry for it and `station` the input's
/// configured station, when it has a provenance sidecar; `episode` is (source index, length, tasks, new
/// index).
pub(super) fn carry_episode(
    label: &str,
    root: &Path,
    (known, station): (Option<super::EpisodeSummary>, Option<&str>),
    episode: (u64, u64, String, u64),
    fps: u32,
    dst: &Path,
) -> Result<super::EpisodeSummary, MergeError> {
    let (index, length, task, new_index) = episode;
    let mut summary = known.unwrap_or_else(|| super::EpisodeSummary {
        length_frames: length,
        duration_s: length as f64 / f64::from(fps.max(1)),
        task,
        ..super::EpisodeSummary::default()
    });
    if summary.station_id.is_empty()
        && let Some(station) = station
    {
        station.clone_into(&mut summary.station_id);
    }
    // An episode merged twice keeps the dataset it was first recorded in.
    if summary.merged_from.is_none() {
        summary.merged_from = Some(MergedFrom {
            dataset: label.to_owned(),
            episode_index: index,
        });
    }
    summary.index = new_index;
    let events = root.join(events_path(index));
    if events.exists() {
        let to = dst.join(events_path(new_index));
        if let Some(p) = to.parent() {
            fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
        }
        fs::copy(&events, &to).map_err(|e| RecorderError::io(&to, e))?;
    }
    Ok(summary)
}

/// A merged dataset's statistics, and how its format writes them into `meta/stats.json`.
pub(super) struct MergedStats<'a> {
    pub(super) aggregates: BTreeMap<String, Aggregate>,
    pub(super) quantiles: &'a QuantileStore,
    pub(super) stats_json: fn(&FeatureStats) -> Value,
}

/// The merged dataset's `meta/stats.json` (each aggregate finished with its quantiles, in the format's JSON)
/// and the sketches beside it; then its provenance sidecar: the inputs, every episode's entry (from `spool`),
/// the running aggregates (so a recorder can resume the merged dataset without re-reading it).
pub(super) fn write_stats_and_provenance(
    dst: &Path,
    MergedStats {
        aggregates,
        quantiles,
        stats_json,
    }: MergedStats<'_>,
    first: Option<&ProvenanceHead>,
    sources: &[Value],
    format: &str,
    spool: ProvenanceSpool,
) -> Result<(), MergeError> {
    let mut stats = serde_json::Map::new();
    for (k, a) in &aggregates {
        if let Some(mut s) = a.finish() {
            quantiles.apply(k, &mut s);
            stats.insert(k.clone(), stats_json(&s));
        }
    }
    let stats_path = dst.join("meta/stats.json");
    fs::write(&stats_path, pretty(&Value::Object(stats))).map_err(|e| RecorderError::io(&stats_path, e))?;
    fs::write(dst.join(QUANTILES_FILE), quantiles.encode())
        .map_err(|e| RecorderError::io(dst.join(QUANTILES_FILE), e))?;
    let base = first.cloned().unwrap_or_default();
    let provenance = Provenance {
        software: "phone2act-recorder".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        format: format.into(),
        video: base.video,
        config: json!({"merged_from": sources}),
        sync: base.sync,
        episodes: Vec::new(),
        stats: aggregates,
    };
    let path = dst.join(PROVENANCE_FILE);
    if let Some(p) = path.parent() {
        fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
    }
    spool.finish(&provenance, &path)?;
    Ok(())
}

#[cfg(test)]
#[path = "merge_equivalence.rs"]
mod equivalence;

#[cfg(test)]
mod tests {
    use super::*;

    fn row_groups(path: &Path) -> Vec<i64> {
        let file = File::open(path).unwrap();
        let reader = ParquetRecordBatchReaderBuilder::try_new(file).unwrap();
        reader
            .metadata()
            .row_groups()
            .iter()
            .map(parquet::file::metadata::RowGroupMetaData::num_rows)
            .collect()
    }

    /// Episode rows share row groups of `META_GROUP_ROWS` (the writer's memory then stays flat however many
    /// episodes a file holds); data rows keep one row group per episode, as lerobot writes them.
    #[test]
    fn metadata_rows_share_row_groups_and_data_rows_keep_one_per_episode() {
        let dir = tempfile::tempdir().unwrap();
        let schema = Arc::new(Schema::new(vec![Field::new(
            "episode_index",
            DataType::Int64,
            false,
        )]));
        let one = |i: i64| {
            RecordBatch::try_new(
                Arc::clone(&schema),
                vec![Arc::new(Int64Array::from(vec![i])) as ArrayRef],
            )
            .unwrap()
        };
        let episodes = 2 * META_GROUP_ROWS + 7;
        for (top, group, expected) in [
            (
                "meta/episodes",
                META_GROUP_ROWS,
                vec![META_GROUP_ROWS as i64, META_GROUP_ROWS as i64, 7],
            ),
            ("data", 1, vec![1; episodes]),
        ] {
            let mut w = RollingWriter::new(dir.path(), top, CHUNKS_SIZE, 100.0, Arc::clone(&schema), group);
            for i in 0..episodes {
                let row = one(i as i64);
                w.file_for(10.0, &row.schema()).unwrap();
                w.write(&row, 10.0).unwrap();
            }
            w.close().unwrap();
            let path = dir.path().join(file_rel(top, 0, CHUNKS_SIZE, "parquet"));
            assert_eq!(row_groups(&path), expected, "{top}");
        }
    }
}

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
use std::collections::{BTreeMap, HashMap};
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

/// Where one episode's files are in its source dataset.
struct SourceEpisode {
    index: u64,
    length: u64,
    from: u64,
    /// Per camera: chunk * CHUNKS + file, from_timestamp, to_timestamp.
    videos: BTreeMap<String, (u64, f64, f64)>,
    /// Where its row of `meta/episodes` is (file in `Input::meta_files`, batch, row), read again when the
    /// merged metadata is written: holding every episode's row (a batch of a hundred-odd stats columns each)
    /// would grow the merge's memory with the number of episodes.
    meta_at: (usize, usize, usize),
}

struct Input {
    label: String,
    root: PathBuf,
    info: IndexMap<String, Value>,
    chunks: u64,
    tasks: Vec<String>,
    episodes: Vec<SourceEpisode>,
    data_files: Vec<PathBuf>,
    meta_files: Vec<PathBuf>,
    provenance: Option<Provenance>,
    stats: Value,
    /// GR00T's `meta/modality.json`, when the input carries one.
    modality: Option<Value>,
}

fn bad(input: &str, detail: impl Into<String>) -> MergeError {
    MergeError::BadInput(input.to_owned(), detail.into())
}

fn parquet_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for chunk in fs::read_dir(dir).into_iter().flatten().flatten() {
        for f in fs::read_dir(chunk.path()).into_iter().flatten().flatten() {
            if f.path().extension().is_some_and(|e| e == "parquet") {
                out.push(f.path());
            }
        }
    }
    out.sort();
    out
}

fn read_json(path: &Path) -> Result<Value, RecorderError> {
    let bytes = fs::read(path).map_err(|e| RecorderError::io(path, e))?;
    serde_json::from_slice(&bytes).map_err(|e| RecorderError::CorruptDataset {
        root: path.to_owned(),
        detail: e.to_string(),
    })
}

fn float_at(batch: &RecordBatch, name: &str, row: usize) -> Option<f64> {
    batch
        .column_by_name(name)
        .and_then(float_values)
        .and_then(|v| v.get(row).copied())
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
        let mut episodes = Vec::new();
        let keys: Vec<String> = video_keys(&info);
        let meta_files = parquet_files(&root.join("meta/episodes"));
        for (fi, f) in meta_files.iter().enumerate() {
            for (bi, b) in parquet_io::read_batches(f)?.into_iter().enumerate() {
                let idx = int_column(&b, "episode_index")
                    .ok_or_else(|| bad(&label, "meta/episodes has no episode_index"))?;
                let len =
                    int_column(&b, "length").ok_or_else(|| bad(&label, "meta/episodes has no length"))?;
                let from = int_column(&b, "dataset_from_index")
                    .ok_or_else(|| bad(&label, "meta/episodes has no dataset_from_index"))?;
                for r in 0..b.num_rows() {
                    let mut videos = BTreeMap::new();
                    for k in &keys {
                        let chunk = int_column(&b, &format!("videos/{k}/chunk_index"));
                        let file = int_column(&b, &format!("videos/{k}/file_index"));
                        let (Some(chunk), Some(file)) = (chunk, file) else {
                            return Err(bad(&label, format!("meta/episodes has no videos/{k} columns")));
                        };
                        let from_s = float_at(&b, &format!("videos/{k}/from_timestamp"), r).unwrap_or(0.0);
                        let to_s = float_at(&b, &format!("videos/{k}/to_timestamp"), r).unwrap_or(0.0);
                        let n = u64::try_from(chunk[r]).unwrap_or(0) * chunks
                            + u64::try_from(file[r]).unwrap_or(0);
                        videos.insert(k.clone(), (n, from_s, to_s));
                    }
                    episodes.push(SourceEpisode {
                        index: u64::try_from(idx[r]).map_err(|_| bad(&label, "negative episode_index"))?,
                        length: u64::try_from(len[r]).map_err(|_| bad(&label, "negative length"))?,
                        from: u64::try_from(from[r])
                            .map_err(|_| bad(&label, "negative dataset_from_index"))?,
                        videos,
                        meta_at: (fi, bi, r),
                    });
                }
            }
        }
        episodes.sort_by_key(|e| e.index);
        let total = info.get("total_episodes").and_then(Value::as_u64).unwrap_or(0);
        let mut frames = 0;
        for (i, e) in episodes.iter().enumerate() {
            if e.index != i as u64 || e.from != frames {
                return Err(bad(
                    &label,
                    format!(
                        "episodes are not numbered 0..n with contiguous rows (episode {} at position {i}, rows from {} where {frames} was expected)",
                        e.index, e.from
                    ),
                ));
            }
            frames += e.length;
        }
        if episodes.len() as u64 != total {
            return Err(bad(
                &label,
                format!(
                    "info.json counts {total} episodes, meta/episodes lists {}",
                    episodes.len()
                ),
            ));
        }
        let provenance = fs::read(root.join(PROVENANCE_FILE))
            .ok()
            .and_then(|b| serde_json::from_slice::<Provenance>(&b).ok());
        let stats = read_json(&root.join("meta/stats.json")).unwrap_or(Value::Null);
        let modality_path = root.join("meta/modality.json");
        let modality = if modality_path.exists() {
            Some(read_json(&modality_path).map_err(|e| bad(&label, format!("meta/modality.json: {e}")))?)
        } else {
            None
        };
        Ok(Input {
            data_files: parquet_files(&root.join("data")),
            meta_files,
            label,
            root,
            info,
            chunks,
            tasks,
            episodes,
            provenance,
            stats,
            modality,
        })
    }

    fn fps(&self) -> u64 {
        self.info.get("fps").and_then(Value::as_u64).unwrap_or(0)
    }

    fn frames(&self) -> u64 {
        self.episodes.iter().map(|e| e.length).sum()
    }

    /// The `meta/episodes` row of `episode`, reading its file only when `cache` holds another one (episodes
    /// are in file order, so each file is read once).
    fn meta_row(
        &self,
        episode: &SourceEpisode,
        cache: &mut Option<(usize, Vec<RecordBatch>)>,
    ) -> Result<RecordBatch, MergeError> {
        let (file, batch, row) = episode.meta_at;
        if cache.as_ref().is_none_or(|(f, _)| *f != file) {
            *cache = Some((file, parquet_io::read_batches(&self.meta_files[file])?));
        }
        let batches = &cache.as_ref().expect("just filled").1;
        let b = batches
            .get(batch)
            .filter(|b| row < b.num_rows())
            .ok_or_else(|| bad(&self.label, "meta/episodes changed during the merge"))?;
        Ok(b.slice(row, 1))
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
    let first_schema = match first.data_files.first() {
        Some(f) => data_schema_of(f)?,
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
        for f in &other.data_files {
            let s = data_schema_of(f)?;
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

/// Where an output episode's rows and videos went.
struct Placed {
    data_file: u64,
    /// Per camera: output file, offset (s) of its source file there.
    videos: BTreeMap<String, (u64, f64)>,
    /// Recomputed stats of the renumbered columns.
    renumbered: Vec<(String, FeatureStats)>,
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
    let (opened, opened_v21) = if v21 {
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
        Some(schema) => write_merged(&opened, &tmp, schema, opts),
        None => super::merge_v21::write(&opened_v21, &tmp),
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

#[allow(clippy::too_many_lines)] // one pass over the inputs, in the order the output's files need
fn write_merged(
    inputs: &[Input],
    dst: &Path,
    data_schema: &SchemaRef,
    opts: &MergeOptions,
) -> Result<MergeReport, MergeError> {
    let first = &inputs[0];
    let fps = u32::try_from(first.fps()).unwrap_or(0);
    let chunks = first.chunks;
    let keys = video_keys(&first.info);
    let mut report = MergeReport::default();

    // Tasks: first appearance wins its index.
    let mut tasks: Vec<String> = Vec::new();
    let mut task_maps: Vec<Vec<i64>> = Vec::new();
    for input in inputs {
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

    // Videos: each source file appended whole, in input and file order; a new output file when the current
    // one would reach the size limit (lerobot's rule).
    let mut video_place: HashMap<(usize, String, u64), (u64, f64)> = HashMap::new();
    for key in &keys {
        let limit = opts.video_file_size_mb * 1e6;
        let mut current: Option<(u64, Concat, f64)> = None;
        let mut next = 0u64;
        for (i, input) in inputs.iter().enumerate() {
            let mut files: Vec<u64> = input.episodes.iter().map(|e| e.videos[key].0).collect();
            files.dedup();
            for n in files {
                let src = input.video_path(key, n);
                let size = fs::metadata(&src).map_err(|e| RecorderError::io(&src, e))?.len() as f64;
                report.files_in += 1;
                let roll = current
                    .as_ref()
                    .is_none_or(|(_, _, bytes)| *bytes > 0.0 && bytes + size >= limit);
                if roll {
                    if let Some((_, c, _)) = current.take() {
                        c.finish()?;
                    }
                    let path = dst.join(file_rel(&format!("videos/{key}"), next, chunks, "mp4"));
                    if let Some(p) = path.parent() {
                        fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
                    }
                    current = Some((next, Concat::create(&path, &src, fps)?, 0.0));
                    next += 1;
                    report.files_out += 1;
                }
                let (out_n, concat, bytes) = current.as_mut().expect("a file is open");
                let offset_s = concat.append(&src)?;
                *bytes += size;
                video_place.insert((i, key.clone(), n), (*out_n, offset_s));
            }
        }
        if let Some((_, c, _)) = current.take() {
            c.finish()?;
        }
    }

    // Data: rows copied episode by episode with episode_index, index and task_index rewritten; statistics
    // of every numeric column gathered on the way.
    let numeric = numeric_columns(data_schema);
    let mut data = RollingWriter::new(
        dst,
        "data",
        chunks,
        opts.data_file_size_mb,
        Arc::clone(data_schema),
        1,
    );
    let mut aggregates: BTreeMap<String, Aggregate> = BTreeMap::new();
    let mut quantiles = QuantileStore::default();
    let mut placed: Vec<Vec<Placed>> = Vec::new();
    let (mut episode_offset, mut frame_offset) = (0u64, 0u64);
    for (i, input) in inputs.iter().enumerate() {
        let mut input_placed: Vec<Option<Placed>> = (0..input.episodes.len()).map(|_| None).collect();
        for f in &input.data_files {
            report.files_in += 1;
            let file_bytes = fs::metadata(f).map_err(|e| RecorderError::io(f, e))?.len() as f64;
            let batches = parquet_io::read_batches(f)?;
            let file_rows: usize = batches.iter().map(RecordBatch::num_rows).sum();
            let batch =
                arrow_select::concat::concat_batches(&batches[0].schema(), &batches).map_err(|e| {
                    RecorderError::Parquet {
                        path: f.clone(),
                        detail: e.to_string(),
                    }
                })?;
            let episodes = int_column(&batch, "episode_index")
                .ok_or_else(|| bad(&input.label, "a data file has no episode_index"))?;
            let mut start = 0;
            while start < batch.num_rows() {
                let old = episodes[start];
                let end = episodes[start..]
                    .iter()
                    .position(|e| *e != old)
                    .map_or(episodes.len(), |p| start + p);
                let src = input
                    .episodes
                    .get(usize::try_from(old).unwrap_or(usize::MAX))
                    .ok_or_else(|| {
                        bad(
                            &input.label,
                            format!("rows of episode {old}, which meta/episodes does not list"),
                        )
                    })?;
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
                let videos = src
                    .videos
                    .iter()
                    .map(|(k, (vn, _, _))| (k.clone(), video_place[&(i, k.clone(), *vn)]))
                    .collect();
                let slot = &mut input_placed[usize::try_from(src.index).unwrap_or(usize::MAX)];
                if slot.is_some() {
                    return Err(bad(
                        &input.label,
                        format!("the rows of episode {old} are not contiguous"),
                    ));
                }
                *slot = Some(Placed {
                    data_file,
                    videos,
                    renumbered,
                });
                start = end;
            }
        }
        let input_placed: Vec<Placed> = input_placed
            .into_iter()
            .enumerate()
            .map(|(e, p)| p.ok_or_else(|| bad(&input.label, format!("episode {e} has no rows"))))
            .collect::<Result<_, _>>()?;
        placed.push(input_placed);
        episode_offset += input.episodes.len() as u64;
        frame_offset += input.frames();
    }
    data.close()?;
    report.files_out += data.next;

    // Episode metadata: each source row with its locations, indices and renumbered stats replaced.
    let first_row_schema = first.meta_row(&first.episodes[0], &mut None)?.schema();
    let mut meta = RollingWriter::new(
        dst,
        "meta/episodes",
        chunks,
        opts.data_file_size_mb,
        first_row_schema,
        META_GROUP_ROWS,
    );
    let (mut episode_offset, mut frame_offset) = (0u64, 0u64);
    let mut episodes_prov = Vec::new();
    for (i, input) in inputs.iter().enumerate() {
        report.files_in += parquet_files(&input.root.join("meta/episodes")).len() as u64;
        let mut cache = None;
        for (src, place) in input.episodes.iter().zip(&placed[i]) {
            let new_ep = episode_offset + src.index;
            let from = frame_offset + src.from;
            let source_row = input.meta_row(src, &mut cache)?;
            let mut row = source_row.clone();
            row = set_column(&row, "episode_index", one_int(new_ep));
            row = set_column(&row, "data/chunk_index", one_int(place.data_file / chunks));
            row = set_column(&row, "data/file_index", one_int(place.data_file % chunks));
            row = set_column(&row, "dataset_from_index", one_int(from));
            row = set_column(&row, "dataset_to_index", one_int(from + src.length));
            for (k, (vn, offset_s)) in &place.videos {
                let (_, from_s, to_s) = src.videos[k];
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
            for (name, s) in &place.renumbered {
                row = set_stats(&row, name, s);
            }
            // 2 kB a row is generous for the metadata of one episode; only the roll-over uses it.
            let estimate = 2e3 + row.get_array_memory_size() as f64 / 8.0;
            let n = meta.file_for(estimate, &row.schema())?;
            row = set_column(&row, "meta/episodes/chunk_index", one_int(n / chunks));
            row = set_column(&row, "meta/episodes/file_index", one_int(n % chunks));
            meta.write(&row, estimate)?;

            let task = parquet_io::episode_task(&source_row, 0);
            episodes_prov.push(carry_episode(
                &input.label,
                &input.root,
                input.provenance.as_ref(),
                (src.index, src.length, task, new_ep),
                fps,
                dst,
            )?);
        }
        episode_offset += input.episodes.len() as u64;
        frame_offset += input.frames();
    }
    meta.close()?;
    report.files_out += meta.next;
    report.episodes = episode_offset;
    report.frames = frame_offset;
    report.tasks = tasks.len();

    parquet_io::write_tasks(&dst.join("meta/tasks.parquet"), &tasks)?;
    if let Some(m) = &first.modality {
        let path = dst.join("meta/modality.json");
        fs::write(&path, pretty(m)).map_err(|e| RecorderError::io(&path, e))?;
    }

    // Cameras: lerobot's count-weighted aggregate of each input's dataset stats.
    for key in &keys {
        let mut agg = Aggregate::default();
        let mut all = true;
        for input in inputs {
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
        .map(|i| json!({"dataset": i.label, "episodes": i.episodes.len(), "frames": i.frames()}))
        .collect();
    write_stats_and_provenance(
        dst,
        MergedStats {
            aggregates,
            quantiles: &quantiles,
            stats_json: FeatureStats::to_json_v30,
        },
        first.provenance.as_ref(),
        &sources,
        "v3.0",
        episodes_prov,
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
/// sidecar copied under the new index. `episode` is (source index, length, tasks, new index).
pub(super) fn carry_episode(
    label: &str,
    root: &Path,
    provenance: Option<&Provenance>,
    episode: (u64, u64, String, u64),
    fps: u32,
    dst: &Path,
) -> Result<super::EpisodeSummary, MergeError> {
    let (index, length, task, new_index) = episode;
    let same = |e: &&super::EpisodeSummary| e.index == index && e.length_frames == length;
    // Episodes are listed in index order, so the lookup is usually direct; a merge of thousands of episodes
    // would otherwise scan the list once per episode.
    let known = provenance.and_then(|p| {
        usize::try_from(index)
            .ok()
            .and_then(|i| p.episodes.get(i))
            .filter(same)
            .or_else(|| p.episodes.iter().find(same))
    });
    let mut summary = known.cloned().unwrap_or_else(|| super::EpisodeSummary {
        length_frames: length,
        duration_s: length as f64 / f64::from(fps.max(1)),
        task,
        ..super::EpisodeSummary::default()
    });
    if summary.station_id.is_empty()
        && let Some(p) = provenance
    {
        p.config["station_id"]
            .as_str()
            .unwrap_or_default()
            .clone_into(&mut summary.station_id);
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
/// and the sketches beside it; then its provenance sidecar: the inputs, every episode's entry, the running
/// aggregates (so a recorder can resume the merged dataset without re-reading it).
pub(super) fn write_stats_and_provenance(
    dst: &Path,
    MergedStats {
        aggregates,
        quantiles,
        stats_json,
    }: MergedStats<'_>,
    first: Option<&Provenance>,
    sources: &[Value],
    format: &str,
    episodes: Vec<super::EpisodeSummary>,
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
        episodes,
        stats: aggregates,
    };
    let path = dst.join(PROVENANCE_FILE);
    if let Some(p) = path.parent() {
        fs::create_dir_all(p).map_err(|e| RecorderError::io(p, e))?;
    }
    super::meta::write_pretty(&path, &provenance).map_err(|e| RecorderError::io(&path, e))?;
    Ok(())
}

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

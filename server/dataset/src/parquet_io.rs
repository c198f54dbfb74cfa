//! Parquet files of a LeRobot dataset, with the exact arrow types lerobot writes: vectors as
//! `fixed_size_list<float>[N]`, scalars plain, the `huggingface` schema metadata, and `tasks.parquet` with
//! the pandas metadata that makes the task text the index (without it lerobot returns integer tasks).

use crate::error::RecorderError;
use crate::stats::{FeatureStats, QUANTILES, StatKind};
use arrow_array::builder::{Float64Builder, Int64Builder, ListBuilder, StringBuilder};
use arrow_array::cast::AsArray;
use arrow_array::types::{Float32Type, Float64Type, Int64Type};
use arrow_array::{
    Array, ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, Int64Array, LargeStringArray, ListArray,
    RecordBatch, StringArray,
};
use arrow_schema::{DataType, Field, Schema, SchemaRef};
use parquet::arrow::ArrowWriter;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::basic::Compression;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use serde_json::json;
use std::collections::HashMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Rows buffered before they become a row group: about 25 s at 20 fps, a few hundred kB, so memory stays
/// flat however long the episode runs.
pub const ROWS_PER_GROUP: usize = 512;

pub(crate) fn props(schema: &Schema) -> WriterProperties {
    // parquet-rs keeps schema metadata only inside ARROW:schema; pyarrow/pandas also look at the file's
    // own key-value metadata, so copy it there (the `huggingface` and `pandas` keys).
    let kv: Vec<KeyValue> = schema
        .metadata()
        .iter()
        .map(|(k, v)| KeyValue::new(k.clone(), v.clone()))
        .collect();
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_key_value_metadata((!kv.is_empty()).then_some(kv))
        .build()
}

fn vec_field(name: &str, n: usize) -> Field {
    Field::new(
        name,
        DataType::FixedSizeList(Arc::new(Field::new("element", DataType::Float32, true)), n as i32),
        true,
    )
}

/// `datasets` feature JSON: v3.0 (datasets 4) says `List`, v2.1 (datasets 3.x) only knows `Sequence`.
fn hf_metadata(state_dim: usize, action_dim: usize, v30: bool, flags: FlagColumns) -> String {
    let list = if v30 { "List" } else { "Sequence" };
    let vecf =
        |n: usize| json!({"feature": {"dtype": "float32", "_type": "Value"}, "length": n, "_type": list});
    let scalar = |t: &str| json!({"dtype": t, "_type": "Value"});
    let mut features = serde_json::Map::new();
    features.insert("observation.state".into(), vecf(state_dim));
    features.insert("action".into(), vecf(action_dim));
    for name in flags.names() {
        features.insert(name.into(), scalar("bool"));
    }
    for (name, dtype) in [
        ("timestamp", "float32"),
        ("frame_index", "int64"),
        ("episode_index", "int64"),
        ("index", "int64"),
        ("task_index", "int64"),
    ] {
        features.insert(name.into(), scalar(dtype));
    }
    json!({"info": {"features": features}}).to_string()
}

/// The per-frame task success column (LeRobot's name for it; a bool scalar).
pub const SUCCESS_FEATURE: &str = "next.success";
/// The per-frame "a person drove" column of LeRobot's human-in-the-loop (DAgger) recording: bool, shape
/// `(1,)`, true while a person corrects (see `lerobot.rollout`).
pub const INTERVENTION_FEATURE: &str = "intervention";

/// Which of the optional per-frame bool columns a dataset carries (LeRobot's names; in `info.json` and the
/// parquet they follow `action`, in this order).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FlagColumns {
    /// `next.success`.
    pub success: bool,
    /// `intervention`.
    pub intervention: bool,
}

impl FlagColumns {
    /// The carried columns' names, in order.
    pub fn names(self) -> Vec<&'static str> {
        [
            (self.success, SUCCESS_FEATURE),
            (self.intervention, INTERVENTION_FEATURE),
        ]
        .into_iter()
        .filter_map(|(on, name)| on.then_some(name))
        .collect()
    }
}

/// The data parquet schema for the given vector sizes, with the bool columns `flags` names.
pub fn data_schema(state_dim: usize, action_dim: usize, v30: bool, flags: FlagColumns) -> SchemaRef {
    let mut fields = vec![
        vec_field("observation.state", state_dim),
        vec_field("action", action_dim),
    ];
    for name in flags.names() {
        fields.push(Field::new(name, DataType::Boolean, true));
    }
    fields.extend([
        Field::new("timestamp", DataType::Float32, true),
        Field::new("frame_index", DataType::Int64, true),
        Field::new("episode_index", DataType::Int64, true),
        Field::new("index", DataType::Int64, true),
        Field::new("task_index", DataType::Int64, true),
    ]);
    let meta = HashMap::from([(
        "huggingface".to_owned(),
        hf_metadata(state_dim, action_dim, v30, flags),
    )]);
    Arc::new(Schema::new_with_metadata(fields, meta))
}

/// One frame's row.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub state: Vec<f32>,
    pub action: Vec<f32>,
    /// `next.success`, in datasets that have the column.
    pub success: Option<bool>,
    /// `intervention`, in datasets that have the column.
    pub intervention: Option<bool>,
    pub timestamp: f32,
    pub frame_index: i64,
    pub episode_index: i64,
    pub index: i64,
    pub task_index: i64,
}

impl Row {
    /// The value of the bool column `name` ([`FlagColumns::names`]) in this row.
    pub fn flag(&self, name: &str) -> Option<bool> {
        match name {
            SUCCESS_FEATURE => self.success,
            INTERVENTION_FEATURE => self.intervention,
            _ => None,
        }
    }
}

/// Streams rows of one episode into a parquet file, one row group per [`ROWS_PER_GROUP`] rows. The newest row
/// stays in memory until the next one or [`DataWriter::finish`], so that an outcome given at the episode's end
/// can still set its `next.success` ([`DataWriter::set_last_success`]).
pub struct DataWriter {
    path: PathBuf,
    schema: SchemaRef,
    writer: ArrowWriter<File>,
    state_dim: usize,
    action_dim: usize,
    flags: FlagColumns,
    buf: Vec<Row>,
    rows: u64,
}

impl DataWriter {
    pub fn create(
        path: &Path,
        state_dim: usize,
        action_dim: usize,
        v30: bool,
        flags: FlagColumns,
    ) -> Result<Self, RecorderError> {
        let file = File::create(path).map_err(|e| RecorderError::io(path, e))?;
        let schema = data_schema(state_dim, action_dim, v30, flags);
        let writer = ArrowWriter::try_new(file, Arc::clone(&schema), Some(props(&schema)))
            .map_err(|e| RecorderError::parquet(path, &e))?;
        Ok(DataWriter {
            path: path.to_owned(),
            schema,
            writer,
            state_dim,
            action_dim,
            flags,
            buf: Vec::new(),
            rows: 0,
        })
    }

    pub fn rows(&self) -> u64 {
        self.rows
    }

    pub fn push(&mut self, row: Row) -> Result<(), RecorderError> {
        debug_assert_eq!(
            (row.state.len(), row.action.len()),
            (self.state_dim, self.action_dim)
        );
        self.buf.push(row);
        self.rows += 1;
        if self.buf.len() > ROWS_PER_GROUP {
            let newest = self.buf.split_off(ROWS_PER_GROUP);
            self.flush_group()?;
            self.buf = newest;
        }
        Ok(())
    }

    /// Sets `next.success` of the newest row (in a dataset with the column). False when there is no row.
    pub fn set_last_success(&mut self, success: bool) -> bool {
        match self.buf.last_mut() {
            Some(row) if self.flags.success => {
                row.success = Some(success);
                true
            }
            _ => false,
        }
    }

    fn flush_group(&mut self) -> Result<(), RecorderError> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let rows = std::mem::take(&mut self.buf);
        let vec_col = |dim: usize, get: &dyn Fn(&Row) -> &[f32]| -> ArrayRef {
            let values: Vec<f32> = rows.iter().flat_map(|r| get(r).iter().copied()).collect();
            Arc::new(FixedSizeListArray::new(
                Arc::new(Field::new("element", DataType::Float32, true)),
                dim as i32,
                Arc::new(Float32Array::from(values)),
                None,
            ))
        };
        let ints = |get: &dyn Fn(&Row) -> i64| -> ArrayRef {
            Arc::new(Int64Array::from_iter_values(rows.iter().map(get)))
        };
        let mut columns = vec![
            vec_col(self.state_dim, &|r| &r.state),
            vec_col(self.action_dim, &|r| &r.action),
        ];
        for name in self.flags.names() {
            // A frame without a value (none can be, see `EpisodeWriter::push_row`) would be a null.
            columns.push(Arc::new(BooleanArray::from(
                rows.iter().map(|r| r.flag(name)).collect::<Vec<_>>(),
            )));
        }
        columns.extend([
            Arc::new(Float32Array::from_iter_values(rows.iter().map(|r| r.timestamp))) as ArrayRef,
            ints(&|r| r.frame_index),
            ints(&|r| r.episode_index),
            ints(&|r| r.index),
            ints(&|r| r.task_index),
        ]);
        let batch =
            RecordBatch::try_new(Arc::clone(&self.schema), columns).map_err(|e| RecorderError::Parquet {
                path: self.path.clone(),
                detail: e.to_string(),
            })?;
        self.writer
            .write(&batch)
            .map_err(|e| RecorderError::parquet(&self.path, &e))?;
        self.writer
            .flush()
            .map_err(|e| RecorderError::parquet(&self.path, &e))?;
        Ok(())
    }

    /// Writes the remaining rows and the footer, and fsyncs the file.
    pub fn finish(mut self) -> Result<u64, RecorderError> {
        self.flush_group()?;
        let file = self
            .writer
            .into_inner()
            .map_err(|e| RecorderError::parquet(&self.path, &e))?;
        file.sync_all().map_err(|e| RecorderError::io(&self.path, e))?;
        Ok(self.rows)
    }
}

fn write_batch(path: &Path, batch: &RecordBatch) -> Result<(), RecorderError> {
    let file = File::create(path).map_err(|e| RecorderError::io(path, e))?;
    let mut w = ArrowWriter::try_new(file, batch.schema(), Some(props(&batch.schema())))
        .map_err(|e| RecorderError::parquet(path, &e))?;
    w.write(batch).map_err(|e| RecorderError::parquet(path, &e))?;
    let file = w.into_inner().map_err(|e| RecorderError::parquet(path, &e))?;
    file.sync_all().map_err(|e| RecorderError::io(path, e))
}

/// Writes `meta/tasks.parquet`: `task_index` int64 and the `task` string index, ordered by task_index.
pub fn write_tasks(path: &Path, tasks: &[String]) -> Result<(), RecorderError> {
    let pandas = json!({
        "index_columns": ["task"],
        "column_indexes": [],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "pandas_version": "2.2.0"
    });
    let schema = Arc::new(Schema::new_with_metadata(
        vec![
            Field::new("task_index", DataType::Int64, true),
            Field::new("task", DataType::Utf8, true),
        ],
        HashMap::from([("pandas".to_owned(), pandas.to_string())]),
    ));
    let batch = RecordBatch::try_new(
        schema,
        vec![
            Arc::new(Int64Array::from_iter_values(0..tasks.len() as i64)),
            Arc::new(StringArray::from_iter_values(tasks)),
        ],
    )
    .map_err(|e| RecorderError::Parquet {
        path: path.to_owned(),
        detail: e.to_string(),
    })?;
    write_batch(path, &batch)
}

/// The values of an int64 column (`-1` for a null), `None` if there is no such int64 column.
pub(crate) fn int_column(batch: &RecordBatch, name: &str) -> Option<Vec<i64>> {
    let ints = batch.column_by_name(name)?.as_primitive_opt::<Int64Type>()?;
    Some(ints.iter().map(|v| v.unwrap_or(-1)).collect())
}

/// The values of a float32 or float64 array as f64 (NaN for a null), `None` for any other type.
pub(crate) fn float_values(array: &ArrayRef) -> Option<Vec<f64>> {
    if let Some(f) = array.as_primitive_opt::<Float32Type>() {
        return Some(f.iter().map(|v| v.map_or(f64::NAN, f64::from)).collect());
    }
    let f = array.as_primitive_opt::<Float64Type>()?;
    Some(f.iter().map(|v| v.unwrap_or(f64::NAN)).collect())
}

/// [`float_values`] of the column `name`.
pub(crate) fn float_column(batch: &RecordBatch, name: &str) -> Option<Vec<f64>> {
    float_values(batch.column_by_name(name)?)
}

pub(crate) fn read_batches(path: &Path) -> Result<Vec<RecordBatch>, RecorderError> {
    let file = File::open(path).map_err(|e| RecorderError::io(path, e))?;
    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
        .and_then(parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::build)
        .map_err(|e| RecorderError::parquet(path, &e))?;
    reader
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| RecorderError::Parquet {
            path: path.to_owned(),
            detail: e.to_string(),
        })
}

fn strings(col: &ArrayRef) -> Option<Vec<String>> {
    if let Some(a) = col.as_any().downcast_ref::<StringArray>() {
        return Some(a.iter().map(|s| s.unwrap_or_default().to_owned()).collect());
    }
    col.as_any()
        .downcast_ref::<LargeStringArray>()
        .map(|a| a.iter().map(|s| s.unwrap_or_default().to_owned()).collect())
}

/// Reads `meta/tasks.parquet` (ours, or lerobot's with `__index_level_0__`), ordered by task_index.
pub fn read_tasks(path: &Path) -> Result<Vec<String>, RecorderError> {
    let bad = |detail: &str| RecorderError::Parquet {
        path: path.to_owned(),
        detail: detail.to_owned(),
    };
    let mut pairs = Vec::new();
    for b in read_batches(path)? {
        let idx = b
            .column_by_name("task_index")
            .ok_or_else(|| bad("no task_index column"))?;
        let idx = idx
            .as_any()
            .downcast_ref::<Int64Array>()
            .ok_or_else(|| bad("task_index is not int64"))?;
        let text = b
            .column_by_name("task")
            .or_else(|| b.column_by_name("__index_level_0__"))
            .and_then(strings)
            .ok_or_else(|| bad("no task text column"))?;
        pairs.extend(idx.values().iter().copied().zip(text));
    }
    pairs.sort_by_key(|p| p.0);
    Ok(pairs.into_iter().map(|p| p.1).collect())
}

/// A summary row read back from an episodes metadata file.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeMetaSummary {
    pub episode_index: u64,
    pub tasks: Vec<String>,
    pub length: u64,
}

/// Reads episode_index, tasks and length from a v3.0 `meta/episodes/*/*.parquet` file.
pub fn read_episode_summaries(path: &Path) -> Result<Vec<EpisodeMetaSummary>, RecorderError> {
    let bad = |detail: &str| RecorderError::Parquet {
        path: path.to_owned(),
        detail: detail.to_owned(),
    };
    let mut out = Vec::new();
    for b in read_batches(path)? {
        let int = |name: &str| {
            b.column_by_name(name)
                .and_then(|c| c.as_any().downcast_ref::<Int64Array>().cloned())
                .ok_or_else(|| bad(&format!("no int64 column {name}")))
        };
        let (ep, len) = (int("episode_index")?, int("length")?);
        let tasks = b
            .column_by_name("tasks")
            .and_then(|c| c.as_any().downcast_ref::<ListArray>().cloned());
        for i in 0..b.num_rows() {
            let t = tasks
                .as_ref()
                .and_then(|l| strings(&l.value(i)))
                .unwrap_or_default();
            out.push(EpisodeMetaSummary {
                episode_index: ep.value(i) as u64,
                tasks: t,
                length: len.value(i) as u64,
            });
        }
    }
    Ok(out)
}

/// The tasks of row `row` of a v3.0 episodes-metadata batch, joined with "; " (empty if it has none).
pub(crate) fn episode_task(batch: &RecordBatch, row: usize) -> String {
    batch
        .column_by_name("tasks")
        .and_then(|c| c.as_any().downcast_ref::<ListArray>().cloned())
        .and_then(|l| strings(&l.value(row)))
        .unwrap_or_default()
        .join("; ")
}

/// Where one episode's files are, for its v3.0 metadata row.
#[derive(Clone, Debug)]
pub struct EpisodeMetaRow {
    pub episode_index: u64,
    pub tasks: Vec<String>,
    pub length: u64,
    pub data_chunk: u64,
    pub data_file: u64,
    pub dataset_from_index: u64,
    pub dataset_to_index: u64,
    /// Per camera key: chunk, file, from_timestamp, to_timestamp.
    pub videos: Vec<(String, u64, u64, f64, f64)>,
    /// Per feature name, in info.json order.
    pub stats: Vec<(String, FeatureStats)>,
    pub meta_chunk: u64,
    pub meta_file: u64,
}

fn single_int(v: u64) -> ArrayRef {
    Arc::new(Int64Array::from_iter_values([v as i64]))
}

pub(crate) fn stat_list(kind: StatKind, values: &[f64], keep_int: bool) -> (DataType, ArrayRef) {
    match kind {
        StatKind::Image => {
            // (3,1,1): list<list<list<double>>>
            let mut b = ListBuilder::new(ListBuilder::new(ListBuilder::new(Float64Builder::new())));
            for v in values {
                b.values().values().values().append_value(*v);
                b.values().values().append(true);
                b.values().append(true);
            }
            b.append(true);
            let a = b.finish();
            (a.data_type().clone(), Arc::new(a))
        }
        StatKind::Int if keep_int => {
            let mut b = ListBuilder::new(Int64Builder::new());
            for v in values {
                b.values().append_value(v.round() as i64);
            }
            b.append(true);
            let a = b.finish();
            (a.data_type().clone(), Arc::new(a))
        }
        _ => {
            let mut b = ListBuilder::new(Float64Builder::new());
            b.values().append_slice(values);
            b.append(true);
            let a = b.finish();
            (a.data_type().clone(), Arc::new(a))
        }
    }
}

/// Writes one episode's row of v3.0 `meta/episodes/chunk-XXX/file-XXX.parquet`, in lerobot's column order.
pub fn write_episode_meta(path: &Path, row: &EpisodeMetaRow) -> Result<(), RecorderError> {
    let mut fields: Vec<Field> = Vec::new();
    let mut cols: Vec<ArrayRef> = Vec::new();
    let mut push = |name: String, dt: DataType, a: ArrayRef| {
        fields.push(Field::new(name, dt, true));
        cols.push(a);
    };
    push(
        "episode_index".into(),
        DataType::Int64,
        single_int(row.episode_index),
    );
    let mut tb = ListBuilder::new(StringBuilder::new());
    for t in &row.tasks {
        tb.values().append_value(t);
    }
    tb.append(true);
    let ta = tb.finish();
    push("tasks".into(), ta.data_type().clone(), Arc::new(ta));
    push("length".into(), DataType::Int64, single_int(row.length));
    push(
        "data/chunk_index".into(),
        DataType::Int64,
        single_int(row.data_chunk),
    );
    push(
        "data/file_index".into(),
        DataType::Int64,
        single_int(row.data_file),
    );
    push(
        "dataset_from_index".into(),
        DataType::Int64,
        single_int(row.dataset_from_index),
    );
    push(
        "dataset_to_index".into(),
        DataType::Int64,
        single_int(row.dataset_to_index),
    );
    for (key, chunk, file, from, to) in &row.videos {
        push(
            format!("videos/{key}/chunk_index"),
            DataType::Int64,
            single_int(*chunk),
        );
        push(
            format!("videos/{key}/file_index"),
            DataType::Int64,
            single_int(*file),
        );
        push(
            format!("videos/{key}/from_timestamp"),
            DataType::Float64,
            Arc::new(arrow_array::Float64Array::from(vec![*from])),
        );
        push(
            format!("videos/{key}/to_timestamp"),
            DataType::Float64,
            Arc::new(arrow_array::Float64Array::from(vec![*to])),
        );
    }
    for (name, s) in &row.stats {
        let mut stat = |stat: &str, kind: StatKind, values: &[f64], keep_int: bool| {
            let (dt, a) = stat_list(kind, values, keep_int);
            push(format!("stats/{name}/{stat}"), dt, a);
        };
        let float_kind = if s.kind == StatKind::Image {
            StatKind::Image
        } else {
            StatKind::Float
        };
        stat("min", s.kind, &s.min, true);
        stat("max", s.kind, &s.max, true);
        stat("mean", float_kind, &s.mean, false);
        stat("std", float_kind, &s.std, false);
        #[allow(clippy::cast_precision_loss)]
        stat("count", StatKind::Int, &[s.count as f64], true);
        for ((_, qname), q) in QUANTILES.iter().zip(&s.quantiles) {
            stat(qname, float_kind, q, false);
        }
    }
    push(
        "meta/episodes/chunk_index".into(),
        DataType::Int64,
        single_int(row.meta_chunk),
    );
    push(
        "meta/episodes/file_index".into(),
        DataType::Int64,
        single_int(row.meta_file),
    );
    let batch =
        RecordBatch::try_new(Arc::new(Schema::new(fields)), cols).map_err(|e| RecorderError::Parquet {
            path: path.to_owned(),
            detail: e.to_string(),
        })?;
    write_batch(path, &batch)
}

/// Reads every row of a data parquet file back (tests and the resume check use it).
pub fn read_rows(path: &Path) -> Result<Vec<Row>, RecorderError> {
    let bad = |detail: &str| RecorderError::Parquet {
        path: path.to_owned(),
        detail: detail.to_owned(),
    };
    let mut out = Vec::new();
    for b in read_batches(path)? {
        let fsl = |name: &str| {
            b.column_by_name(name)
                .and_then(|c| c.as_any().downcast_ref::<FixedSizeListArray>().cloned())
                .ok_or_else(|| bad(&format!("{name} is not a fixed_size_list")))
        };
        let int = |name: &str| {
            b.column_by_name(name)
                .and_then(|c| c.as_any().downcast_ref::<Int64Array>().cloned())
                .ok_or_else(|| bad(&format!("{name} is not int64")))
        };
        let (state, action) = (fsl("observation.state")?, fsl("action")?);
        let flag = |name: &str| match b.column_by_name(name) {
            None => Ok(None),
            Some(c) => c
                .as_any()
                .downcast_ref::<BooleanArray>()
                .cloned()
                .map(Some)
                .ok_or_else(|| bad(&format!("{name} is not bool"))),
        };
        let (success, intervention) = (flag(SUCCESS_FEATURE)?, flag(INTERVENTION_FEATURE)?);
        let ts = b
            .column_by_name("timestamp")
            .and_then(|c| c.as_any().downcast_ref::<Float32Array>().cloned())
            .ok_or_else(|| bad("timestamp is not float32"))?;
        let (fi, ei, ix, ti) = (
            int("frame_index")?,
            int("episode_index")?,
            int("index")?,
            int("task_index")?,
        );
        let floats = |l: &FixedSizeListArray, i: usize| -> Vec<f32> {
            l.value(i)
                .as_any()
                .downcast_ref::<Float32Array>()
                .map(|a| a.values().to_vec())
                .unwrap_or_default()
        };
        for i in 0..b.num_rows() {
            out.push(Row {
                state: floats(&state, i),
                action: floats(&action, i),
                success: success.as_ref().map(|s| s.value(i)),
                intervention: intervention.as_ref().map(|s| s.value(i)),
                timestamp: ts.value(i),
                frame_index: fi.value(i),
                episode_index: ei.value(i),
                index: ix.value(i),
                task_index: ti.value(i),
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_newest_row_takes_an_outcome_even_at_a_row_group_boundary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.parquet");
        let flags = FlagColumns {
            success: true,
            intervention: false,
        };
        let mut w = DataWriter::create(&p, 1, 1, true, flags).unwrap();
        assert!(!w.set_last_success(true), "no row yet");
        // Exactly one full row group: the row that completes it is the one an outcome at Stop marks.
        for i in 0..ROWS_PER_GROUP as i64 {
            w.push(Row {
                state: vec![0.0],
                action: vec![0.0],
                success: Some(false),
                intervention: None,
                timestamp: i as f32 / 20.0,
                frame_index: i,
                episode_index: 0,
                index: i,
                task_index: 0,
            })
            .unwrap();
        }
        assert!(w.set_last_success(true));
        w.finish().unwrap();
        let rows = read_rows(&p).unwrap();
        let marked: Vec<i64> = rows
            .iter()
            .filter(|r| r.success == Some(true))
            .map(|r| r.frame_index)
            .collect();
        assert_eq!(marked, [ROWS_PER_GROUP as i64 - 1]);
        let without = DataWriter::create(&dir.path().join("e.parquet"), 1, 1, true, FlagColumns::default());
        let mut without = without.unwrap();
        without
            .push(Row {
                state: vec![0.0],
                action: vec![0.0],
                success: None,
                intervention: None,
                timestamp: 0.0,
                frame_index: 0,
                episode_index: 0,
                index: 0,
                task_index: 0,
            })
            .unwrap();
        assert!(
            !without.set_last_success(true),
            "a dataset without the column has nothing to mark"
        );
    }

    #[test]
    fn data_rows_round_trip_in_row_groups() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.parquet");
        let flags = FlagColumns {
            success: true,
            intervention: true,
        };
        let mut w = DataWriter::create(&p, 3, 2, true, flags).unwrap();
        for i in 0..(ROWS_PER_GROUP as i64 + 10) {
            w.push(Row {
                state: vec![i as f32, 1.0, 2.0],
                action: vec![-(i as f32), 0.5],
                success: Some(i % 3 == 0),
                intervention: Some(i % 2 == 0),
                timestamp: i as f32 / 20.0,
                frame_index: i,
                episode_index: 3,
                index: 100 + i,
                task_index: 1,
            })
            .unwrap();
        }
        assert_eq!(w.finish().unwrap(), ROWS_PER_GROUP as u64 + 10);
        let rows = read_rows(&p).unwrap();
        assert_eq!(rows.len(), ROWS_PER_GROUP + 10);
        assert_eq!(rows[7].state, vec![7.0, 1.0, 2.0]);
        assert_eq!((rows[7].index, rows[7].episode_index), (107, 3));
        assert_eq!((rows[6].success, rows[7].success), (Some(true), Some(false)));
        assert_eq!(
            (rows[6].intervention, rows[7].intervention),
            (Some(true), Some(false))
        );
        let file = File::open(&p).unwrap();
        let meta = parquet::file::reader::FileReader::metadata(
            &parquet::file::serialized_reader::SerializedFileReader::new(file).unwrap(),
        )
        .clone();
        assert_eq!(
            meta.num_row_groups(),
            2,
            "rows are flushed in row groups as they come"
        );
        let kv = meta.file_metadata().key_value_metadata().unwrap();
        let hf = kv.iter().find(|k| k.key == "huggingface").unwrap();
        assert!(
            hf.value
                .as_deref()
                .unwrap()
                .contains(r#""next.success":{"_type":"Value","dtype":"bool"}"#),
            "{hf:?}"
        );
        assert!(
            hf.value
                .as_deref()
                .unwrap()
                .contains(r#""intervention":{"_type":"Value","dtype":"bool"}"#),
            "{hf:?}"
        );
    }

    #[test]
    fn tasks_round_trip_in_index_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("tasks.parquet");
        let tasks = vec!["pick".to_owned(), "place ünïcode".to_owned()];
        write_tasks(&p, &tasks).unwrap();
        assert_eq!(read_tasks(&p).unwrap(), tasks);
    }
}

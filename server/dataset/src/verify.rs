//! Read-only dataset verification: checks a LeRobot v3.0 or v2.1 dataset against the rules its loaders
//! enforce and says, in words, what is wrong. Nothing is modified (unlike `Dataset::open`, which cleans up
//! an interrupted episode), so it is safe on a dataset another process is writing.

use crate::av::probe::{FrameTimes, video_duration_s, video_frame_times};
use crate::dataset::{TimestampMismatch, timestamp_pairs};
use crate::parquet_io::{float_column, int_column};
use arrow_array::RecordBatch;
use arrow_array::cast::AsArray;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// What verification found.
#[derive(Debug, Default, Clone)]
pub struct Report {
    /// `codebase_version` from info.json.
    pub version: String,
    pub episodes: u64,
    pub frames: u64,
    /// Problems, each a sentence; empty when the dataset is valid.
    pub problems: Vec<String>,
    /// What a valid dataset still gets wrong for some reader (timestamps that pair a frame with its
    /// predecessor in GR00T's default reader), each a sentence.
    pub warnings: Vec<String>,
    /// What the data files say of each episode, by episode index.
    pub per_episode: BTreeMap<i64, EpisodeFacts>,
    /// The task table (task index order), when it could be read.
    pub tasks: Vec<String>,
}

/// One episode as its data rows describe it.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct EpisodeFacts {
    pub frames: u64,
    /// Task indices its rows carry (one, for every dataset phone2act or lerobot writes).
    pub task_indices: BTreeSet<i64>,
    /// `next.success` at the episode's last frame, if the dataset records it.
    pub success_at_end: Option<bool>,
    /// Frame index of the row `success_at_end` was taken from.
    last_frame: i64,
}

impl Report {
    pub fn ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// Per video key: the file holding an episode and the episode's time span in it.
type EpisodeVideos = BTreeMap<String, (PathBuf, f64, f64)>;

/// Columns the data parquet must carry besides the declared vector features.
const INDEX_COLUMNS: [&str; 5] = ["timestamp", "frame_index", "episode_index", "index", "task_index"];

fn files_with_ext(dir: &Path, ext: &str, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let mut entries: Vec<_> = entries.filter_map(Result::ok).map(|e| e.path()).collect();
    entries.sort();
    for path in entries {
        if path.is_dir() {
            // Staging folders of an episode in progress are not part of the dataset.
            if path
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with('.'))
            {
                continue;
            }
            files_with_ext(&path, ext, out);
        } else if path.extension().is_some_and(|e| e == ext) {
            out.push(path);
        }
    }
}

fn read_parquet(path: &Path) -> Result<Vec<RecordBatch>, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
        .and_then(parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::build)
        .map_err(|e| format!("{} is not a readable parquet file: {e}", path.display()))?;
    reader
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("{}: {e}", path.display()))
}

/// Frame k of an episode must be presented at exactly `(first + k) / fps` seconds of its file, where `first`
/// is the episode's first frame in the file (`from_timestamp * fps`): the timestamp rule (see
/// [`timestamp_pairs`]) places every timestamp at or just after that time, so a time base that does not
/// hold `k / fps` exactly, or a `from_timestamp` off the frame grid, would pair it with a neighbour.
fn check_presentation(
    times: &FrameTimes,
    from_s: f64,
    frames: u64,
    fps: u32,
    what: &str,
    report: &mut Report,
) {
    let (pts, num, den) = times;
    let first = from_s * f64::from(fps);
    // The metadata's float64 from_timestamp may be an ulp off the grid; a millionth of a frame is far below the
    // timestamps' margin.
    if (first - first.round()).abs() > 1e-6 || first < 0.0 {
        report.problems.push(format!(
            "{what}: from_timestamp {from_s} is not a whole number of frames at {fps} fps"
        ));
        return;
    }
    let first = first.round() as usize;
    for k in 0..frames as usize {
        let Some(&p) = pts.get(first + k) else {
            report.problems.push(format!(
                "{what}: the file has {} frames, the episode needs frame {}",
                pts.len(),
                first + k
            ));
            return;
        };
        // pts * num / den == (first + k) / fps, in integers.
        if i128::from(p) * i128::from(*num) * i128::from(fps) != (first + k) as i128 * i128::from(*den) {
            report.problems.push(format!(
                "{what}: frame {k} is presented at {p} * {num}/{den} s, not at {}/{fps} s: its timestamp would pair with another frame",
                first + k
            ));
            return;
        }
    }
}

/// Verifies the dataset at `root`.
pub fn verify(root: &Path) -> Report {
    let mut report = Report::default();
    let info_path = root.join("meta/info.json");
    let info: Value = match std::fs::read_to_string(&info_path).map(|t| serde_json::from_str(&t)) {
        Ok(Ok(v)) => v,
        Ok(Err(e)) => {
            report
                .problems
                .push(format!("meta/info.json is not valid JSON: {e}"));
            return report;
        }
        Err(e) => {
            report.problems.push(format!(
                "{} cannot be read ({e}): not a LeRobot dataset (phone2act writes nothing there before the first episode is saved)",
                info_path.display()
            ));
            return report;
        }
    };
    info["codebase_version"]
        .as_str()
        .unwrap_or("")
        .clone_into(&mut report.version);
    let v30 = match report.version.as_str() {
        "v3.0" => true,
        "v2.1" | "v2.0" => false,
        other => {
            report
                .problems
                .push(format!("codebase_version {other:?} is neither v3.0 nor v2.1"));
            return report;
        }
    };
    let fps = info["fps"].as_f64().unwrap_or(0.0);
    if fps <= 0.0 {
        report.problems.push("info.json has no positive fps".to_owned());
        return report;
    }
    if fps.fract() != 0.0 || fps > 1000.0 {
        report.problems.push(format!(
            "info.json's fps {fps} is not a whole number of frames per second up to 1000"
        ));
        return report;
    }
    let fps_whole = fps as u32;
    let Some(features) = info["features"].as_object() else {
        report.problems.push("info.json has no features".to_owned());
        return report;
    };
    let video_keys: Vec<String> = features
        .iter()
        .filter(|(_, f)| f["dtype"] == "video")
        .map(|(k, _)| k.clone())
        .collect();
    let column_keys: BTreeSet<String> = features
        .iter()
        .filter(|(_, f)| f["dtype"] != "video")
        .map(|(k, _)| k.clone())
        .collect();
    for col in INDEX_COLUMNS {
        if !column_keys.contains(col) {
            report
                .problems
                .push(format!("info.json does not declare the {col:?} feature"));
        }
    }

    // Data files: columns, per-episode frame and timestamp continuity, global index.
    let mut data_files = Vec::new();
    files_with_ext(&root.join("data"), "parquet", &mut data_files);
    if data_files.is_empty() && info["total_episodes"].as_u64().unwrap_or(0) > 0 {
        report.problems.push("no parquet files under data/".to_owned());
    }
    let mut lengths: BTreeMap<i64, u64> = BTreeMap::new();
    let mut before_frame = 0u64;
    let mut first_before: Option<String> = None;
    let mut indices = Vec::new();
    let mut data_tasks: BTreeSet<i64> = BTreeSet::new();
    for path in &data_files {
        let rel = path.strip_prefix(root).unwrap_or(path).display().to_string();
        let batches = match read_parquet(path) {
            Ok(b) => b,
            Err(e) => {
                report.problems.push(e);
                continue;
            }
        };
        if let Some(first) = batches.first() {
            let names: BTreeSet<String> = first.schema().fields().iter().map(|f| f.name().clone()).collect();
            for missing in column_keys.difference(&names) {
                report
                    .problems
                    .push(format!("{rel} lacks the declared column {missing:?}"));
            }
            for extra in names.difference(&column_keys) {
                report.problems.push(format!("{rel} has column {extra:?} that info.json does not declare (the v3.0 loader refuses this)"));
            }
        }
        let mut last_frame: BTreeMap<i64, i64> = BTreeMap::new();
        for batch in &batches {
            let (Some(ts), Some(fi), Some(ep), Some(ix)) = (
                float_column(batch, "timestamp"),
                int_column(batch, "frame_index"),
                int_column(batch, "episode_index"),
                int_column(batch, "index"),
            ) else {
                report.problems.push(format!(
                    "{rel}: timestamp/frame_index/episode_index/index columns unreadable"
                ));
                break;
            };
            for row in 0..batch.num_rows() {
                let expected = last_frame.get(&ep[row]).map_or(0, |f| f + 1);
                if fi[row] != expected && report.problems.len() < 50 {
                    report.problems.push(format!(
                        "{rel}: episode {} jumps from frame {} to {} (a gap the loader rejects)",
                        ep[row],
                        expected - 1,
                        fi[row]
                    ));
                }
                last_frame.insert(ep[row], fi[row]);
                // Read back as f64 from a float32 column: the cast is exact. A negative frame index is reported
                // as a gap above.
                let pairing = u64::try_from(fi[row])
                    .ok()
                    .map(|k| timestamp_pairs(ts[row] as f32, k, fps_whole));
                match pairing {
                    Some(Err(why @ TimestampMismatch::BeyondTolerance { .. }))
                        if report.problems.len() < 50 =>
                    {
                        report.problems.push(format!(
                            "{rel}: episode {} frame {}: timestamp {:.6} {why}",
                            ep[row], fi[row], ts[row]
                        ));
                    }
                    Some(Err(why @ TimestampMismatch::BeforeFrame { .. })) => {
                        before_frame += 1;
                        first_before.get_or_insert_with(|| {
                            format!(
                                "{rel}: episode {} frame {}: timestamp {:.9} {why}",
                                ep[row], fi[row], ts[row]
                            )
                        });
                    }
                    _ => {}
                }
                *lengths.entry(ep[row]).or_default() += 1;
                indices.push(ix[row]);
            }
            let task = int_column(batch, "task_index");
            let success = batch
                .column_by_name("next.success")
                .and_then(|c| c.as_boolean_opt().cloned());
            for row in 0..batch.num_rows() {
                let facts = report.per_episode.entry(ep[row]).or_default();
                facts.frames += 1;
                if let Some(t) = &task {
                    facts.task_indices.insert(t[row]);
                }
                if let Some(s) = &success
                    && (facts.success_at_end.is_none() || fi[row] >= facts.last_frame)
                {
                    facts.success_at_end = Some(s.value(row));
                    facts.last_frame = fi[row];
                }
            }
            if let Some(t) = task {
                data_tasks.extend(t);
            }
        }
    }
    if let Some(first) = first_before {
        report.warnings.push(format!(
            "{before_frame} of {} frames have a timestamp below frame_index / fps (LeRobot's rounding): LeRobot reads them, GR00T's default reader pairs them with the previous frame. First: {first}",
            indices.len()
        ));
    }
    indices.sort_unstable();
    if indices.iter().enumerate().any(|(i, &ix)| ix != i as i64) {
        report
            .problems
            .push("the global `index` column is not 0..total_frames without gaps or repeats".to_owned());
    }
    report.frames = lengths.values().sum();
    report.episodes = lengths.len() as u64;
    let total_frames = info["total_frames"].as_u64().unwrap_or(u64::MAX);
    let total_episodes = info["total_episodes"].as_u64().unwrap_or(u64::MAX);
    if total_frames != report.frames {
        report.problems.push(format!(
            "info.json says {total_frames} frames, the data files hold {}",
            report.frames
        ));
    }
    if total_episodes != report.episodes {
        report.problems.push(format!(
            "info.json says {total_episodes} episodes, the data files hold {}",
            report.episodes
        ));
    }

    // Episode metadata and videos.
    let mut episode_meta: BTreeMap<i64, (u64, EpisodeVideos)> = BTreeMap::new();
    // Task texts named by the episode metadata, and the task table (index order), to cross-check them.
    let mut meta_tasks: BTreeSet<String> = BTreeSet::new();
    let mut tasks: Option<Vec<String>> = None;
    if v30 {
        let mut meta_files = Vec::new();
        files_with_ext(&root.join("meta/episodes"), "parquet", &mut meta_files);
        for path in &meta_files {
            match read_parquet(path) {
                Ok(batches) => {
                    for batch in &batches {
                        let (Some(ep), Some(len)) =
                            (int_column(batch, "episode_index"), int_column(batch, "length"))
                        else {
                            report
                                .problems
                                .push(format!("{} lacks episode_index/length", path.display()));
                            continue;
                        };
                        for row in 0..batch.num_rows() {
                            let mut videos = BTreeMap::new();
                            for key in &video_keys {
                                let col = |s: &str| format!("videos/{key}/{s}");
                                let chunk = int_column(batch, &col("chunk_index")).map(|v| v[row]);
                                let file = int_column(batch, &col("file_index")).map(|v| v[row]);
                                let from = float_column(batch, &col("from_timestamp")).map(|v| v[row]);
                                let to = float_column(batch, &col("to_timestamp")).map(|v| v[row]);
                                if let (Some(c), Some(f), Some(from), Some(to)) = (chunk, file, from, to) {
                                    let rel = format!("videos/{key}/chunk-{c:03}/file-{f:03}.mp4");
                                    videos.insert(key.clone(), (root.join(rel), from, to));
                                } else {
                                    report
                                        .problems
                                        .push(format!("episode {} has no video location for {key}", ep[row]));
                                }
                            }
                            let rel = path.strip_prefix(root).unwrap_or(path).display().to_string();
                            if episode_meta
                                .insert(ep[row], (len[row].max(0) as u64, videos))
                                .is_some()
                            {
                                report.problems.push(format!(
                                    "episode index {} appears twice in the episode metadata (again in {rel})",
                                    ep[row]
                                ));
                            }
                            if let Some(tasks) = string_list_column(batch, "tasks", row) {
                                meta_tasks.extend(tasks);
                            }
                        }
                    }
                }
                Err(e) => report.problems.push(e),
            }
        }
        let tp = root.join("meta/tasks.parquet");
        if tp.exists() {
            match crate::parquet_io::read_tasks(&tp) {
                Ok(t) => tasks = Some(t),
                Err(e) => report.problems.push(format!("meta/tasks.parquet: {e}")),
            }
        } else {
            report.problems.push("meta/tasks.parquet is missing".to_owned());
        }
    } else {
        let text = std::fs::read_to_string(root.join("meta/episodes.jsonl")).unwrap_or_default();
        let chunks_size = info["chunks_size"].as_i64().unwrap_or(1000).max(1);
        let video_path = info["video_path"].as_str().unwrap_or("");
        for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let Ok(v) = serde_json::from_str::<Value>(line) else {
                report
                    .problems
                    .push(format!("meta/episodes.jsonl line {} is not JSON", n + 1));
                continue;
            };
            let ep = v["episode_index"].as_i64().unwrap_or(-1);
            let mut videos = BTreeMap::new();
            for key in &video_keys {
                let rel = video_path
                    .replace("{episode_chunk:03d}", &format!("{:03}", ep / chunks_size))
                    .replace("{video_key}", key)
                    .replace("{episode_index:06d}", &format!("{ep:06}"));
                let len = v["length"].as_u64().unwrap_or(0);
                videos.insert(key.clone(), (root.join(rel), 0.0, len as f64 / fps));
            }
            if episode_meta
                .insert(ep, (v["length"].as_u64().unwrap_or(0), videos))
                .is_some()
            {
                report.problems.push(format!(
                    "episode index {ep} appears twice in meta/episodes.jsonl (again on line {})",
                    n + 1
                ));
            }
            meta_tasks.extend(
                v["tasks"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|t| t.as_str().map(str::to_owned)),
            );
        }
        check_episodes_stats(root, &episode_meta, &mut report);
        match std::fs::read_to_string(root.join("meta/tasks.jsonl")) {
            Ok(text) => {
                let mut table: BTreeMap<i64, String> = BTreeMap::new();
                for line in text.lines().filter(|l| !l.trim().is_empty()) {
                    let v: Value = serde_json::from_str(line).unwrap_or_default();
                    let i = v["task_index"].as_i64().unwrap_or(-1);
                    let t = v["task"].as_str().unwrap_or("").to_owned();
                    if table.insert(i, t).is_some() {
                        report
                            .problems
                            .push(format!("task index {i} appears twice in meta/tasks.jsonl"));
                    }
                }
                if table.keys().copied().ne(0..table.len() as i64) {
                    report
                        .problems
                        .push("meta/tasks.jsonl task indices are not 0..n".to_owned());
                }
                tasks = Some(table.into_values().collect());
            }
            Err(_) => report.problems.push("meta/tasks.jsonl is missing".to_owned()),
        }
    }
    // GR00T's layout file, in either format (phone2act writes it into both; lerobot ignores it).
    if let Ok(text) = std::fs::read_to_string(root.join("meta/modality.json")) {
        check_modality(&text, features, &mut report);
    }
    if episode_meta.len() as u64 != report.episodes {
        report.problems.push(format!(
            "episode metadata lists {} episodes, the data files hold {}",
            episode_meta.len(),
            report.episodes
        ));
    }
    report.tasks.clone_from(tasks.as_ref().unwrap_or(&Vec::new()));
    check_metadata_agrees(
        &info,
        &episode_meta,
        &lengths,
        tasks.as_deref(),
        &meta_tasks,
        &data_tasks,
        &mut report,
    );
    let mut durations: BTreeMap<PathBuf, Result<(f64, i64), String>> = BTreeMap::new();
    let mut frame_times: BTreeMap<PathBuf, Result<FrameTimes, String>> = BTreeMap::new();
    for (ep, (len, videos)) in &episode_meta {
        for (key, (path, from, _)) in videos {
            let times = frame_times
                .entry(path.clone())
                .or_insert_with(|| video_frame_times(path));
            // An unreadable file is reported once, below, by the duration probe.
            if let Ok(times) = times {
                check_presentation(
                    times,
                    *from,
                    *len,
                    fps_whole,
                    &format!("episode {ep} {key}"),
                    &mut report,
                );
            }
        }
        match lengths.get(ep) {
            Some(rows) if rows != len => {
                report.problems.push(format!(
                    "episode {ep}: metadata says {len} frames, the data holds {rows}"
                ));
            }
            None => report
                .problems
                .push(format!("episode {ep} is in the metadata but has no data rows")),
            _ => {}
        }
        for (key, (path, _from, to)) in videos {
            let probe = durations
                .entry(path.clone())
                .or_insert_with(|| video_duration_s(path));
            match probe {
                Ok((duration_s, _)) => {
                    // The last frame starts at to - 1/fps; its presentation must exist in the file.
                    if *duration_s + 1e-3 < to - 1.0 / fps {
                        report.problems.push(format!(
                            "episode {ep} {key}: video {} lasts {duration_s:.3} s, the episode needs {to:.3} s",
                            path.strip_prefix(root).unwrap_or(path).display()
                        ));
                    }
                }
                Err(e) => report.problems.push(format!("episode {ep} {key}: {e}")),
            }
        }
    }
    // GR00T N1.6 snaps a step's time to a multiple of 1 / (frames / duration): a file whose rate comes out
    // above fps in float64 puts some of those times an ulp before their frame.
    for (path, times) in &frame_times {
        if let (Ok((pts, _, _)), Some(Ok((duration_s, _)))) = (times, durations.get(path))
            && !pts.is_empty()
            && pts.len() as f64 / duration_s > fps
        {
            report.warnings.push(format!(
                "video {}: {} frames over {duration_s} s make an average rate above {fps} fps in float64: GR00T N1.6's reader pairs some steps with the previous frame",
                path.strip_prefix(root).unwrap_or(path).display(),
                pts.len()
            ));
        }
    }
    report
}

/// The metadata files must tell one story: info.json's totals, the episode list (indices 0..n, each
/// once), the data files and the task table.
fn check_metadata_agrees(
    info: &Value,
    episode_meta: &BTreeMap<i64, (u64, EpisodeVideos)>,
    lengths: &BTreeMap<i64, u64>,
    tasks: Option<&[String]>,
    meta_tasks: &BTreeSet<String>,
    data_tasks: &BTreeSet<i64>,
    report: &mut Report,
) {
    let n = episode_meta.len() as u64;
    if let Some(total) = info["total_episodes"].as_u64()
        && total != n
    {
        report.problems.push(format!(
            "info.json says {total} episodes, the episode metadata lists {n}"
        ));
    }
    let meta_frames: u64 = episode_meta.values().map(|(len, _)| len).sum();
    if let Some(total) = info["total_frames"].as_u64()
        && total != meta_frames
    {
        report.problems.push(format!(
            "info.json says {total} frames, the episode metadata adds up to {meta_frames}"
        ));
    }
    if episode_meta.keys().copied().ne(0..n as i64) {
        report.problems.push(format!(
            "episode metadata indices are not 0..{n}: {:?}",
            episode_meta.keys().take(20).collect::<Vec<_>>()
        ));
    }
    for ep in lengths.keys().filter(|ep| !episode_meta.contains_key(ep)) {
        report
            .problems
            .push(format!("episode {ep} has data rows but no episode metadata"));
    }
    let Some(tasks) = tasks else { return };
    if let Some(total) = info["total_tasks"].as_u64()
        && total != tasks.len() as u64
    {
        report.problems.push(format!(
            "info.json says {total} tasks, the task table has {}",
            tasks.len()
        ));
    }
    for t in meta_tasks.iter().filter(|t| !tasks.contains(t)) {
        report.problems.push(format!(
            "task {t:?} is in the episode metadata but not in the task table"
        ));
    }
    for i in data_tasks.iter().filter(|&&i| i < 0 || i as usize >= tasks.len()) {
        report.problems.push(format!(
            "the data uses task_index {i}, the task table has {} tasks",
            tasks.len()
        ));
    }
}

/// v2.1: `episodes_stats.jsonl` holds exactly one line per episode of `episodes.jsonl`.
fn check_episodes_stats(
    root: &Path,
    episode_meta: &BTreeMap<i64, (u64, EpisodeVideos)>,
    report: &mut Report,
) {
    let Ok(text) = std::fs::read_to_string(root.join("meta/episodes_stats.jsonl")) else {
        report
            .problems
            .push("meta/episodes_stats.jsonl is missing".to_owned());
        return;
    };
    let mut seen = BTreeSet::new();
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let ep = serde_json::from_str::<Value>(line).unwrap_or_default()["episode_index"]
            .as_i64()
            .unwrap_or(-1);
        if !seen.insert(ep) {
            report.problems.push(format!(
                "episode index {ep} appears twice in meta/episodes_stats.jsonl"
            ));
        }
    }
    let listed: BTreeSet<i64> = episode_meta.keys().copied().collect();
    if seen != listed {
        report.problems.push(format!(
            "meta/episodes_stats.jsonl covers {} episodes, meta/episodes.jsonl lists {}; they differ",
            seen.len(),
            listed.len()
        ));
    }
}

fn string_list_column(batch: &RecordBatch, name: &str, row: usize) -> Option<Vec<String>> {
    let list = batch.column_by_name(name)?.as_list_opt::<i32>()?;
    let values = list.value(row);
    let strings = values.as_string_opt::<i32>()?;
    Some(strings.iter().flatten().map(str::to_owned).collect())
}

fn check_modality(text: &str, features: &serde_json::Map<String, Value>, report: &mut Report) {
    let Ok(modality) = serde_json::from_str::<Value>(text) else {
        report
            .problems
            .push("meta/modality.json is not valid JSON".to_owned());
        return;
    };
    for (group, key) in [("state", "observation.state"), ("action", "action")] {
        let width = features
            .get(key)
            .and_then(|f| f["shape"][0].as_u64())
            .unwrap_or(0);
        let Some(entries) = modality[group].as_object() else {
            report
                .problems
                .push(format!("meta/modality.json has no {group:?} block"));
            continue;
        };
        for (name, range) in entries {
            let (start, end) = (
                range["start"].as_u64().unwrap_or(u64::MAX),
                range["end"].as_u64().unwrap_or(0),
            );
            if start >= end || end > width {
                report.problems.push(format!(
                    "meta/modality.json {group}.{name} = [{start}, {end}) does not fit {key} of width {width}"
                ));
            }
        }
    }
    // GR00T's loader reads `video.<name>` from the feature `original_key` names, and an annotation from the
    // column its `original_key` names: a key the dataset lacks fails there, at training time.
    for (group, want_video) in [("video", true), ("annotation", false)] {
        let Some(entries) = modality[group].as_object() else {
            continue;
        };
        for (name, entry) in entries {
            let Some(original) = entry["original_key"].as_str() else {
                report
                    .problems
                    .push(format!("meta/modality.json {group}.{name} has no original_key"));
                continue;
            };
            let found = features.get(original);
            let is_video = found.is_some_and(|f| f["dtype"] == "video" || f["dtype"] == "image");
            if found.is_none() || is_video != want_video {
                let what = if want_video {
                    "video feature"
                } else {
                    "data column"
                };
                report.problems.push(format!(
                    "meta/modality.json {group}.{name} names {original:?}, which is not a {what} of info.json"
                ));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Datasets written by the real lerobot library, committed with the repository (tests/fixtures/README.md).
    fn golden(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/fixtures")
            .join(name)
    }

    fn copy_dir(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                copy_dir(&e.path(), &to.join(e.file_name()));
            } else {
                std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
            }
        }
    }

    #[test]
    fn golden_datasets_written_by_lerobot_verify_clean() {
        for name in ["lerobot_sample_v30", "lerobot_sample_v21"] {
            let root = golden(name);
            let report = verify(&root);
            assert!(report.ok(), "{name}: {:?}", report.problems);
            // lerobot's nearest-float32 timestamps: 0.7 and 0.9 s lie below 7/10 and 9/10 s.
            assert_eq!(report.warnings.len(), 1, "{name}: {:?}", report.warnings);
            assert!(
                report.warnings[0].starts_with("5 of 30 frames have a timestamp below"),
                "{name}: {:?}",
                report.warnings
            );
            assert_eq!((report.episodes, report.frames), (3, 30), "{name}");
            // Per episode, from the rows: the frames add up, one task each, no `next.success` column.
            assert_eq!(report.per_episode.len(), 3, "{name}");
            let frames: u64 = report.per_episode.values().map(|f| f.frames).sum();
            assert_eq!(frames, 30, "{name}");
            for facts in report.per_episode.values() {
                assert!(
                    facts.frames > 0 && facts.task_indices.len() == 1,
                    "{name}: {facts:?}"
                );
                assert_eq!(facts.success_at_end, None, "{name}");
            }
            assert!(!report.tasks.is_empty(), "{name}");
        }
    }

    #[test]
    fn broken_copies_are_described_in_words() {
        let root = golden("lerobot_sample_v21");
        let dir = tempfile::tempdir().unwrap();
        copy_dir(&root, dir.path());
        std::fs::remove_file(
            dir.path()
                .join("videos/chunk-000/observation.images.front/episode_000001.mp4"),
        )
        .unwrap();
        let info_path = dir.path().join("meta/info.json");
        let info = std::fs::read_to_string(&info_path)
            .unwrap()
            .replace("\"total_frames\": 30", "\"total_frames\": 31");
        std::fs::write(&info_path, info).unwrap();
        let report = verify(dir.path());
        let text = report.problems.join("\n");
        assert!(text.contains("episode 1 observation.images.front"), "{text}");
        assert!(
            text.contains("info.json says 31 frames, the data files hold 30"),
            "{text}"
        );

        let empty = tempfile::tempdir().unwrap();
        let report = verify(empty.path());
        assert!(
            report.problems[0].contains("not a LeRobot dataset"),
            "{:?}",
            report.problems
        );
    }

    #[test]
    fn a_v30_modality_json_is_checked_against_the_features() {
        let dir = tempfile::tempdir().unwrap();
        copy_dir(&golden("lerobot_sample_v30"), dir.path());
        let path = dir.path().join("meta/modality.json");
        let good = serde_json::json!({
            "state": {"arm": {"start": 0, "end": 5}, "gripper": {"start": 5, "end": 6}},
            "action": {"arm": {"start": 0, "end": 6, "absolute": true}},
            "video": {"front": {"original_key": "observation.images.front"}},
            "annotation": {"human.task_description": {"original_key": "task_index"}},
        });
        std::fs::write(&path, good.to_string()).unwrap();
        let report = verify(dir.path());
        assert!(report.problems.is_empty(), "{:?}", report.problems);

        let mut bad = good;
        bad["action"]["arm"]["end"] = serde_json::json!(7);
        bad["video"]["top"] = serde_json::json!({"original_key": "observation.images.top"});
        bad["annotation"]["human.success"] = serde_json::json!({"original_key": "next.success"});
        std::fs::write(&path, bad.to_string()).unwrap();
        let text = verify(dir.path()).problems.join("\n");
        for want in [
            "meta/modality.json action.arm = [0, 7) does not fit action of width 6",
            "meta/modality.json video.top names \"observation.images.top\", which is not a video feature",
            "meta/modality.json annotation.human.success names \"next.success\", which is not a data column",
        ] {
            assert!(text.contains(want), "{want}: {text}");
        }
    }
}

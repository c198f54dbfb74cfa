//! A LeRobot dataset on disk: layout, `info.json`, metadata files, and the crash-safe episode commit.
//!
//! Durability design. Every episode is written into its *own* new files (v3.0: its own data, video and
//! episodes-metadata file, i.e. the size roll-over happens after every episode; lerobot's reader accepts any
//! split of episodes into files). Nothing already committed is ever appended to or rewritten in place, so a
//! kill can never damage a saved episode. While recording, the episode's parquet and mp4s stream into
//! `<root>/.phone2act-staging/`, which no reader looks at. Saving = closing those files, writing the new
//! metadata files into staging too, fsyncing, writing a rename journal, and renaming everything into place
//! in an order in which every intermediate state still loads in lerobot (v3.0: videos, tasks, episode
//! metadata, data, then `info.json` last). v2.1 needs its data file and the `episodes.jsonl` line to appear
//! together; they are renamed back to back (a window of two syscalls) and `open` replays the journal if a
//! crash hit between them. `open` also deletes whatever an interrupted recording left in staging.

use crate::error::RecorderError;
use crate::fsutil::{Journal, sync_dir, write_atomic, write_synced};
use crate::parquet_io::{self, DataWriter, EpisodeMetaRow, Row, SUCCESS_FEATURE};
use crate::quantiles::{QUANTILES_FILE, QuantileStore};
use crate::spec::{DatasetSpec, Format, MAX_TASK_BYTES, VideoSettings};
use crate::stats::{Aggregate, ColumnStats, FeatureStats, StatKind};
use crate::video::{EncodeReport, EncoderThread};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

/// lerobot's `chunks_size`: files (v3.0) or episodes (v2.1) per chunk directory.
pub const CHUNKS_SIZE: u64 = 1000;
/// The provenance sidecar, ignored by lerobot and GR00T.
pub const PROVENANCE_FILE: &str = "meta/phone2act_provenance.json";
const STAGING_DIR: &str = ".phone2act-staging";
const JOURNAL_FILE: &str = ".phone2act-commit.json";
const DEFAULT_FEATURES: [&str; 5] = ["timestamp", "frame_index", "episode_index", "index", "task_index"];

/// A saved (or being saved) episode, as reported to the operator.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EpisodeSummary {
    pub index: u64,
    pub task: String,
    pub length_frames: u64,
    pub duration_s: f64,
    /// Ticks where a source had no new sample and its last value was reused (within tolerance).
    pub held_ticks: u64,
    /// Ticks not recorded because a source was stale beyond tolerance (the episode was paused).
    pub paused_ticks: u64,
    /// Ticks skipped because the recorder stalled longer than the hold tolerance (machine overloaded);
    /// not recorded, never a gap. Shorter stalls are caught up and counted in `held_ticks`.
    pub late_ticks: u64,
    /// Video frames that did not fit in an encoder queue (replaced by a repeat of the previous frame).
    pub dropped_frames: u64,
    pub start_unix_ns: i64,
    pub save_latency_s: f64,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct Provenance {
    software: String,
    version: String,
    format: String,
    video: Value,
    config: Value,
    sync: Value,
    episodes: Vec<EpisodeSummary>,
    /// Running aggregates of per-episode stats, so resuming needs no re-read of old episodes. (Files written
    /// before Rerecord stopped deleting saved episodes also hold an `undo` entry, which is ignored.)
    stats: BTreeMap<String, Aggregate>,
}

/// The dataset being written.
pub struct Dataset {
    spec: DatasetSpec,
    video: VideoSettings,
    tasks: Vec<String>,
    total_episodes: u64,
    total_frames: u64,
    next_data_file: u64,
    next_video_file: Vec<u64>,
    next_meta_file: u64,
    provenance: Provenance,
    episodes_jsonl: String,
    episodes_stats_jsonl: String,
    /// Dataset quantiles of the numeric columns (see [`crate::quantiles`]).
    quantiles: QuantileStore,
}

/// An episode being recorded into staging files.
pub struct EpisodeWriter {
    pub index: u64,
    pub task: String,
    task_index: i64,
    first_global_index: u64,
    data: DataWriter,
    pub(crate) encoders: Vec<EncoderThread>,
    state_stats: ColumnStats,
    action_stats: ColumnStats,
    /// `next.success`, when the dataset records it.
    success_stats: Option<ColumnStats>,
    frames: u64,
    fps: u32,
    staging: PathBuf,
}

fn file_path(root: &Path, top: &str, n: u64, ext: &str) -> PathBuf {
    root.join(format!(
        "{top}/chunk-{:03}/file-{:03}.{ext}",
        n / CHUNKS_SIZE,
        n % CHUNKS_SIZE
    ))
}

/// Largest `chunk*1000+file` among `dir/chunk-CCC/file-FFF.ext`, plus one (0 if none).
fn next_file_index(dir: &Path, ext: &str) -> u64 {
    let mut next = 0;
    let Ok(chunks) = fs::read_dir(dir) else { return 0 };
    for c in chunks.flatten() {
        let cname = c.file_name().to_string_lossy().into_owned();
        let Some(ci) = cname.strip_prefix("chunk-").and_then(|s| s.parse::<u64>().ok()) else {
            continue;
        };
        let Ok(files) = fs::read_dir(c.path()) else {
            continue;
        };
        for f in files.flatten() {
            let fname = f.file_name().to_string_lossy().into_owned();
            if let Some(fi) = fname
                .strip_prefix("file-")
                .and_then(|s| s.strip_suffix(&format!(".{ext}")))
                .and_then(|s| s.parse::<u64>().ok())
            {
                next = next.max(ci * CHUNKS_SIZE + fi + 1);
            }
        }
    }
    next
}

fn pretty(v: &Value) -> Vec<u8> {
    let mut out = Vec::new();
    let fmt = serde_json::ser::PrettyFormatter::with_indent(b"    ");
    let mut ser = serde_json::Serializer::with_formatter(&mut out, fmt);
    v.serialize(&mut ser).expect("JSON values always serialise");
    out
}

/// An ordered JSON object (serde_json's map sorts keys unless a workspace-wide feature is enabled).
struct Ordered(Vec<(String, Value)>);

impl Ordered {
    fn to_json_string(&self) -> String {
        // Serialise each value with serde, join in order by hand.
        let body: Vec<String> = self
            .0
            .iter()
            .map(|(k, v)| format!("{}: {}", Value::String(k.clone()), v))
            .collect();
        format!("{{{}}}", body.join(", "))
    }
}

impl Dataset {
    /// Opens `spec.root`, creating it or resuming it (finishing an interrupted save, removing the leftovers
    /// of an interrupted recording, and checking that fps, format and features match).
    pub fn open(spec: DatasetSpec) -> Result<Self, RecorderError> {
        spec.validate()?;
        let video = VideoSettings::parse(spec.video_codec.as_deref(), spec.format)?;
        let root = spec.root.clone();
        // Only the root: meta/ and info.json come with the first saved episode. An info.json for zero
        // episodes (v3.0: without tasks.parquet) is a dataset no reader accepts, and lerobot, finding none
        // it can load, goes looking for it on the Hub.
        fs::create_dir_all(&root).map_err(|e| RecorderError::io(&root, e))?;
        if let Some(ep) = Journal::recover(&root.join(JOURNAL_FILE))? {
            tracing::warn!(episode = ep, root = %root.display(), "finished a save interrupted by a crash");
        }
        let staging = root.join(STAGING_DIR);
        if staging.exists() {
            tracing::warn!(root = %root.display(), "removing the files of an episode interrupted while recording");
            fs::remove_dir_all(&staging).map_err(|e| RecorderError::io(&staging, e))?;
        }
        let mut ds = Dataset {
            next_video_file: vec![0; spec.cameras.len()],
            spec,
            video,
            tasks: Vec::new(),
            total_episodes: 0,
            total_frames: 0,
            next_data_file: 0,
            next_meta_file: 0,
            provenance: Provenance::default(),
            episodes_jsonl: String::new(),
            episodes_stats_jsonl: String::new(),
            quantiles: QuantileStore::default(),
        };
        let info_path = root.join("meta/info.json");
        if info_path.exists() {
            ds.resume(&info_path)?;
        }
        ds.provenance.software = "phone2act-recorder".into();
        ds.provenance.version = env!("CARGO_PKG_VERSION").into();
        ds.provenance.format = ds.spec.format.codebase_version().into();
        ds.provenance.video = serde_json::to_value(&ds.video).unwrap_or(Value::Null);
        ds.provenance.config = ds.spec.provenance.clone();
        ds.load_quantiles()?;
        Ok(ds)
    }

    /// Loads the persisted quantile sketches, or rebuilds them from the data when they are missing or do not
    /// describe exactly the committed episodes (a dataset from another writer or an older phone2act).
    fn load_quantiles(&mut self) -> Result<(), RecorderError> {
        let root = &self.spec.root;
        if let Some(q) = QuantileStore::load(root, self.total_episodes, self.total_frames) {
            self.quantiles = q;
        } else if self.total_episodes > 0 {
            tracing::warn!(root = %root.display(), "rebuilding the dataset quantiles from the data");
            self.quantiles = QuantileStore::rebuild(root, self.total_episodes)?;
            // A dataset from an older phone2act has averaged quantiles in stats.json: correct it now rather
            // than at the next save, if the running aggregates describe the same frames (each file is
            // replaced atomically, and both describe only committed episodes).
            let agg = &self.provenance.stats;
            if self.quantiles.current.frames == self.total_frames
                && agg.get("index").is_some_and(|a| a.count == self.total_frames)
            {
                let stats = stats_json(agg, &self.quantiles, self.spec.format);
                write_atomic(&root.join("meta/stats.json"), &pretty(&stats))?;
                write_atomic(&root.join(QUANTILES_FILE), &self.quantiles.encode())?;
            }
        }
        Ok(())
    }

    fn corrupt(&self, detail: impl Into<String>) -> RecorderError {
        RecorderError::CorruptDataset {
            root: self.spec.root.clone(),
            detail: detail.into(),
        }
    }

    fn resume(&mut self, info_path: &Path) -> Result<(), RecorderError> {
        let root = self.spec.root.clone();
        let text = fs::read_to_string(info_path).map_err(|e| RecorderError::io(info_path, e))?;
        let info: Value =
            serde_json::from_str(&text).map_err(|e| self.corrupt(format!("meta/info.json: {e}")))?;
        let version = info["codebase_version"].as_str().unwrap_or("?").to_owned();
        if version != self.spec.format.codebase_version() {
            return Err(RecorderError::FormatMismatch {
                root,
                found: version,
                wanted: self.spec.format.codebase_version().into(),
            });
        }
        let fps = info["fps"].as_u64().unwrap_or(0) as u32;
        if fps != self.spec.fps {
            return Err(RecorderError::FpsMismatch {
                root,
                found: fps,
                wanted: self.spec.fps,
            });
        }
        self.check_features(&info["features"])?;
        self.total_episodes = info["total_episodes"].as_u64().unwrap_or(0);
        self.total_frames = info["total_frames"].as_u64().unwrap_or(0);
        match self.spec.format {
            Format::V30 => {
                let tp = root.join("meta/tasks.parquet");
                if tp.exists() {
                    self.tasks = parquet_io::read_tasks(&tp)?;
                }
                self.next_data_file = next_file_index(&root.join("data"), "parquet");
                self.next_meta_file = next_file_index(&root.join("meta/episodes"), "parquet");
                for (i, c) in self.spec.cameras.iter().enumerate() {
                    self.next_video_file[i] = next_file_index(&root.join("videos").join(c.key()), "mp4");
                }
            }
            Format::V21 => {
                let read = |p: &str| fs::read_to_string(root.join(p)).unwrap_or_default();
                let mut tasks: Vec<(u64, String)> = Vec::new();
                for line in read("meta/tasks.jsonl").lines().filter(|l| !l.trim().is_empty()) {
                    let v: Value = serde_json::from_str(line)
                        .map_err(|e| self.corrupt(format!("meta/tasks.jsonl: {e}")))?;
                    tasks.push((
                        v["task_index"].as_u64().unwrap_or(0),
                        v["task"].as_str().unwrap_or("").to_owned(),
                    ));
                }
                tasks.sort();
                self.tasks = tasks.into_iter().map(|t| t.1).collect();
                self.episodes_jsonl = read("meta/episodes.jsonl");
                self.episodes_stats_jsonl = read("meta/episodes_stats.jsonl");
                let lines = self
                    .episodes_jsonl
                    .lines()
                    .filter(|l| !l.trim().is_empty())
                    .count() as u64;
                if lines != self.total_episodes {
                    return Err(self.corrupt(format!(
                        "meta/info.json says {} episodes, meta/episodes.jsonl has {lines}",
                        self.total_episodes
                    )));
                }
            }
        }
        let prov_path = root.join(PROVENANCE_FILE);
        if let Some(p) = fs::read(&prov_path)
            .ok()
            .and_then(|b| serde_json::from_slice::<Provenance>(&b).ok())
        {
            self.provenance = p;
            // Episodes past the committed count belong to a save that never reached info.json.
            self.provenance.episodes.retain(|e| e.index < self.total_episodes);
        }
        self.provenance.episodes = self.episodes_on_disk()?;
        tracing::info!(root = %root.display(), episodes = self.total_episodes, frames = self.total_frames, "resuming dataset");
        Ok(())
    }

    /// The committed episodes as the dataset's own metadata lists them, with the sidecar's extra fields
    /// (held, paused, late ticks, save latency) where the sidecar knows the episode. The sidecar alone is
    /// not the list: a dataset whose sidecar is missing, older or unreadable still lists every episode.
    fn episodes_on_disk(&self) -> Result<Vec<EpisodeSummary>, RecorderError> {
        let mut listed: Vec<(u64, String, u64)> = Vec::new();
        match self.spec.format {
            Format::V30 => {
                let mut files = Vec::new();
                let dir = self.spec.root.join("meta/episodes");
                for chunk in fs::read_dir(&dir).into_iter().flatten().flatten() {
                    for f in fs::read_dir(chunk.path()).into_iter().flatten().flatten() {
                        if f.path().extension().is_some_and(|e| e == "parquet") {
                            files.push(f.path());
                        }
                    }
                }
                files.sort();
                for f in files {
                    for e in parquet_io::read_episode_summaries(&f)? {
                        listed.push((e.episode_index, e.tasks.join("; "), e.length));
                    }
                }
            }
            Format::V21 => {
                for line in self.episodes_jsonl.lines().filter(|l| !l.trim().is_empty()) {
                    let v: Value = serde_json::from_str(line)
                        .map_err(|e| self.corrupt(format!("meta/episodes.jsonl: {e}")))?;
                    let task = v["tasks"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .filter_map(Value::as_str);
                    listed.push((
                        v["episode_index"].as_u64().unwrap_or(0),
                        task.collect::<Vec<_>>().join("; "),
                        v["length"].as_u64().unwrap_or(0),
                    ));
                }
            }
        }
        listed.sort_by_key(|e| e.0);
        listed.retain(|e| e.0 < self.total_episodes);
        let fps = f64::from(self.spec.fps);
        Ok(listed
            .into_iter()
            .map(|(index, task, length_frames)| {
                self.provenance
                    .episodes
                    .iter()
                    .find(|p| p.index == index && p.length_frames == length_frames)
                    .cloned()
                    .unwrap_or_else(|| EpisodeSummary {
                        index,
                        task,
                        length_frames,
                        duration_s: length_frames as f64 / fps,
                        ..EpisodeSummary::default()
                    })
            })
            .collect())
    }

    fn check_features(&self, found: &Value) -> Result<(), RecorderError> {
        let mismatch = |detail: String| RecorderError::FeatureMismatch {
            root: self.spec.root.clone(),
            detail,
        };
        let Some(found) = found.as_object() else {
            return Err(mismatch("info.json has no features".into()));
        };
        let want = self.features_json();
        let want_keys: Vec<&String> = want.0.iter().map(|(k, _)| k).collect();
        let mut found_keys: Vec<&String> = found.keys().collect();
        found_keys.sort();
        let mut wk = want_keys.clone();
        wk.sort();
        if wk != found_keys {
            return Err(mismatch(format!("dataset has {found_keys:?}, config has {wk:?}")));
        }
        for (k, w) in &want.0 {
            let f = &found[k];
            for field in ["dtype", "shape"] {
                if f[field] != w[field] {
                    return Err(mismatch(format!(
                        "{k}.{field} is {} in the dataset, {} in the config",
                        f[field], w[field]
                    )));
                }
            }
            if w["dtype"] != "video" && f["names"] != w["names"] {
                return Err(mismatch(format!(
                    "{k}.names are {} in the dataset, {} in the config",
                    f["names"], w["names"]
                )));
            }
        }
        Ok(())
    }

    fn features_json(&self) -> Ordered {
        let s = &self.spec;
        let mut f = vec![
            (
                "observation.state".to_owned(),
                json!({"dtype": "float32", "shape": [s.state_names.len()], "names": s.state_names}),
            ),
            (
                "action".to_owned(),
                json!({"dtype": "float32", "shape": [s.action_names.len()], "names": s.action_names}),
            ),
        ];
        if s.success {
            f.push((
                SUCCESS_FEATURE.to_owned(),
                json!({"dtype": "bool", "shape": [1], "names": null}),
            ));
        }
        for c in &s.cameras {
            f.push((
                c.key(),
                json!({
                    "dtype": "video",
                    "shape": [c.height, c.width, 3],
                    "names": ["height", "width", "channels"],
                    "info": {
                        "video.height": c.height, "video.width": c.width, "video.codec": self.video.codec,
                        "video.pix_fmt": "yuv420p", "video.is_depth_map": false, "video.fps": s.fps,
                        "video.channels": 3, "has_audio": false
                    }
                }),
            ));
        }
        f.push((
            "timestamp".to_owned(),
            json!({"dtype": "float32", "shape": [1], "names": null}),
        ));
        for k in &DEFAULT_FEATURES[1..] {
            f.push((
                (*k).to_owned(),
                json!({"dtype": "int64", "shape": [1], "names": null}),
            ));
        }
        Ordered(f)
    }

    /// `meta/info.json` for the current totals, keys in lerobot's order.
    fn info_json(&self) -> Vec<u8> {
        let s = &self.spec;
        let n = self.total_episodes;
        let mut top: Vec<(String, Value)> = vec![
            ("codebase_version".into(), json!(s.format.codebase_version())),
            ("robot_type".into(), json!(s.robot_type)),
            ("total_episodes".into(), json!(n)),
            ("total_frames".into(), json!(self.total_frames)),
            ("total_tasks".into(), json!(self.tasks.len())),
        ];
        match s.format {
            Format::V30 => {
                top.push(("chunks_size".into(), json!(CHUNKS_SIZE)));
                top.push(("data_files_size_in_mb".into(), json!(100)));
                top.push(("video_files_size_in_mb".into(), json!(200)));
            }
            Format::V21 => {
                top.push(("total_videos".into(), json!(n * s.cameras.len() as u64)));
                top.push(("total_chunks".into(), json!(n.div_ceil(CHUNKS_SIZE))));
                top.push(("chunks_size".into(), json!(CHUNKS_SIZE)));
            }
        }
        top.push(("fps".into(), json!(s.fps)));
        top.push(("splits".into(), json!({"train": format!("0:{n}")})));
        let (data_path, video_path) = match s.format {
            Format::V30 => (
                "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
                "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
            ),
            Format::V21 => (
                "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
                "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
            ),
        };
        top.push(("data_path".into(), json!(data_path)));
        top.push((
            "video_path".into(),
            if s.cameras.is_empty() {
                Value::Null
            } else {
                json!(video_path)
            },
        ));
        // Ordered objects are serialised by hand and re-parsed only to pretty-print them: the parse keeps
        // order because it goes through a string the Python reader sees in the same order.
        let features = self.features_json().to_json_string();
        let head: Vec<String> = top
            .iter()
            .map(|(k, v)| format!("{}: {}", Value::String(k.clone()), pretty_inline(v)))
            .collect();
        let text = format!(
            "{{\n    {},\n    \"features\": {}\n}}\n",
            head.join(",\n    "),
            reindent(&features)
        );
        text.into_bytes()
    }

    /// Next task index for `task`, and whether it is new.
    fn task_index(&self, task: &str) -> (i64, bool) {
        match self.tasks.iter().position(|t| t == task) {
            Some(i) => (i as i64, false),
            None => (self.tasks.len() as i64, true),
        }
    }

    pub fn total_episodes(&self) -> u64 {
        self.total_episodes
    }

    pub fn total_frames(&self) -> u64 {
        self.total_frames
    }

    pub fn spec(&self) -> &DatasetSpec {
        &self.spec
    }

    pub fn video_settings(&self) -> &VideoSettings {
        &self.video
    }

    /// Summaries of the committed episodes (from the provenance sidecar).
    pub fn episodes(&self) -> Vec<EpisodeSummary> {
        self.provenance.episodes.clone()
    }

    /// Records the sync settings in the provenance sidecar.
    pub fn set_sync_provenance(&mut self, sync: Value) {
        self.provenance.sync = sync;
    }

    /// Starts writing episode `total_episodes` into staging.
    pub fn begin_episode(&mut self, task: &str, queue_frames: usize) -> Result<EpisodeWriter, RecorderError> {
        let task = check_task(task)?;
        let staging = self.spec.root.join(STAGING_DIR);
        if staging.exists() {
            fs::remove_dir_all(&staging).map_err(|e| RecorderError::io(&staging, e))?;
        }
        fs::create_dir_all(&staging).map_err(|e| RecorderError::io(&staging, e))?;
        let data = DataWriter::create(
            &staging.join("data.parquet"),
            self.spec.state_names.len(),
            self.spec.action_names.len(),
            self.spec.format == Format::V30,
            self.spec.success,
        )?;
        let mut encoders = Vec::new();
        for c in &self.spec.cameras {
            encoders.push(EncoderThread::spawn(
                &c.name,
                staging.join(format!("{}.mp4", c.key())),
                c.width,
                c.height,
                self.spec.fps,
                self.video.clone(),
                queue_frames,
            )?);
        }
        Ok(EpisodeWriter {
            index: self.total_episodes,
            task: task.to_owned(),
            task_index: self.task_index(task).0,
            first_global_index: self.total_frames,
            data,
            encoders,
            state_stats: ColumnStats::new(StatKind::Float, self.spec.state_names.len()),
            action_stats: ColumnStats::new(StatKind::Float, self.spec.action_names.len()),
            success_stats: self.spec.success.then(|| ColumnStats::new(StatKind::Bool, 1)),
            frames: 0,
            fps: self.spec.fps,
            staging,
        })
    }

    /// Throws away an episode being recorded.
    pub fn abort_episode(&mut self, ep: EpisodeWriter) {
        let staging = ep.staging.clone();
        drop(ep);
        let _ = fs::remove_dir_all(&staging);
    }

    /// Saves an episode: closes its files and commits it (see the module doc). On error the dataset keeps
    /// its earlier episodes and the staging files are removed.
    pub fn commit_episode(
        &mut self,
        ep: EpisodeWriter,
        mut summary: EpisodeSummary,
    ) -> Result<EpisodeSummary, RecorderError> {
        let staging = ep.staging.clone();
        let r = self.commit_inner(ep, &mut summary);
        if r.is_err() {
            let _ = fs::remove_dir_all(&staging);
        }
        r.map(|()| summary)
    }

    // One linear commit sequence reads better than helpers that pass a dozen values around.
    #[allow(clippy::too_many_lines)]
    fn commit_inner(&mut self, ep: EpisodeWriter, summary: &mut EpisodeSummary) -> Result<(), RecorderError> {
        let EpisodeWriter {
            index,
            task,
            task_index,
            first_global_index,
            data,
            encoders,
            state_stats,
            action_stats,
            success_stats,
            frames,
            fps,
            staging,
        } = ep;
        if frames == 0 {
            drop(encoders);
            return Err(RecorderError::EmptyEpisode(index));
        }
        // Finish the encoders first (they run in parallel with the parquet close).
        let t0 = std::time::Instant::now();
        for e in &encoders {
            e.request_finish(frames);
        }
        let rows = data.finish()?;
        let mut reports: Vec<Result<EncodeReport, RecorderError>> = Vec::new();
        for e in encoders {
            reports.push(e.join());
        }
        let flush_ms = t0.elapsed().as_secs_f64() * 1e3;
        let reports: Vec<EncodeReport> = reports.into_iter().collect::<Result<_, _>>()?;
        for r in &reports {
            if r.frames != frames {
                return Err(RecorderError::Video {
                    camera: r.camera.clone(),
                    detail: format!("video has {} frames, episode has {frames}", r.frames),
                });
            }
            let f = fs::File::open(&r.path).map_err(|e| RecorderError::io(&r.path, e))?;
            f.sync_all().map_err(|e| RecorderError::io(&r.path, e))?;
        }
        debug_assert_eq!(rows, frames);
        summary.dropped_frames = reports.iter().map(|r| r.dropped).sum();
        summary.length_frames = frames;
        summary.index = index;
        summary.task.clone_from(&task);
        summary.duration_s = frames as f64 / f64::from(fps);

        // Per-episode stats, in info.json feature order.
        let mut stats: Vec<(String, FeatureStats)> = vec![
            ("observation.state".into(), state_stats.finish()),
            ("action".into(), action_stats.finish()),
        ];
        if let Some(s) = &success_stats {
            stats.push((SUCCESS_FEATURE.into(), s.finish()));
        }
        for (c, r) in self.spec.cameras.iter().zip(&reports) {
            stats.push((c.key(), r.image_stats.finish()));
        }
        let defaults = default_feature_columns(frames, fps, index, first_global_index, task_index);
        stats.extend(defaults.iter().map(|(k, c)| ((*k).to_owned(), c.finish())));
        let mut quantiles = self.quantiles.clone();
        let mut columns = vec![("observation.state", &state_stats), ("action", &action_stats)];
        columns.extend(success_stats.as_ref().map(|s| (SUCCESS_FEATURE, s)));
        columns.extend(defaults.iter().map(|(k, c)| (*k, c)));
        quantiles.add_episode(frames, &columns);

        let (_, new_task) = self.task_index(&task);
        let mut tasks = self.tasks.clone();
        if new_task {
            tasks.push(task.clone());
        }
        let root = self.spec.root.clone();
        let mut renames: Vec<(PathBuf, PathBuf)> = Vec::new();
        let mut new_jsonl: Option<(String, String)> = None;
        let mut agg = self.provenance.stats.clone();
        for (name, s) in &stats {
            agg.entry(name.clone()).or_default().add(s);
        }
        match self.spec.format {
            Format::V30 => {
                let dfile = self.next_data_file;
                let mfile = self.next_meta_file;
                let mut videos = Vec::new();
                for (i, (c, r)) in self.spec.cameras.iter().zip(&reports).enumerate() {
                    let vfile = self.next_video_file[i];
                    renames.push((
                        r.path.clone(),
                        file_path(&root, &format!("videos/{}", c.key()), vfile, "mp4"),
                    ));
                    videos.push((
                        c.key(),
                        vfile / CHUNKS_SIZE,
                        vfile % CHUNKS_SIZE,
                        0.0,
                        summary.duration_s,
                    ));
                }
                if new_task {
                    let p = staging.join("tasks.parquet");
                    parquet_io::write_tasks(&p, &tasks)?;
                    renames.push((p, root.join("meta/tasks.parquet")));
                }
                let meta_row = EpisodeMetaRow {
                    episode_index: index,
                    tasks: vec![task.clone()],
                    length: frames,
                    data_chunk: dfile / CHUNKS_SIZE,
                    data_file: dfile % CHUNKS_SIZE,
                    dataset_from_index: first_global_index,
                    dataset_to_index: first_global_index + frames,
                    videos,
                    stats: stats.clone(),
                    meta_chunk: mfile / CHUNKS_SIZE,
                    meta_file: mfile % CHUNKS_SIZE,
                };
                let mp = staging.join("episodes.parquet");
                parquet_io::write_episode_meta(&mp, &meta_row)?;
                renames.push((mp, file_path(&root, "meta/episodes", mfile, "parquet")));
                renames.push((
                    staging.join("data.parquet"),
                    file_path(&root, "data", dfile, "parquet"),
                ));
                let sp = staging.join("stats.json");
                write_synced(&sp, &pretty(&stats_json(&agg, &quantiles, Format::V30)))?;
                renames.push((sp, root.join("meta/stats.json")));
            }
            Format::V21 => {
                let chunk = index / CHUNKS_SIZE;
                for (c, r) in self.spec.cameras.iter().zip(&reports) {
                    renames.push((
                        r.path.clone(),
                        root.join(format!(
                            "videos/chunk-{chunk:03}/{}/episode_{index:06}.mp4",
                            c.key()
                        )),
                    ));
                }
                let mut tasks_jsonl = String::new();
                for (i, t) in tasks.iter().enumerate() {
                    tasks_jsonl.push_str(&json!({"task_index": i, "task": t}).to_string());
                    tasks_jsonl.push('\n');
                }
                let tp = staging.join("tasks.jsonl");
                write_synced(&tp, tasks_jsonl.as_bytes())?;
                renames.push((tp, root.join("meta/tasks.jsonl")));
                let mut el = self.episodes_jsonl.clone();
                el.push_str(&json!({"episode_index": index, "tasks": [task], "length": frames}).to_string());
                el.push('\n');
                let elp = staging.join("episodes.jsonl");
                write_synced(&elp, el.as_bytes())?;
                // The data file and its episodes.jsonl line must appear together: back to back, and before the
                // stats files, so that stats.json never counts an episode whose data is not on disk yet.
                renames.push((
                    staging.join("data.parquet"),
                    root.join(format!("data/chunk-{chunk:03}/episode_{index:06}.parquet")),
                ));
                renames.push((elp, root.join("meta/episodes.jsonl")));
                let ep_stats: Vec<(String, Value)> =
                    stats.iter().map(|(k, s)| (k.clone(), s.to_json_v21())).collect();
                let mut es = self.episodes_stats_jsonl.clone();
                let _ = writeln!(
                    es,
                    "{{\"episode_index\": {index}, \"stats\": {}}}",
                    Ordered(ep_stats).to_json_string()
                );
                let esp = staging.join("episodes_stats.jsonl");
                write_synced(&esp, es.as_bytes())?;
                renames.push((esp, root.join("meta/episodes_stats.jsonl")));
                let sp = staging.join("stats.json");
                write_synced(&sp, &pretty(&stats_json(&agg, &quantiles, Format::V21)))?;
                renames.push((sp, root.join("meta/stats.json")));
                let mp = staging.join("modality.json");
                write_synced(&mp, &pretty(&self.modality_json()))?;
                renames.push((mp, root.join("meta/modality.json")));
                // Kept in memory only once the save succeeds: a line left over from a failed save would be
                // written again by the next one and give its episode index twice.
                new_jsonl = Some((el, es));
            }
        }
        // Sidecar and info.json last: info.json is what makes the episode count official.
        let mut prov = self.provenance.clone();
        prov.stats = agg;
        prov.episodes.push(summary.clone());
        let qp = staging.join("quantiles.bin");
        write_synced(&qp, &quantiles.encode())?;
        renames.push((qp, root.join(QUANTILES_FILE)));
        let pp = staging.join("provenance.json");
        write_synced(&pp, &pretty(&serde_json::to_value(&prov).unwrap_or(Value::Null)))?;
        renames.push((pp, root.join(PROVENANCE_FILE)));
        let old = (self.total_episodes, self.total_frames, self.tasks.clone());
        self.total_episodes += 1;
        self.total_frames += frames;
        self.tasks = tasks;
        let ip = staging.join("info.json");
        let info = self.info_json();
        let res = write_synced(&ip, &info).and_then(|()| {
            sync_dir(&staging)?;
            renames.push((ip, root.join("meta/info.json")));
            Journal {
                episode_index: index,
                renames,
            }
            .commit(&root.join(JOURNAL_FILE))
        });
        if let Err(e) = res {
            (self.total_episodes, self.total_frames, self.tasks) = old;
            return Err(e);
        }
        tracing::debug!(
            episode = index,
            flush_ms,
            commit_ms = t0.elapsed().as_secs_f64() * 1e3 - flush_ms,
            "episode committed"
        );
        let _ = fs::remove_dir_all(&staging);
        if self.spec.format == Format::V30 {
            self.next_data_file += 1;
            self.next_meta_file += 1;
            for v in &mut self.next_video_file {
                *v += 1;
            }
        }
        if let Some((el, es)) = new_jsonl {
            self.episodes_jsonl = el;
            self.episodes_stats_jsonl = es;
        }
        self.provenance = prov;
        self.quantiles = quantiles;
        Ok(())
    }

    fn modality_json(&self) -> Value {
        let mut state = serde_json::Map::new();
        let mut action = serde_json::Map::new();
        let groups = if self.spec.modality.is_empty() {
            vec![crate::spec::ModalityGroup {
                name: "arm".into(),
                state_range: 0..self.spec.state_names.len(),
                action_range: 0..self.spec.action_names.len(),
                action_absolute: true,
            }]
        } else {
            self.spec.modality.clone()
        };
        for g in &groups {
            if !g.state_range.is_empty() {
                state.insert(
                    g.name.clone(),
                    json!({"start": g.state_range.start, "end": g.state_range.end}),
                );
            }
            if !g.action_range.is_empty() {
                action.insert(
                    g.name.clone(),
                    json!({
                        "start": g.action_range.start,
                        "end": g.action_range.end,
                        "absolute": g.action_absolute,
                    }),
                );
            }
        }
        let video: serde_json::Map<String, Value> = self
            .spec
            .cameras
            .iter()
            .map(|c| (c.name.clone(), json!({"original_key": c.key()})))
            .collect();
        json!({
            "state": state,
            "action": action,
            "video": video,
            "annotation": {"human.task_description": {"original_key": "task_index"}}
        })
    }
}

/// The dataset's `meta/stats.json`: the running aggregates, with the numeric columns' quantiles taken from
/// the dataset's sketches. v3.0: lerobot's keys for every feature; v2.1: GR00T's six keys for every parquet
/// column (lerobot 0.3 ignores the file).
fn stats_json(agg: &BTreeMap<String, Aggregate>, quantiles: &QuantileStore, format: Format) -> Value {
    let map: serde_json::Map<String, Value> = agg
        .iter()
        .filter(|(k, _)| format == Format::V30 || !k.starts_with("observation.images."))
        .filter_map(|(k, a)| {
            let mut s = a.finish()?;
            quantiles.apply(k, &mut s);
            Some((
                k.clone(),
                match format {
                    Format::V30 => s.to_json_v30(),
                    Format::V21 => s.to_json_gr00t(),
                },
            ))
        })
        .collect();
    Value::Object(map)
}

/// The default features' values over one episode, as the parquet holds them.
fn default_feature_columns(
    frames: u64,
    fps: u32,
    episode: u64,
    first_index: u64,
    task_index: i64,
) -> [(&'static str, ColumnStats); 5] {
    let mut ts = ColumnStats::new(StatKind::Float, 1);
    let mut fi = ColumnStats::new(StatKind::Int, 1);
    let mut ei = ColumnStats::new(StatKind::Int, 1);
    let mut ix = ColumnStats::new(StatKind::Int, 1);
    let mut ti = ColumnStats::new(StatKind::Int, 1);
    for i in 0..frames {
        ts.push(&[f64::from(timestamp_s(i, fps))]);
        fi.push(&[i as f64]);
        ei.push(&[episode as f64]);
        ix.push(&[(first_index + i) as f64]);
        ti.push(&[task_index as f64]);
    }
    [
        ("timestamp", ts),
        ("frame_index", fi),
        ("episode_index", ei),
        ("index", ix),
        ("task_index", ti),
    ]
}

/// `frame_index / fps` as float32, computed in f64 first so it is the nearest float32 to the exact value.
/// The task text as recorded (trimmed), or why it cannot be.
pub fn check_task(task: &str) -> Result<&str, RecorderError> {
    let task = task.trim();
    if task.is_empty() {
        return Err(RecorderError::EmptyTask);
    }
    if task.len() > MAX_TASK_BYTES {
        return Err(RecorderError::TaskTooLong {
            len: task.len(),
            max: MAX_TASK_BYTES,
        });
    }
    Ok(task)
}

pub fn timestamp_s(frame_index: u64, fps: u32) -> f32 {
    (frame_index as f64 / f64::from(fps)) as f32
}

fn pretty_inline(v: &Value) -> String {
    String::from_utf8(pretty(v))
        .unwrap_or_default()
        .replace('\n', "\n    ")
}

/// Pretty-prints a compact JSON string without reordering keys (a tiny re-indenter: strings are copied
/// verbatim, structure characters start new lines).
fn reindent(compact: &str) -> String {
    let mut out = String::new();
    let mut depth = 1usize;
    let mut in_str = false;
    let mut esc = false;
    let nl = |out: &mut String, d: usize| {
        out.push('\n');
        out.push_str(&"    ".repeat(d));
    };
    let mut chars = compact.chars().peekable();
    while let Some(c) = chars.next() {
        if in_str {
            out.push(c);
            if esc {
                esc = false;
            } else if c == '\\' {
                esc = true;
            } else if c == '"' {
                in_str = false;
            }
            continue;
        }
        match c {
            '"' => {
                in_str = true;
                out.push(c);
            }
            '{' | '[' => {
                out.push(c);
                if matches!(chars.peek(), Some('}' | ']')) {
                    continue;
                }
                depth += 1;
                nl(&mut out, depth);
            }
            '}' | ']' => {
                if !(out.ends_with('{') || out.ends_with('[')) {
                    depth -= 1;
                    nl(&mut out, depth);
                }
                out.push(c);
            }
            ',' => {
                out.push(',');
                nl(&mut out, depth);
                while matches!(chars.peek(), Some(' ')) {
                    chars.next();
                }
            }
            ' ' => {}
            ':' => out.push_str(": "),
            _ => out.push(c),
        }
    }
    out
}

impl EpisodeWriter {
    /// Appends frame `frames()` (state, executed action and task success as recorded) to the parquet and the
    /// per-episode stats. `success` is written only if the dataset records `next.success`. Camera frames are
    /// queued separately through [`EpisodeWriter::encoders`].
    pub fn push_row(&mut self, state: &[f64], action: &[f64], success: bool) -> Result<(), RecorderError> {
        let state: Vec<f32> = state.iter().map(|v| *v as f32).collect();
        let action: Vec<f32> = action.iter().map(|v| *v as f32).collect();
        self.state_stats.push_f32(&state);
        self.action_stats.push_f32(&action);
        if let Some(s) = &mut self.success_stats {
            s.push(&[f64::from(u8::from(success))]);
        }
        let i = self.frames;
        self.data.push(Row {
            state,
            action,
            success: self.success_stats.is_some().then_some(success),
            timestamp: timestamp_s(i, self.fps),
            frame_index: i as i64,
            episode_index: self.index as i64,
            index: (self.first_global_index + i) as i64,
            task_index: self.task_index,
        })?;
        self.frames += 1;
        Ok(())
    }

    /// Length of the state vector.
    pub fn state_dims(&self) -> usize {
        self.state_stats.dims()
    }

    /// Length of the action vector.
    pub fn action_dims(&self) -> usize {
        self.action_stats.dims()
    }

    /// Frames (rows) written so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Video frames dropped so far, all cameras.
    pub fn dropped(&self) -> u64 {
        self.encoders.iter().map(EncoderThread::dropped).sum()
    }

    /// The name of a camera whose encoder has failed, if any.
    pub fn failed_camera(&self) -> Option<String> {
        self.encoders
            .iter()
            .find(|e| e.failed())
            .map(|e| e.camera().to_owned())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reindent_keeps_order_and_strings() {
        let s = r#"{"b": [1, 2], "a": {"x, y": "q\"{", "e": []}}"#;
        let r = reindent(s);
        let v: Value = serde_json::from_str(&r).unwrap();
        assert_eq!(v, serde_json::from_str::<Value>(s).unwrap());
        assert!(r.find("\"b\"").unwrap() < r.find("\"a\"").unwrap());
    }

    #[test]
    #[allow(clippy::float_cmp)] // exactness is the point
    fn timestamps_are_exact_multiples() {
        assert_eq!(timestamp_s(3, 30), 0.1_f32);
        assert_eq!(timestamp_s(20, 20), 1.0);
    }
}

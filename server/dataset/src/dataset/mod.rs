//! A LeRobot dataset on disk: layout, `info.json`, metadata files, and the crash-safe episode commit.
//!
//! Durability design. Every episode is written into its *own* new files (v3.0: its own data, video and
//! episodes-metadata file, i.e. the size roll-over happens after every episode; lerobot's reader accepts any
//! split of episodes into files). Nothing already committed is ever appended to or rewritten in place, so a
//! kill can never damage a saved episode. While recording, the episode's parquet and mp4s stream into
//! `<root>/.phone2act-staging/`, which no reader looks at. Saving = closing those files, writing the new
//! metadata files into staging too, fsyncing, writing a rename journal, and renaming everything into place
//! in an order in which every intermediate state still loads in lerobot (v3.0: videos, tasks, episode
//! metadata, data, `stats.json` and GR00T's `modality.json`, then `info.json` last). v2.1 needs its data file and the `episodes.jsonl` line to appear
//! together; they are renamed back to back (a window of two syscalls) and `open` replays the journal if a
//! crash hit between them. `open` also deletes whatever an interrupted recording left in staging.
//!
//! Rooms: [`journal`] (staging and the rename journal), [`meta`] (`info.json`, `stats.json`, GR00T's
//! `modality.json`), and one [`Layout`] per format ([`v30`], [`v21`]), chosen once when the dataset opens.

mod journal;
mod merge;
mod merge_stream;
mod merge_v21;
mod meta;
mod v21;
mod v30;

pub use merge::{
    DEFAULT_DATA_FILE_SIZE_MB, DEFAULT_VIDEO_FILE_SIZE_MB, MergeError, MergeInput, MergeOptions, MergeReport,
    merge,
};

use crate::error::RecorderError;
use crate::events::{ArmActivity, EventWriter, events_path};
use crate::fsutil::write_atomic;
use crate::parquet_io::{DataWriter, INTERVENTION_FEATURE, Row, SUCCESS_FEATURE};
use crate::quantiles::{QUANTILES_FILE, QuantileStore};
use crate::spec::{DatasetSpec, Format, MAX_TASK_BYTES, VideoSettings};
use crate::stats::{Aggregate, ColumnStats, FeatureStats, ImageStats, StatKind};
use journal::Staging;
use meta::{Totals, pretty};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

/// lerobot's `chunks_size`: files (v3.0) or episodes (v2.1) per chunk directory.
pub const CHUNKS_SIZE: u64 = 1000;
/// The provenance sidecar, ignored by lerobot and GR00T.
pub const PROVENANCE_FILE: &str = "meta/phone2act_provenance.json";

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
    /// Frames recorded with a sample captured farther from the frame's time than the sample tolerance
    /// (see the recorder's `timeline`); each is a `late_tick` event in the episode's sidecar.
    pub late_ticks: u64,
    /// Video frames that did not fit in an encoder queue (replaced by a repeat of the previous frame).
    pub dropped_frames: u64,
    pub start_unix_ns: i64,
    /// The instant frame 0 stands for, on the process monotonic clock (frame i: plus i / fps, plus the
    /// paused ticks before it); 0 in provenance written before it was recorded.
    #[serde(default)]
    pub first_frame_time_ns: i64,
    pub save_latency_s: f64,
    /// Who recorded it (set at start, e.g. `phone2act episode start --operator`); empty when unknown.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub operator: String,
    /// The recording station (`[storage] station_id`, see `DatasetSpec::provenance`); empty when unknown.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub station_id: String,
    /// The phone2act version that recorded it.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub software_version: String,
    /// The policies that drove an arm during the episode (their `PolicyHello.policy_name`), by name; which
    /// arm and when is in the episode's events sidecar (`policy_start`, `policy_stop`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub policies: Vec<String>,
    /// The outcome the operator gave when stopping it (`Episodes.Stop`'s `outcome`): true for a success, false
    /// for a failure; absent when none was given. A given outcome is also the last frame's `next.success` in a
    /// dataset that records the column.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success: Option<bool>,
    /// In a merged dataset: the dataset and episode it was copied from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub merged_from: Option<MergedFrom>,
}

/// Where a merged dataset's episode came from (`phone2act dataset merge`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MergedFrom {
    /// The input as given to the merge (a path or an s3:// URL).
    pub dataset: String,
    pub episode_index: u64,
}

/// A camera's finished video of an episode, as its encoder hands it to [`Dataset::commit_episode`].
#[derive(Debug)]
pub struct EncodeReport {
    pub camera: String,
    pub path: PathBuf,
    pub frames: u64,
    /// Frames that did not fit in the queue and were replaced by a repeat of the previous frame.
    pub dropped: u64,
    pub image_stats: ImageStats,
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

/// What differs between the on-disk layouts; one implementation per [`Format`], chosen at open.
trait Layout: Send {
    /// The `info.json` keys between `total_tasks` and `fps`, in lerobot's order.
    fn info_fields(&self, total_episodes: u64, cameras: u64) -> Vec<(&'static str, Value)>;
    /// `data_path` and `video_path` of `info.json`.
    fn path_templates(&self) -> (&'static str, &'static str);
    /// Reads the layout's own state of a committed dataset; returns its tasks by index.
    fn resume(&mut self, spec: &DatasetSpec, total_episodes: u64) -> Result<Vec<String>, RecorderError>;
    /// `(episode_index, tasks joined, length)` of every episode the metadata lists, in any order.
    fn listed_episodes(&self, root: &Path) -> Result<Vec<(u64, String, u64)>, RecorderError>;
    /// One feature's entry of `meta/stats.json`, or `None` to leave the feature out.
    fn stats_entry(&self, key: &str, stats: &FeatureStats) -> Option<Value>;
    /// Writes the layout's files of a save into staging and queues their renames, in commit order.
    fn stage(&mut self, ep: &Saving<'_>, staging: &mut Staging) -> Result<(), RecorderError>;
    /// The save staged last was committed.
    fn committed(&mut self);
}

fn layout_for(spec: &DatasetSpec) -> Box<dyn Layout> {
    match spec.format {
        Format::V30 => Box::new(v30::V30::new(spec.cameras.len())),
        Format::V21 => Box::<v21::V21>::default(),
    }
}

/// An episode being saved, as the layouts need it.
struct Saving<'a> {
    spec: &'a DatasetSpec,
    index: u64,
    task: &'a str,
    frames: u64,
    duration_s: f64,
    first_global_index: u64,
    /// One per camera, in `spec.cameras` order.
    videos: &'a [EncodeReport],
    /// Every task including this episode's.
    tasks: &'a [String],
    new_task: bool,
    /// This episode's stats, in `info.json` feature order.
    stats: &'a [(String, FeatureStats)],
    /// The dataset's `meta/stats.json` after this episode.
    stats_json: &'a [u8],
}

fn corrupt(root: &Path, detail: impl Into<String>) -> RecorderError {
    RecorderError::CorruptDataset {
        root: root.to_owned(),
        detail: detail.into(),
    }
}

/// The dataset being written.
pub struct Dataset {
    spec: DatasetSpec,
    video: VideoSettings,
    layout: Box<dyn Layout>,
    tasks: Vec<String>,
    total_episodes: u64,
    total_frames: u64,
    provenance: Provenance,
    /// Dataset quantiles of the numeric columns (see [`crate::quantiles`]).
    quantiles: QuantileStore,
    /// The files the last commit made visible, in order (see [`Dataset::last_commit_files`]).
    last_commit_files: Vec<String>,
}

/// An episode's rows and events being written into staging files. Its videos are the recorder's: it encodes
/// them into [`EpisodeWriter::video_path`] and hands them over at [`Dataset::commit_episode`].
pub struct EpisodeWriter {
    pub index: u64,
    pub task: String,
    task_index: i64,
    first_global_index: u64,
    data: DataWriter,
    state_stats: ColumnStats,
    action_stats: ColumnStats,
    /// The optional bool columns the dataset records (`next.success`, `intervention`), in order.
    flag_stats: Vec<(&'static str, ColumnStats)>,
    /// The newest row's flags, counted in `flag_stats` only once the row can no longer change (the next row or
    /// the commit): an outcome given at Stop may still set its `next.success`.
    last_flags: Option<FrameFlags>,
    frames: u64,
    fps: u32,
    staging: PathBuf,
    /// Clutch and gate events, streamed into staging (see [`crate::events`]).
    events: EventWriter,
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
        journal::recover(&root)?;
        let mut ds = Dataset {
            layout: layout_for(&spec),
            spec,
            video,
            tasks: Vec::new(),
            total_episodes: 0,
            total_frames: 0,
            provenance: Provenance::default(),
            quantiles: QuantileStore::default(),
            last_commit_files: Vec::new(),
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
            if self.quantiles.current.episodes < self.total_episodes {
                // Data files removed after their upload (`retain_local = false`): the quantiles describe the
                // episodes still here; `dataset compact` of the stored copy recomputes them over all.
                tracing::warn!(
                    root = %root.display(),
                    episodes_with_data = self.quantiles.current.episodes,
                    episodes = self.total_episodes,
                    "dataset quantiles rebuilt from the episodes whose data files are on this disk"
                );
            }
            // A dataset from an older phone2act has averaged quantiles in stats.json: correct it now rather
            // than at the next save, if the running aggregates describe the same frames (each file is
            // replaced atomically, and both describe only committed episodes).
            let agg = &self.provenance.stats;
            if self.quantiles.current.frames == self.total_frames
                && agg.get("index").is_some_and(|a| a.count == self.total_frames)
            {
                let stats = meta::stats_json(agg, &self.quantiles, self.layout.as_ref());
                write_atomic(&root.join("meta/stats.json"), &pretty(&stats))?;
                write_atomic(&root.join(QUANTILES_FILE), &self.quantiles.encode())?;
            }
        }
        Ok(())
    }

    fn resume(&mut self, info_path: &Path) -> Result<(), RecorderError> {
        let root = self.spec.root.clone();
        let text = fs::read_to_string(info_path).map_err(|e| RecorderError::io(info_path, e))?;
        let info: Value =
            serde_json::from_str(&text).map_err(|e| corrupt(&root, format!("meta/info.json: {e}")))?;
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
        meta::check_features(&root, &self.spec, &self.video, &info["features"])?;
        self.total_episodes = info["total_episodes"].as_u64().unwrap_or(0);
        self.total_frames = info["total_frames"].as_u64().unwrap_or(0);
        self.tasks = self.layout.resume(&self.spec, self.total_episodes)?;
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
        let mut listed = self.layout.listed_episodes(&self.spec.root)?;
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

    /// The files (dataset-relative, `/`-separated) the last successful commit renamed into place, in the
    /// order it did: an uploader that copies them in this order never shows a reader a half episode.
    pub fn last_commit_files(&self) -> &[String] {
        &self.last_commit_files
    }

    /// Records the sync settings in the provenance sidecar.
    pub fn set_sync_provenance(&mut self, sync: Value) {
        self.provenance.sync = sync;
    }

    /// Starts writing episode `total_episodes` into staging (its videos go to [`EpisodeWriter::video_path`]).
    pub fn begin_episode(&mut self, task: &str) -> Result<EpisodeWriter, RecorderError> {
        let task = check_task(task)?;
        let staging = journal::fresh_staging(&self.spec.root)?;
        let data = DataWriter::create(
            &staging.join("data.parquet"),
            self.spec.state_names.len(),
            self.spec.action_names.len(),
            self.spec.format == Format::V30,
            self.spec.flag_columns(),
        )?;
        let events = EventWriter::create(staging.join("events.jsonl"), self.spec.fps)?;
        Ok(EpisodeWriter {
            index: self.total_episodes,
            task: task.to_owned(),
            task_index: self.task_index(task).0,
            first_global_index: self.total_frames,
            data,
            state_stats: ColumnStats::new(StatKind::Float, self.spec.state_names.len()),
            action_stats: ColumnStats::new(StatKind::Float, self.spec.action_names.len()),
            flag_stats: self
                .spec
                .flag_columns()
                .names()
                .into_iter()
                .map(|name| (name, ColumnStats::new(StatKind::Bool, 1)))
                .collect(),
            last_flags: None,
            frames: 0,
            fps: self.spec.fps,
            events,
            staging,
        })
    }

    /// Throws away an episode being recorded.
    pub fn abort_episode(&mut self, ep: EpisodeWriter) {
        let staging = ep.staging.clone();
        drop(ep);
        let _ = fs::remove_dir_all(&staging);
    }

    /// Saves an episode: closes its files and commits it (see the module doc). `videos` finishes the episode's
    /// videos (one per camera, in `spec.cameras` order, each at its [`EpisodeWriter::video_path`]); it is called
    /// after the parquet file is closed, so encoders told to finish beforehand flush while it closes, and not
    /// at all for an episode without frames. On error the dataset keeps its earlier episodes and the staging
    /// files are removed.
    pub fn commit_episode(
        &mut self,
        ep: EpisodeWriter,
        mut summary: EpisodeSummary,
        videos: impl FnOnce() -> Result<Vec<EncodeReport>, RecorderError>,
    ) -> Result<EpisodeSummary, RecorderError> {
        let staging = ep.staging.clone();
        let r = self.commit_inner(ep, &mut summary, videos);
        if r.is_err() {
            let _ = fs::remove_dir_all(&staging);
        }
        r.map(|()| summary)
    }

    /// Closes the episode's files and returns their encoder reports, checked against the row count.
    fn close_files(
        data: DataWriter,
        videos: impl FnOnce() -> Result<Vec<EncodeReport>, RecorderError>,
        frames: u64,
    ) -> Result<Vec<EncodeReport>, RecorderError> {
        let rows = data.finish()?;
        let reports = videos()?;
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
        Ok(reports)
    }

    fn commit_inner(
        &mut self,
        ep: EpisodeWriter,
        summary: &mut EpisodeSummary,
        videos: impl FnOnce() -> Result<Vec<EncodeReport>, RecorderError>,
    ) -> Result<(), RecorderError> {
        let EpisodeWriter {
            index,
            task,
            task_index,
            first_global_index,
            data,
            state_stats,
            action_stats,
            mut flag_stats,
            last_flags,
            frames,
            fps,
            staging,
            events,
        } = ep;
        if let Some(flags) = last_flags {
            count_flags(&mut flag_stats, flags);
        }
        if frames == 0 {
            return Err(RecorderError::EmptyEpisode(index));
        }
        let t0 = std::time::Instant::now();
        let reports = Self::close_files(data, videos, frames)?;
        summary.policies = events.policies();
        let events = events.finish()?;
        let flush_ms = t0.elapsed().as_secs_f64() * 1e3;
        summary.dropped_frames = reports.iter().map(|r| r.dropped).sum();
        summary.length_frames = frames;
        summary.index = index;
        summary.task.clone_from(&task);
        summary.duration_s = frames as f64 / f64::from(fps);
        self.spec.provenance["station_id"]
            .as_str()
            .unwrap_or_default()
            .clone_into(&mut summary.station_id);
        env!("CARGO_PKG_VERSION").clone_into(&mut summary.software_version);

        // Per-episode stats, in info.json feature order.
        let mut stats: Vec<(String, FeatureStats)> = vec![
            ("observation.state".into(), state_stats.finish()),
            ("action".into(), action_stats.finish()),
        ];
        stats.extend(
            flag_stats
                .iter()
                .map(|(name, s)| ((*name).to_owned(), s.finish())),
        );
        for (c, r) in self.spec.cameras.iter().zip(&reports) {
            stats.push((c.key(), r.image_stats.finish()));
        }
        let defaults = meta::default_feature_columns(frames, fps, index, first_global_index, task_index);
        stats.extend(defaults.iter().map(|(k, c)| ((*k).to_owned(), c.finish())));
        let mut quantiles = self.quantiles.clone();
        let mut columns = vec![("observation.state", &state_stats), ("action", &action_stats)];
        columns.extend(flag_stats.iter().map(|(name, s)| (*name, s)));
        columns.extend(defaults.iter().map(|(k, c)| (*k, c)));
        quantiles.add_episode(frames, &columns);

        let (_, new_task) = self.task_index(&task);
        let mut tasks = self.tasks.clone();
        if new_task {
            tasks.push(task.clone());
        }
        let mut agg = self.provenance.stats.clone();
        for (name, s) in &stats {
            agg.entry(name.clone()).or_default().add(s);
        }
        let root = self.spec.root.clone();
        let mut staged = Staging::new(staging.clone(), root.clone());
        let stats_json = pretty(&meta::stats_json(&agg, &quantiles, self.layout.as_ref()));
        self.layout.stage(
            &Saving {
                spec: &self.spec,
                index,
                task: &task,
                frames,
                duration_s: summary.duration_s,
                first_global_index,
                videos: &reports,
                tasks: &tasks,
                new_task,
                stats: &stats,
                stats_json: &stats_json,
            },
            &mut staged,
        )?;
        // Sidecars and info.json last: info.json is what makes the episode count official. The events file
        // replaces any left by a save that never reached info.json.
        staged.rename(events, staged.dest(events_path(index)));
        let mut prov = self.provenance.clone();
        prov.stats = agg;
        prov.episodes.push(summary.clone());
        staged.write("quantiles.bin", &quantiles.encode(), QUANTILES_FILE)?;
        staged.write(
            "provenance.json",
            &pretty(&serde_json::to_value(&prov).unwrap_or(Value::Null)),
            PROVENANCE_FILE,
        )?;
        let totals = Totals {
            episodes: self.total_episodes + 1,
            frames: self.total_frames + frames,
            tasks: tasks.len(),
        };
        let info = meta::info_json(&self.spec, &self.video, self.layout.as_ref(), &totals);
        self.last_commit_files = staged.commit(index, &info)?;
        tracing::debug!(
            episode = index,
            flush_ms,
            commit_ms = t0.elapsed().as_secs_f64() * 1e3 - flush_ms,
            "episode committed"
        );
        let _ = fs::remove_dir_all(&staging);
        self.total_episodes = totals.episodes;
        self.total_frames = totals.frames;
        self.tasks = tasks;
        self.layout.committed();
        self.provenance = prov;
        self.quantiles = quantiles;
        Ok(())
    }
}

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

/// How far past `k / fps` frame k's timestamp is put (see `docs/timestamps.md`): far above the rounding error
/// of any reader's float64 (or short float32) arithmetic on the frame's presentation time, and together with
/// float32's spacing (at most 61 µs below 1024 s) still inside LeRobot's 100 µs tolerance.
pub const TIMESTAMP_MARGIN_S: f64 = 20e-6;

/// Frame `frame_index`'s `timestamp`: the smallest float32 at or above `frame_index / fps +`
/// [`TIMESTAMP_MARGIN_S`], and 0 for frame 0. Never below the frame's presentation time `k / fps` (its pts), so
/// a reader that asks for "the frame shown at this time" (torchcodec's `get_frames_played_at`, a floor of
/// `t * fps`) finds frame k, where the nearest float32 (LeRobot's own rounding) lies below `k / fps` for about
/// 40 % of frames and finds frame k - 1. Readers that take the nearest frame are indifferent.
pub fn timestamp_s(frame_index: u64, fps: u32) -> f32 {
    if frame_index == 0 {
        // Every reader computes frame 0's presentation time as exactly 0: no rounding to guard against.
        return 0.0;
    }
    // The f64 quotient is off by at most half an f64 ulp, far below the margin.
    let target = frame_index as f64 / f64::from(fps) + TIMESTAMP_MARGIN_S;
    let nearest = target as f32;
    if f64::from(nearest) >= target {
        nearest
    } else {
        nearest.next_up()
    }
}

/// Why a timestamp does not pair with its frame in every reader (see [`timestamp_pairs`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TimestampMismatch {
    /// Below the frame's presentation time `k / fps` (LeRobot's own rounding does this for about 40 % of
    /// frames): LeRobot and the nearest-frame readers still find frame k, a reader of the frame played at
    /// that time (GR00T N1.5's torchcodec) finds frame k - 1.
    BeforeFrame {
        frame_index: u64,
        fps: u32,
        before_s: f64,
    },
    /// Farther after `k / fps` than LeRobot's tolerance: LeRobot refuses to decode it.
    BeyondTolerance {
        frame_index: u64,
        fps: u32,
        after_s: f64,
    },
}

impl std::fmt::Display for TimestampMismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            TimestampMismatch::BeforeFrame {
                frame_index,
                fps,
                before_s,
            } => write!(
                f,
                "lies {:.2} µs before the frame's presentation time {frame_index}/{fps} s: a reader of the frame played at that time (GR00T's torchcodec) returns frame {}",
                before_s * 1e6,
                frame_index.saturating_sub(1)
            ),
            TimestampMismatch::BeyondTolerance {
                frame_index,
                fps,
                after_s,
            } => write!(
                f,
                "lies {:.1} µs after the frame's presentation time {frame_index}/{fps} s, beyond LeRobot's {} µs tolerance",
                after_s * 1e6,
                LEROBOT_TOLERANCE_S * 1e6
            ),
        }
    }
}

/// Whether `timestamp` pairs with frame `frame_index` at `fps` in every reader: at or above the frame's
/// presentation time `k / fps` (compared exactly: a float32 times a whole fps below 2^29 is exact in f64) and
/// within LeRobot's tolerance of it, or within one float32 step where float32 is coarser than that tolerance
/// (from 1024 s on). Returns how far above `k / fps` it lies, in seconds.
pub fn timestamp_pairs(timestamp: f32, frame_index: u64, fps: u32) -> Result<f64, TimestampMismatch> {
    let scaled = f64::from(timestamp) * f64::from(fps);
    let k = frame_index as f64;
    let above_s = (scaled - k) / f64::from(fps);
    if scaled < k {
        return Err(TimestampMismatch::BeforeFrame {
            frame_index,
            fps,
            before_s: -above_s,
        });
    }
    let step_s = f64::from(timestamp.next_up() - timestamp);
    if above_s >= LEROBOT_TOLERANCE_S.max(step_s) {
        return Err(TimestampMismatch::BeyondTolerance {
            frame_index,
            fps,
            after_s: above_s,
        });
    }
    Ok(above_s)
}

/// One frame's bool values; each is recorded only in a dataset that has its column.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameFlags {
    /// `next.success`: the task is done at this frame.
    pub success: bool,
    /// `intervention`: a person drove an arm at this frame.
    pub intervention: bool,
}

/// Counts one frame's flags in the stats of the columns the dataset records.
fn count_flags(stats: &mut [(&'static str, ColumnStats)], flags: FrameFlags) {
    for (name, column) in stats {
        let value = match *name {
            SUCCESS_FEATURE => flags.success,
            INTERVENTION_FEATURE => flags.intervention,
            _ => continue,
        };
        column.push(&[f64::from(u8::from(value))]);
    }
}

/// LeRobot's default `tolerance_s` between a frame's timestamp and the decoded frame's time (0.3 to 0.6).
pub const LEROBOT_TOLERANCE_S: f64 = 1e-4;

impl EpisodeWriter {
    /// Appends frame `frames()` (state, executed action and the frame's flags as recorded) to the parquet and
    /// the per-episode stats. Each flag is written only if the dataset records its column. Camera frames go
    /// to the recorder's encoders, which write [`EpisodeWriter::video_path`].
    pub fn push_row(
        &mut self,
        state: &[f64],
        action: &[f64],
        flags: FrameFlags,
    ) -> Result<(), RecorderError> {
        let state: Vec<f32> = state.iter().map(|v| *v as f32).collect();
        let action: Vec<f32> = action.iter().map(|v| *v as f32).collect();
        self.state_stats.push_f32(&state);
        self.action_stats.push_f32(&action);
        if let Some(previous) = self.last_flags.replace(flags) {
            count_flags(&mut self.flag_stats, previous);
        }
        let row_flag =
            |name: &str, value: bool| self.flag_stats.iter().any(|(n, _)| *n == name).then_some(value);
        let success = row_flag(SUCCESS_FEATURE, flags.success);
        let intervention = row_flag(INTERVENTION_FEATURE, flags.intervention);
        let i = self.frames;
        self.data.push(Row {
            state,
            action,
            success,
            intervention,
            timestamp: timestamp_s(i, self.fps),
            frame_index: i as i64,
            episode_index: self.index as i64,
            index: (self.first_global_index + i) as i64,
            task_index: self.task_index,
        })?;
        self.frames += 1;
        Ok(())
    }

    /// Sets `next.success` of the newest frame: the operator's outcome, given when the episode stops. False
    /// when the dataset has no `next.success` column or no frame was recorded.
    pub fn set_last_success(&mut self, success: bool) -> bool {
        match &mut self.last_flags {
            Some(flags) if self.data.set_last_success(success) => {
                flags.success = success;
                true
            }
            _ => false,
        }
    }

    /// Notes the arms' clutch and gate state at the frame about to be pushed; their changes since the
    /// previous frame go to the events sidecar.
    pub fn note_activity(&mut self, arms: &[ArmActivity]) -> Result<(), RecorderError> {
        self.events.observe(arms, self.frames)
    }

    /// Writes one of the recorder's timeline events at the frame about to be pushed.
    pub fn note_timeline(
        &mut self,
        kind: crate::events::EventKind,
        count: u64,
        detail: String,
    ) -> Result<(), RecorderError> {
        self.events.note(kind, self.frames, count, detail)
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

    /// Where the episode's video of the camera whose feature key is `key` is written until it is committed.
    pub fn video_path(&self, key: &str) -> PathBuf {
        self.staging.join(format!("{key}.mp4"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exact rational comparison `t >= k / fps` for a float32 `t`, independent of `timestamp_pairs`:
    /// float32 is m * 2^e with a 24-bit m, so `t * fps >= k` is decided in 128-bit integers.
    fn at_or_after(t: f32, k: u64, fps: u32) -> bool {
        if t == 0.0 {
            return k == 0;
        }
        let bits = t.to_bits();
        let exp = i32::try_from((bits >> 23) & 0xff).unwrap();
        let mantissa = u128::from(bits & 0x7f_ffff) | if exp > 0 { 1 << 23 } else { 0 };
        let shift = exp.max(1) - 127 - 23;
        let lhs = mantissa * u128::from(fps);
        let rhs = u128::from(k);
        if shift >= 0 {
            lhs << shift >= rhs
        } else {
            lhs >= rhs << -shift
        }
    }

    #[test]
    fn every_timestamp_is_at_or_after_its_frame_and_within_lerobots_tolerance() {
        for fps in [1, 10, 15, 20, 24, 25, 30, 50, 60, 100, 120] {
            // Ten minutes of frames, then a stride to the end of the range float32 can keep within 100 µs.
            let frames =
                (0..u64::from(fps) * 600).chain((u64::from(fps) * 600..u64::from(fps) * 1023).step_by(7));
            for k in frames {
                let t = timestamp_s(k, fps);
                assert!(at_or_after(t, k, fps), "fps {fps} frame {k}: {t} < k/fps");
                let above_s = f64::from(t) - k as f64 / f64::from(fps);
                assert!(
                    above_s < LEROBOT_TOLERANCE_S,
                    "fps {fps} frame {k}: {above_s} s late"
                );
                assert!(timestamp_pairs(t, k, fps).is_ok(), "fps {fps} frame {k}");
                // A reader that floors t * fps in f64 finds frame k, and rounding finds it too.
                let scaled = f64::from(t) * f64::from(fps);
                assert_eq!(scaled.floor() as u64, k, "fps {fps} frame {k}");
                assert_eq!(scaled.round() as u64, k, "fps {fps} frame {k}");
            }
        }
    }

    #[test]
    fn a_reader_computing_pts_times_time_base_in_f64_still_finds_frame_k() {
        // The mp4 muxer's time base is fps * 2^n (at least 10000); a reader computes pts * (1 / den) in f64,
        // which can land an ulp above k / fps (3 * 0.1 > 0.3); the margin keeps the timestamp above it.
        for fps in [10, 15, 20, 30, 60] {
            let mut den = fps;
            while den < 10_000 {
                den *= 2;
            }
            let scale = den / fps;
            let tb = 1.0 / f64::from(den);
            for k in 1..u64::from(fps) * 300 {
                let frame_start_s = (k * u64::from(scale)) as f64 * tb;
                let t = f64::from(timestamp_s(k, fps));
                assert!(t >= frame_start_s, "fps {fps} frame {k}: {t} < {frame_start_s}");
                let next_start_s = ((k + 1) * u64::from(scale)) as f64 * tb;
                assert!(t < next_start_s, "fps {fps} frame {k}");
            }
        }
    }

    #[test]
    fn the_nearest_float32_is_what_the_pairing_check_refuses() {
        // LeRobot's rounding: below k / fps for a large share of frames at 20 fps, and each is caught.
        let below = (1..2000u64)
            .filter(|&k| {
                let nearest = (k as f64 / 20.0) as f32;
                let refused = timestamp_pairs(nearest, k, 20).is_err();
                assert_eq!(refused, !at_or_after(nearest, k, 20), "frame {k}");
                refused
            })
            .count();
        assert!(
            below > 500,
            "{below} of 1999 nearest float32 timestamps lie below k/fps"
        );
        assert!(timestamp_pairs(timestamp_s(7, 20), 7, 20).is_ok());
        assert!(
            timestamp_pairs(0.35 + 2e-4, 7, 20).is_err(),
            "beyond the tolerance"
        );
        assert!(timestamp_pairs(0.0, 0, 20).is_ok());
    }
}

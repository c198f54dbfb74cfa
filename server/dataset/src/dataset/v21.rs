//! LeRobot v2.1, the layout GR00T's own loader reads (`meta/modality.json` comes from [`super::meta`]): one
//! data file and one video per camera for each episode, and JSON-lines metadata (`tasks.jsonl`,
//! `episodes.jsonl`, `episodes_stats.jsonl`) that every save rewrites whole into staging and renames over the
//! old file.

use super::journal::Staging;
use super::meta::stage_modality;
use super::{CHUNKS_SIZE, Layout, Saving, corrupt};
use crate::error::RecorderError;
use crate::spec::DatasetSpec;
use crate::stats::FeatureStats;
use indexmap::IndexMap;
use serde::Serialize;
use serde_json::{Value, json};
use std::fs;
use std::path::Path;

/// The committed `episodes.jsonl` and `episodes_stats.jsonl`, and those of a save not yet committed.
#[derive(Default)]
pub(super) struct V21 {
    episodes_jsonl: String,
    episodes_stats_jsonl: String,
    /// Taken over only once the save succeeds: a line left over from a failed save would be written again
    /// by the next one and give its episode index twice.
    pending: Option<(String, String)>,
}

/// One line of `episodes_stats.jsonl`, the features in `info.json` order.
#[derive(Serialize)]
struct EpisodeStatsLine {
    episode_index: u64,
    stats: IndexMap<String, Value>,
}

fn non_empty_lines(text: &str) -> impl Iterator<Item = &str> {
    text.lines().filter(|l| !l.trim().is_empty())
}

impl Layout for V21 {
    fn info_fields(&self, total_episodes: u64, cameras: u64) -> Vec<(&'static str, Value)> {
        let n = total_episodes;
        vec![
            ("total_videos", json!(n * cameras)),
            ("total_chunks", json!(n.div_ceil(CHUNKS_SIZE))),
            ("chunks_size", json!(CHUNKS_SIZE)),
        ]
    }

    fn path_templates(&self) -> (&'static str, &'static str) {
        (
            "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
        )
    }

    fn resume(&mut self, spec: &DatasetSpec, total_episodes: u64) -> Result<Vec<String>, RecorderError> {
        let root = &spec.root;
        let read = |p: &str| fs::read_to_string(root.join(p)).unwrap_or_default();
        let mut tasks: Vec<(u64, String)> = Vec::new();
        for line in non_empty_lines(&read("meta/tasks.jsonl")) {
            let v: Value =
                serde_json::from_str(line).map_err(|e| corrupt(root, format!("meta/tasks.jsonl: {e}")))?;
            tasks.push((
                v["task_index"].as_u64().unwrap_or(0),
                v["task"].as_str().unwrap_or("").to_owned(),
            ));
        }
        tasks.sort();
        self.episodes_jsonl = read("meta/episodes.jsonl");
        self.episodes_stats_jsonl = read("meta/episodes_stats.jsonl");
        let lines = non_empty_lines(&self.episodes_jsonl).count() as u64;
        if lines != total_episodes {
            return Err(corrupt(
                root,
                format!("meta/info.json says {total_episodes} episodes, meta/episodes.jsonl has {lines}"),
            ));
        }
        Ok(tasks.into_iter().map(|t| t.1).collect())
    }

    fn listed_episodes(&self, root: &Path) -> Result<Vec<(u64, String, u64)>, RecorderError> {
        let mut listed = Vec::new();
        for line in non_empty_lines(&self.episodes_jsonl) {
            let v: Value =
                serde_json::from_str(line).map_err(|e| corrupt(root, format!("meta/episodes.jsonl: {e}")))?;
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
        Ok(listed)
    }

    /// GR00T's six keys for every parquet column (lerobot 0.3 ignores the file).
    fn stats_entry(&self, key: &str, stats: &FeatureStats) -> Option<Value> {
        (!key.starts_with("observation.images.")).then(|| stats.to_json_gr00t())
    }

    fn stage(&mut self, ep: &Saving<'_>, staging: &mut Staging) -> Result<(), RecorderError> {
        let index = ep.index;
        let chunk = index / CHUNKS_SIZE;
        for (c, r) in ep.spec.cameras.iter().zip(ep.videos) {
            let to = staging.dest(format!(
                "videos/chunk-{chunk:03}/{}/episode_{index:06}.mp4",
                c.key()
            ));
            staging.rename(r.path.clone(), to);
        }
        let mut tasks_jsonl = String::new();
        for (i, t) in ep.tasks.iter().enumerate() {
            tasks_jsonl.push_str(&json!({"task_index": i, "task": t}).to_string());
            tasks_jsonl.push('\n');
        }
        staging.write("tasks.jsonl", tasks_jsonl.as_bytes(), "meta/tasks.jsonl")?;
        let mut el = self.episodes_jsonl.clone();
        el.push_str(&json!({"episode_index": index, "tasks": [ep.task], "length": ep.frames}).to_string());
        el.push('\n');
        let elp = staging.path("episodes.jsonl");
        crate::fsutil::write_synced(&elp, el.as_bytes())?;
        // The data file and its episodes.jsonl line must appear together: back to back, and before the
        // stats files, so that stats.json never counts an episode whose data is not on disk yet.
        staging.rename(
            staging.path("data.parquet"),
            staging.dest(format!("data/chunk-{chunk:03}/episode_{index:06}.parquet")),
        );
        staging.rename(elp, staging.dest("meta/episodes.jsonl"));
        let line = EpisodeStatsLine {
            episode_index: index,
            stats: ep
                .stats
                .iter()
                .map(|(k, s)| (k.clone(), s.to_json_v21()))
                .collect(),
        };
        let mut es = self.episodes_stats_jsonl.clone();
        es.push_str(&serde_json::to_string(&line).expect("JSON values always serialise"));
        es.push('\n');
        staging.write("episodes_stats.jsonl", es.as_bytes(), "meta/episodes_stats.jsonl")?;
        staging.write("stats.json", ep.stats_json, "meta/stats.json")?;
        stage_modality(ep.spec, staging)?;
        self.pending = Some((el, es));
        Ok(())
    }

    fn committed(&mut self) {
        if let Some((el, es)) = self.pending.take() {
            self.episodes_jsonl = el;
            self.episodes_stats_jsonl = es;
        }
    }
}

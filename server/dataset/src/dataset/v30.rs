//! LeRobot v3.0: episodes in chunked files, `meta/tasks.parquet` and `meta/episodes/` parquet metadata. Every
//! episode gets its own data, video and metadata file (the roll-over happens after every episode), so a
//! save never touches a committed file.

use super::journal::Staging;
use super::{CHUNKS_SIZE, Layout, Saving};
use crate::error::RecorderError;
use crate::parquet_io::{self, EpisodeMetaRow};
use crate::spec::DatasetSpec;
use crate::stats::FeatureStats;
use serde_json::{Value, json};
use std::fs;
use std::path::{Path, PathBuf};

/// The next free file number of each kind (`chunk * CHUNKS_SIZE + file`).
pub(super) struct V30 {
    data: u64,
    meta: u64,
    /// One per camera.
    videos: Vec<u64>,
}

impl V30 {
    pub(super) fn new(cameras: usize) -> Self {
        V30 {
            data: 0,
            meta: 0,
            videos: vec![0; cameras],
        }
    }
}

fn file_path(top: &str, n: u64, ext: &str) -> PathBuf {
    PathBuf::from(format!(
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

/// Every `meta/episodes/chunk-*/file-*.parquet`, sorted.
fn episode_meta_files(root: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for chunk in fs::read_dir(root.join("meta/episodes"))
        .into_iter()
        .flatten()
        .flatten()
    {
        for f in fs::read_dir(chunk.path()).into_iter().flatten().flatten() {
            if f.path().extension().is_some_and(|e| e == "parquet") {
                files.push(f.path());
            }
        }
    }
    files.sort();
    files
}

/// The largest `chunk*1000+file` each file family (`data`, `videos/<key>`) reaches in the episode
/// metadata's `<family>/chunk_index` and `<family>/file_index` columns.
fn named_file_indices(root: &Path) -> Result<std::collections::HashMap<String, u64>, RecorderError> {
    let mut most = std::collections::HashMap::new();
    for f in episode_meta_files(root) {
        for batch in parquet_io::read_batches(&f)? {
            let schema = batch.schema();
            for field in schema.fields() {
                let Some(family) = field.name().strip_suffix("/file_index") else {
                    continue;
                };
                if family.starts_with("meta/") {
                    continue;
                }
                let (Some(chunks), Some(idx)) = (
                    parquet_io::int_column(&batch, &format!("{family}/chunk_index")),
                    parquet_io::int_column(&batch, field.name()),
                ) else {
                    continue;
                };
                for (c, i) in chunks.into_iter().zip(idx) {
                    if let (Ok(c), Ok(i)) = (u64::try_from(c), u64::try_from(i)) {
                        let n = c * CHUNKS_SIZE + i;
                        most.entry(family.to_owned())
                            .and_modify(|m: &mut u64| *m = (*m).max(n))
                            .or_insert(n);
                    }
                }
            }
        }
    }
    Ok(most)
}

impl Layout for V30 {
    fn info_fields(&self, _total_episodes: u64, _cameras: u64) -> Vec<(&'static str, Value)> {
        vec![
            ("chunks_size", json!(CHUNKS_SIZE)),
            ("data_files_size_in_mb", json!(100)),
            ("video_files_size_in_mb", json!(200)),
        ]
    }

    fn path_templates(&self) -> (&'static str, &'static str) {
        (
            "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        )
    }

    fn resume(&mut self, spec: &DatasetSpec, _total_episodes: u64) -> Result<Vec<String>, RecorderError> {
        let root = &spec.root;
        // The episode metadata names every data and video file, including ones no longer on this disk (a
        // station that removes uploaded episodes' files, `retain_local = false`): a new episode must never
        // take the index of a file that exists in the dataset's storage.
        let named = named_file_indices(root)?;
        let after = |col: &str| named.get(col).map_or(0, |n| n + 1);
        self.data = next_file_index(&root.join("data"), "parquet").max(after("data"));
        self.meta = next_file_index(&root.join("meta/episodes"), "parquet");
        for (i, c) in spec.cameras.iter().enumerate() {
            self.videos[i] = next_file_index(&root.join("videos").join(c.key()), "mp4")
                .max(after(&format!("videos/{}", c.key())));
        }
        let tp = root.join("meta/tasks.parquet");
        if tp.exists() {
            parquet_io::read_tasks(&tp)
        } else {
            Ok(Vec::new())
        }
    }

    fn listed_episodes(&self, root: &Path) -> Result<Vec<(u64, String, u64)>, RecorderError> {
        let mut listed = Vec::new();
        for f in episode_meta_files(root) {
            for e in parquet_io::read_episode_summaries(&f)? {
                listed.push((e.episode_index, e.tasks.join("; "), e.length));
            }
        }
        Ok(listed)
    }

    fn stats_entry(&self, _key: &str, stats: &FeatureStats) -> Option<Value> {
        Some(stats.to_json_v30())
    }

    fn stage(&mut self, ep: &Saving<'_>, staging: &mut Staging) -> Result<(), RecorderError> {
        let dfile = self.data;
        let mfile = self.meta;
        let mut videos = Vec::new();
        for (i, (c, r)) in ep.spec.cameras.iter().zip(ep.videos).enumerate() {
            let vfile = self.videos[i];
            let to = staging.dest(file_path(&format!("videos/{}", c.key()), vfile, "mp4"));
            staging.rename(r.path.clone(), to);
            videos.push((
                c.key(),
                vfile / CHUNKS_SIZE,
                vfile % CHUNKS_SIZE,
                0.0,
                ep.duration_s,
            ));
        }
        if ep.new_task {
            let p = staging.path("tasks.parquet");
            parquet_io::write_tasks(&p, ep.tasks)?;
            staging.rename(p, staging.dest("meta/tasks.parquet"));
        }
        let meta_row = EpisodeMetaRow {
            episode_index: ep.index,
            tasks: vec![ep.task.to_owned()],
            length: ep.frames,
            data_chunk: dfile / CHUNKS_SIZE,
            data_file: dfile % CHUNKS_SIZE,
            dataset_from_index: ep.first_global_index,
            dataset_to_index: ep.first_global_index + ep.frames,
            videos,
            stats: ep.stats.to_vec(),
            meta_chunk: mfile / CHUNKS_SIZE,
            meta_file: mfile % CHUNKS_SIZE,
        };
        let mp = staging.path("episodes.parquet");
        parquet_io::write_episode_meta(&mp, &meta_row)?;
        staging.rename(mp, staging.dest(file_path("meta/episodes", mfile, "parquet")));
        staging.rename(
            staging.path("data.parquet"),
            staging.dest(file_path("data", dfile, "parquet")),
        );
        staging.write("stats.json", ep.stats_json, "meta/stats.json")?;
        // GR00T's body-part layout, so that one v3.0 dataset also serves LeRobot's GR00T training and
        // GR00T's own loader; lerobot ignores the file.
        super::meta::stage_modality(ep.spec, staging)
    }

    fn committed(&mut self) {
        self.data += 1;
        self.meta += 1;
        for v in &mut self.videos {
            *v += 1;
        }
    }
}

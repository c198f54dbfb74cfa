//! Crash safety: the staging directory an episode is written into, and the rename journal that moves a
//! saved episode into place (see the [module doc](super)).

use crate::error::RecorderError;
use crate::fsutil::{Journal, sync_dir, write_synced};
use std::fs;
use std::path::{Path, PathBuf};

const STAGING_DIR: &str = ".phone2act-staging";
const JOURNAL_FILE: &str = ".phone2act-commit.json";

/// At open: finishes a save a crash interrupted and deletes what an interrupted recording left in staging.
pub(super) fn recover(root: &Path) -> Result<(), RecorderError> {
    if let Some(ep) = Journal::recover(&root.join(JOURNAL_FILE))? {
        tracing::warn!(episode = ep, root = %root.display(), "finished a save interrupted by a crash");
    }
    let staging = root.join(STAGING_DIR);
    if staging.exists() {
        tracing::warn!(root = %root.display(), "removing the files of an episode interrupted while recording");
        fs::remove_dir_all(&staging).map_err(|e| RecorderError::io(&staging, e))?;
    }
    Ok(())
}

/// An empty staging directory for a new episode (whatever an earlier one left there is removed).
pub(super) fn fresh_staging(root: &Path) -> Result<PathBuf, RecorderError> {
    let staging = root.join(STAGING_DIR);
    if staging.exists() {
        fs::remove_dir_all(&staging).map_err(|e| RecorderError::io(&staging, e))?;
    }
    fs::create_dir_all(&staging).map_err(|e| RecorderError::io(&staging, e))?;
    Ok(staging)
}

/// The files of one save, written into staging, and the renames that put them in place, in commit order.
pub(super) struct Staging {
    dir: PathBuf,
    root: PathBuf,
    renames: Vec<(PathBuf, PathBuf)>,
}

impl Staging {
    pub(super) fn new(dir: PathBuf, root: PathBuf) -> Self {
        Staging {
            dir,
            root,
            renames: Vec::new(),
        }
    }

    /// `name` inside the staging directory.
    pub(super) fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    /// `rel` inside the dataset.
    pub(super) fn dest(&self, rel: impl AsRef<Path>) -> PathBuf {
        self.root.join(rel)
    }

    /// Queues the move of an already written, already synced file to `to`.
    pub(super) fn rename(&mut self, from: PathBuf, to: PathBuf) {
        self.renames.push((from, to));
    }

    /// Writes `bytes` to staging file `name` (synced) and queues its move to `rel` inside the dataset.
    pub(super) fn write(
        &mut self,
        name: &str,
        bytes: &[u8],
        rel: impl AsRef<Path>,
    ) -> Result<(), RecorderError> {
        let from = self.path(name);
        write_synced(&from, bytes)?;
        let to = self.dest(rel);
        self.rename(from, to);
        Ok(())
    }

    /// Writes `info.json` last (it is what makes the episode count official), then journals and performs
    /// every rename. Returns the committed files, dataset-relative, in the order they became visible (what
    /// an uploader must follow: see [`super::Dataset::last_commit_files`]).
    pub(super) fn commit(
        mut self,
        episode_index: u64,
        info_json: &[u8],
    ) -> Result<Vec<String>, RecorderError> {
        self.write("info.json", info_json, "meta/info.json")?;
        sync_dir(&self.dir)?;
        let files = self
            .renames
            .iter()
            .filter_map(|(_, to)| to.strip_prefix(&self.root).ok())
            .map(|p| p.to_string_lossy().replace('\\', "/"))
            .collect();
        Journal {
            episode_index,
            renames: self.renames,
        }
        .commit(&self.root.join(JOURNAL_FILE))?;
        Ok(files)
    }
}

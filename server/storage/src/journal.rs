//! The upload journal: `<dataset>/.phone2act-upload/journal.json`, replaced atomically after every change,
//! so a `kill -9` at any moment leaves either the previous or the next state. It lists the batches still to
//! upload (one per committed episode, or one catch-up batch for episodes committed while storage was off)
//! and how many episodes are fully remote. Each batch's files are hard links taken at commit time in
//! `.phone2act-upload/b<id>/`, so the bytes uploaded are the ones that commit made visible, whatever the
//! recorder has replaced since.

use crate::StorageError;
use serde::{Deserialize, Serialize};
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The upload directory inside the dataset root (hidden: no LeRobot reader looks at it).
pub const UPLOAD_DIR: &str = ".phone2act-upload";
const JOURNAL_FILE: &str = "journal.json";
/// The dataset files removed after their upload (`retain_local = false`), a JSON array of dataset-relative
/// paths. Written before the files go, so every removal is on record.
const REMOVED_FILE: &str = "removed-locally.json";

/// The dataset files `retain_local = false` removed from `root` after their upload, oldest first (empty for
/// a dataset that keeps everything). Such a dataset is complete only in its storage.
pub fn removed_locally(root: &Path) -> Result<Vec<String>, StorageError> {
    let path = root.join(UPLOAD_DIR).join(REMOVED_FILE);
    match fs::read(&path) {
        Ok(b) => {
            serde_json::from_slice(&b).map_err(|e| StorageError::Corrupt(format!("{}: {e}", path.display())))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(StorageError::io(path, e)),
    }
}

/// Adds `rels` to the record of [`removed_locally`] (atomically; call before removing them).
pub(crate) fn note_removed(root: &Path, rels: &[String]) -> Result<(), StorageError> {
    let mut all = removed_locally(root)?;
    all.extend(rels.iter().cloned());
    let bytes = serde_json::to_vec(&all).map_err(|e| StorageError::Corrupt(e.to_string()))?;
    write_atomic(&root.join(UPLOAD_DIR).join(REMOVED_FILE), &bytes)
}

/// One file of a batch.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct BatchFile {
    /// Dataset-relative path, `/`-separated: the object's key under the remote root.
    pub rel: String,
    /// Name of the hard link inside the batch directory.
    pub link: String,
    pub size_bytes: u64,
    /// Filled in by the uploader (hashing is not the recorder's job).
    #[serde(default)]
    pub sha256: Option<String>,
    /// Remote and checked; a hint only: after an error the batch is re-checked from its first file.
    #[serde(default)]
    pub done: bool,
}

/// The files of one commit (or catch-up), in the order they must become visible.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Batch {
    pub id: u64,
    /// The episodes this batch makes remote: `first..end`.
    pub first_episode: u64,
    pub end_episode: u64,
    pub files: Vec<BatchFile>,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct UploadJournal {
    /// Episodes `0..episodes_uploaded` are remote and complete.
    pub episodes_uploaded: u64,
    pub next_batch_id: u64,
    pub batches: Vec<Batch>,
}

/// Replaces `path` atomically: temp file beside it, fsync, rename, fsync the directory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StorageError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir).map_err(|e| StorageError::io(dir, e))?;
    let tmp = dir.join(format!(
        ".{}.tmp",
        path.file_name().and_then(|n| n.to_str()).unwrap_or("file")
    ));
    let mut f = File::create(&tmp).map_err(|e| StorageError::io(&tmp, e))?;
    f.write_all(bytes)
        .and_then(|()| f.sync_all())
        .map_err(|e| StorageError::io(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| StorageError::io(path, e))?;
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| StorageError::io(dir, e))
}

impl UploadJournal {
    pub fn dir(root: &Path) -> PathBuf {
        root.join(UPLOAD_DIR)
    }

    /// The journal of the dataset at `root` (empty if there is none yet). An unreadable journal cannot
    /// come from a torn write (it is replaced atomically); it is reported rather than silently reset.
    pub fn load(root: &Path) -> Result<Self, StorageError> {
        let path = Self::dir(root).join(JOURNAL_FILE);
        match fs::read(&path) {
            Ok(bytes) => serde_json::from_slice(&bytes)
                .map_err(|e| StorageError::Corrupt(format!("{}: {e}", path.display()))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Self::default()),
            Err(e) => Err(StorageError::io(path, e)),
        }
    }

    pub fn save(&self, root: &Path) -> Result<(), StorageError> {
        let bytes =
            serde_json::to_vec(self).map_err(|e| StorageError::Corrupt(format!("upload journal: {e}")))?;
        write_atomic(&Self::dir(root).join(JOURNAL_FILE), &bytes)
    }

    /// Episodes `0..covered()` are remote or in a batch.
    pub fn covered(&self) -> u64 {
        self.batches
            .iter()
            .map(|b| b.end_episode)
            .max()
            .unwrap_or(0)
            .max(self.episodes_uploaded)
    }

    /// Hard-links `rels` (dataset-relative, in visibility order) into a new batch directory and appends
    /// the batch. The caller saves the journal. A file that cannot be linked (a filesystem without hard
    /// links) is copied.
    pub fn snapshot(
        &mut self,
        root: &Path,
        rels: &[String],
        first_episode: u64,
        end_episode: u64,
    ) -> Result<&Batch, StorageError> {
        let id = self.next_batch_id;
        let dir = Self::dir(root).join(format!("b{id}"));
        if dir.exists() {
            fs::remove_dir_all(&dir).map_err(|e| StorageError::io(&dir, e))?;
        }
        fs::create_dir_all(&dir).map_err(|e| StorageError::io(&dir, e))?;
        let mut files = Vec::with_capacity(rels.len());
        for (i, rel) in rels.iter().enumerate() {
            let src = root.join(rel);
            let link = format!("b{id}/f{i:04}");
            let dst = Self::dir(root).join(&link);
            if fs::hard_link(&src, &dst).is_err() {
                fs::copy(&src, &dst).map_err(|e| StorageError::io(&src, e))?;
            }
            let size_bytes = fs::metadata(&dst).map_err(|e| StorageError::io(&dst, e))?.len();
            files.push(BatchFile {
                rel: rel.clone(),
                link,
                size_bytes,
                sha256: None,
                done: false,
            });
        }
        // The links must be durable before the journal names them.
        File::open(&dir)
            .and_then(|d| d.sync_all())
            .map_err(|e| StorageError::io(&dir, e))?;
        self.next_batch_id += 1;
        self.batches.push(Batch {
            id,
            first_episode,
            end_episode,
            files,
        });
        Ok(self.batches.last().expect("just pushed"))
    }

    /// Removes batch directories no batch names (links made by a snapshot whose journal write a crash
    /// interrupted).
    pub fn remove_orphans(&self, root: &Path) {
        let Ok(entries) = fs::read_dir(Self::dir(root)) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let Some(id) = name.strip_prefix('b').and_then(|s| s.parse::<u64>().ok()) else {
                continue;
            };
            if !self.batches.iter().any(|b| b.id == id) {
                let _ = fs::remove_dir_all(e.path());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_snapshot_keeps_the_committed_bytes_after_the_file_is_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        fs::create_dir_all(root.join("meta")).unwrap();
        fs::write(root.join("meta/info.json"), "one").unwrap();
        let mut j = UploadJournal::default();
        let b = j
            .snapshot(root, &["meta/info.json".to_owned()], 0, 1)
            .unwrap()
            .clone();
        j.save(root).unwrap();
        // The recorder replaces files by rename: the link still holds the old inode.
        fs::write(root.join("meta/.info.tmp"), "two!").unwrap();
        fs::rename(root.join("meta/.info.tmp"), root.join("meta/info.json")).unwrap();
        let linked = UploadJournal::dir(root).join(&b.files[0].link);
        assert_eq!(fs::read_to_string(linked).unwrap(), "one");
        assert_eq!(b.files[0].size_bytes, 3);
        let back = UploadJournal::load(root).unwrap();
        assert_eq!(back, j);
        assert_eq!(back.covered(), 1);
        fs::create_dir_all(UploadJournal::dir(root).join("b7")).unwrap();
        back.remove_orphans(root);
        assert!(!UploadJournal::dir(root).join("b7").exists());
        assert!(UploadJournal::dir(root).join("b0").exists());
    }
}

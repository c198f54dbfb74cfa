//! Durable file operations: write-to-temp + fsync + rename, directory fsync, and the commit journal that
//! makes a multi-file commit restartable after a crash.

use crate::error::RecorderError;
use serde::{Deserialize, Serialize};
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

/// fsyncs a directory so that renames and creations inside it survive power loss.
pub fn sync_dir(dir: &Path) -> Result<(), RecorderError> {
    File::open(dir)
        .and_then(|f| f.sync_all())
        .map_err(|e| RecorderError::io(dir, e))
}

/// Writes `bytes` to `path` and fsyncs it (no rename: callers stage files and rename them in a commit).
pub fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), RecorderError> {
    let mut f = File::create(path).map_err(|e| RecorderError::io(path, e))?;
    f.write_all(bytes)
        .and_then(|()| f.sync_all())
        .map_err(|e| RecorderError::io(path, e))
}

/// Replaces `path` atomically: temp file beside it, fsync, rename, fsync the directory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RecorderError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir).map_err(|e| RecorderError::io(dir, e))?;
    let tmp = dir.join(format!(
        ".{}.tmp",
        path.file_name().and_then(|n| n.to_str()).unwrap_or("file")
    ));
    write_synced(&tmp, bytes)?;
    fs::rename(&tmp, path).map_err(|e| RecorderError::io(path, e))?;
    sync_dir(dir)
}

/// An ordered list of renames that together commit one episode. Written (atomically) before the first
/// rename; replayed by [`Journal::recover`] if the process died part way; removed when done.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct Journal {
    pub episode_index: u64,
    pub renames: Vec<(PathBuf, PathBuf)>,
}

impl Journal {
    /// Writes the journal, then performs every rename in order, fsyncing touched directories, then
    /// removes the journal.
    pub fn commit(&self, journal_path: &Path) -> Result<(), RecorderError> {
        let bytes = serde_json::to_vec(self)
            .map_err(|e| RecorderError::io(journal_path, std::io::Error::other(e)))?;
        write_atomic(journal_path, &bytes)?;
        self.apply()?;
        fs::remove_file(journal_path).map_err(|e| RecorderError::io(journal_path, e))?;
        sync_dir(journal_path.parent().unwrap_or(Path::new(".")))
    }

    /// Performs the renames whose source still exists (idempotent, so replaying is safe).
    pub fn apply(&self) -> Result<(), RecorderError> {
        let mut dirs: Vec<PathBuf> = Vec::new();
        for (src, dst) in &self.renames {
            if !src.exists() {
                continue;
            }
            if let Some(parent) = dst.parent() {
                if !parent.exists() {
                    fs::create_dir_all(parent).map_err(|e| RecorderError::io(parent, e))?;
                    if let Some(pp) = parent.parent() {
                        dirs.push(pp.to_owned());
                    }
                }
                if !dirs.iter().any(|d| d == parent) {
                    dirs.push(parent.to_owned());
                }
            }
            fs::rename(src, dst).map_err(|e| RecorderError::io(dst, e))?;
        }
        for d in dirs {
            sync_dir(&d)?;
        }
        Ok(())
    }

    /// Finishes an interrupted commit if a complete journal is present. Returns the episode it committed.
    pub fn recover(journal_path: &Path) -> Result<Option<u64>, RecorderError> {
        let Ok(bytes) = fs::read(journal_path) else {
            return Ok(None);
        };
        let Ok(journal) = serde_json::from_slice::<Journal>(&bytes) else {
            // Written atomically, so an unreadable journal was never complete: nothing was renamed yet.
            fs::remove_file(journal_path).map_err(|e| RecorderError::io(journal_path, e))?;
            return Ok(None);
        };
        journal.apply()?;
        fs::remove_file(journal_path).map_err(|e| RecorderError::io(journal_path, e))?;
        Ok(Some(journal.episode_index))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_interrupted_journal_is_replayed() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        fs::write(&a, "A").unwrap();
        fs::write(&b, "B").unwrap();
        let j = Journal {
            episode_index: 4,
            renames: vec![
                (a.clone(), dir.path().join("x/a")),
                (b.clone(), dir.path().join("y/b")),
            ],
        };
        let jp = dir.path().join("commit.json");
        write_atomic(&jp, &serde_json::to_vec(&j).unwrap()).unwrap();
        // Simulate a crash after the first rename.
        fs::create_dir_all(dir.path().join("x")).unwrap();
        fs::rename(&a, dir.path().join("x/a")).unwrap();
        assert_eq!(Journal::recover(&jp).unwrap(), Some(4));
        assert_eq!(fs::read_to_string(dir.path().join("y/b")).unwrap(), "B");
        assert_eq!(fs::read_to_string(dir.path().join("x/a")).unwrap(), "A");
        assert!(!jp.exists());
        assert_eq!(Journal::recover(&jp).unwrap(), None);
    }
}

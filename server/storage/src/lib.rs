//! S3-compatible object storage for phone2act datasets: the per-episode background upload (an
//! [`Uploader`] fed by the recorder's commit hook), and the one-shot [`push`] and [`pull`].
//!
//! Consistency design. S3 has no multi-object transaction, so the remote copy is kept readable the same way
//! the local commit keeps the disk readable: objects are written one at a time, each complete before the
//! next starts (a PUT or a completed multipart upload is atomic), in the order the local commit renames
//! them into place: videos, tasks, episode metadata, data, the stats files, the sidecars, and `info.json`
//! (which makes the episode count official) last. A file the recorder later replaces (`info.json`,
//! `stats.json`, ...) is uploaded from a hard link taken when its episode committed, so a slow upload never
//! sends metadata that counts an episode whose data is not remote yet. Every object carries its sha256 as
//! `x-amz-meta-sha256`; an object already remote with the same size and sha256 is never sent again, which is
//! what makes a resumed upload (after `kill -9`, a storage outage or a restart) cheap and idempotent.
//!
//! Rooms: [`config`] (the `[storage]` table, the URL, credentials), [`remote`] (object_store wrapper),
//! [`order`] (which file goes first), [`journal`] (the upload journal beside the dataset), [`uploader`]
//! (the background thread), [`sync`] (push and pull).

pub mod config;
pub mod journal;
pub mod order;
pub mod remote;
pub mod sync;
pub mod uploader;

pub use config::{Credentials, StorageConfig, StorageUrl};
pub use journal::removed_locally;
pub use remote::Remote;
pub use sync::{PushReport, pull, push};
pub use uploader::{EpisodeUpload, UploadStatus, Uploader};

use std::path::PathBuf;

/// Why a storage operation failed. Messages never contain a secret (credentials are not part of any of
/// these, and object_store's errors carry the URL and S3's message, not the signing key).
#[derive(Debug, thiserror::Error)]
pub enum StorageError {
    #[error("storage config: {0}")]
    Config(String),
    #[error("{url}: {detail}")]
    Remote { url: String, detail: String },
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{0}")]
    Corrupt(String),
    #[error("refusing to push {local} to {url}: {detail} (nothing was written)")]
    Mismatch {
        local: PathBuf,
        url: String,
        detail: String,
    },
    #[error("cannot start the uploader: {0}")]
    Start(String),
}

impl StorageError {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        StorageError::Io {
            path: path.into(),
            source,
        }
    }
}

/// Lowercase hex of `bytes`.
pub(crate) fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    bytes
        .iter()
        .fold(String::with_capacity(bytes.len() * 2), |mut s, b| {
            let _ = write!(s, "{b:02x}");
            s
        })
}

/// Streams `path` through sha256 (1 MiB at a time, so a video never sits in memory whole).
pub fn sha256_file(path: &std::path::Path) -> Result<(u64, String), StorageError> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| StorageError::io(path, e))?;
    let mut ctx = ring::digest::Context::new(&ring::digest::SHA256);
    let mut buf = vec![0u8; 1 << 20];
    let mut size_bytes = 0u64;
    loop {
        let n = f.read(&mut buf).map_err(|e| StorageError::io(path, e))?;
        if n == 0 {
            break;
        }
        size_bytes += n as u64;
        ctx.update(&buf[..n]);
    }
    Ok((size_bytes, hex(ctx.finish().as_ref())))
}

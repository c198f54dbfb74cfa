//! The recorder's errors. Messages are written for the operator who reads them in a status line or a
//! gRPC error, so they name the dataset, the episode and what to do.

use std::path::PathBuf;

/// Everything the recorder can refuse or fail at.
#[derive(Debug, thiserror::Error)]
pub enum RecorderError {
    #[error("invalid dataset configuration: {0}")]
    InvalidSpec(String),
    #[error("dataset at {root} was recorded at {found} fps, config says {wanted}")]
    FpsMismatch { root: PathBuf, found: u32, wanted: u32 },
    #[error("dataset at {root} is LeRobot {found}, config says {wanted}")]
    FormatMismatch {
        root: PathBuf,
        found: String,
        wanted: String,
    },
    #[error("dataset at {root} has different features than the config: {detail}")]
    FeatureMismatch { root: PathBuf, detail: String },
    #[error("dataset at {root} is not readable: {detail}")]
    CorruptDataset { root: PathBuf, detail: String },
    #[error("an episode is already being recorded (episode {0}); stop or discard it first")]
    AlreadyRecording(u64),
    #[error("no episode is being recorded")]
    NotRecording,
    #[error("episode {0} has no frames: nothing to save (it was discarded)")]
    EmptyEpisode(u64),
    #[error("the task text is {len} bytes, the limit is {max} bytes")]
    TaskTooLong { len: usize, max: usize },
    #[error("the task text is empty")]
    EmptyTask,
    #[error(
        "no episode is being recorded, so there is nothing to re-record (saved episodes are never deleted by a re-record; use Start)"
    )]
    NothingToRerecord,
    #[error(
        "saving the last seconds is off: set [recorder] highlight_s to the seconds the recorder keeps while idle"
    )]
    HighlightOff,
    #[error(
        "an episode is being recorded (episode {0}): it already holds these seconds; stop it to save it, or discard it"
    )]
    HighlightWhileRecording(u64),
    #[error(
        "nothing buffered yet: the recorder keeps the last seconds only once every source has sent a sample"
    )]
    NothingBuffered,
    #[error("video encoder for camera {camera}: {detail}")]
    Video { camera: String, detail: String },
    #[error(
        "disk full while writing {path}: the episode was not saved, the dataset keeps its earlier episodes"
    )]
    DiskFull { path: PathBuf },
    #[error("I/O error on {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("parquet error on {path}: {detail}")]
    Parquet { path: PathBuf, detail: String },
    #[error("camera {0}: {1}")]
    Camera(String, String),
    #[error("the recorder thread stopped unexpectedly")]
    ThreadGone,
}

impl RecorderError {
    /// Wraps an I/O error with the path it happened on, recognising a full disk.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        let path = path.into();
        if is_disk_full(&source) {
            RecorderError::DiskFull { path }
        } else {
            RecorderError::Io { path, source }
        }
    }

    /// Wraps a parquet error with the path it happened on, recognising a full disk.
    pub fn parquet(path: impl Into<PathBuf>, err: &parquet::errors::ParquetError) -> Self {
        let path = path.into();
        let detail = err.to_string();
        if detail.contains("No space left") {
            RecorderError::DiskFull { path }
        } else {
            RecorderError::Parquet { path, detail }
        }
    }
}

/// ENOSPC or EDQUOT, by kind or by raw errno (older std maps quota errors to `Other`).
pub fn is_disk_full(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded
    ) || matches!(e.raw_os_error(), Some(28 | 122))
}

//! phone2act datasets on disk: the LeRobot v3.0 and v2.1 formats (both with GR00T's modality.json), their
//! metadata, parquet and statistics, the crash-safe episode commit (see [`dataset`]), and the reading side the
//! CLI and tests use: reading episodes back ([`readback`]), checking a dataset ([`verify`]), decoding its videos
//! ([`av::decode`]) and merging datasets without re-encoding ([`dataset::merge`]).
//!
//! Nothing here captures or encodes: the recorder (`phone2act-recorder`) writes episodes through
//! [`Dataset`] and hands it finished video files, so this crate builds without the writer or the cameras.
//! FFmpeg is reached only through [`av`].

pub mod av;
pub mod dataset;
pub mod error;
pub mod events;
pub mod frame;
pub mod fsutil;
pub mod parquet_io;
pub mod quantiles;
pub mod readback;
pub mod spec;
pub mod stats;
pub mod verify;

pub use dataset::{Dataset, EpisodeSummary};
pub use error::RecorderError;
pub use frame::Frame;
pub use spec::{CameraSpec, DatasetSpec, Format, ModalityGroup, VideoSettings};

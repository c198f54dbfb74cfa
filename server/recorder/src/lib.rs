//! The phone2act recorder: a fixed-rate sync gate over robot state and cameras, streaming video encoders
//! (one thread per camera), and LeRobot dataset writers (v3.0 and v2.1, both with GR00T's modality.json). Threads,
//! not tokio; crash-safe by construction (see [`dataset`] for the commit design).

pub mod avcapture;
pub mod camera;
pub mod dataset;
pub mod decode;
pub mod error;
pub mod events;
pub mod fsutil;
pub mod jpeg;
pub mod live;
pub mod memory;
pub mod parquet_io;
pub mod priority;
pub mod quantiles;
pub mod readback;
pub mod recorder;
pub mod spec;
pub mod stats;
pub mod synthetic;
pub mod timeline;
pub mod verify;
pub mod video;

pub use dataset::{Dataset, EpisodeSummary};
pub use error::RecorderError;
pub use recorder::{Highlight, Phase, Recorder, RecorderStatus, RobotSample, RobotSource, SyncConfig};
pub use spec::{CameraSpec, DatasetSpec, Format, ModalityGroup, VideoSettings};

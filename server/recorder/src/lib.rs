//! The phone2act recorder, the writing side: a fixed-rate sync gate over robot state and cameras
//! ([`recorder`]), streaming video encoders, one thread per camera ([`av`], the crate's one FFmpeg module), and
//! the episode that ties them to the dataset being written ([`episode`]). Threads, not tokio. The dataset format,
//! its crash-safe commit and the reading side are `phone2act-dataset`'s; the cameras are `phone2act-capture`'s.

pub mod av;
pub mod episode;
pub mod memory;
pub mod recorder;
pub mod synthetic;

pub use recorder::{Highlight, Phase, Recorder, RecorderStatus, RobotSample, RobotSource, SyncConfig};

//! The phone2act recorder: a fixed-rate sync gate over robot state and cameras, streaming video encoders
//! (one thread per camera), and LeRobot dataset writers (v3.0, and v2.1 with GR00T's modality.json). Threads,
//! not tokio; crash-safe by construction.

pub mod camera;
pub mod clock;

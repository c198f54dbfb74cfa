//! The picture type every part shares: cameras produce it, encoders and image statistics take it, the decoder
//! gives it back.

use std::sync::Arc;

/// One RGB8 frame.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Packed RGB, row-major, `width * height * 3` bytes.
    pub rgb: Arc<Vec<u8>>,
    /// Capture time on the process monotonic clock.
    pub capture_time_ns: i64,
    /// Sequence number at the source, +1 per captured frame.
    pub seq: u64,
}

//! FFmpeg, for the reading side: the one module of this crate that reaches `ffmpeg-next`
//! (`tests/scripts/check-deps.py` keeps it so). Decoding frames back ([`decode`]), what a video file
//! says about itself (`probe`, for `dataset verify`), and stream-copying episodes between files (`remux`,
//! for `dataset merge`). The process-wide FFmpeg set-up the other crates' FFmpeg modules share lives here too.

pub mod decode;
pub(crate) mod probe;
pub(crate) mod remux;

use std::sync::Once;

/// Serialises opening and closing FFmpeg codecs and devices across threads. Encoder libraries set up
/// process-wide tables when an instance is created (SVT-AV1 1.4 among them) and are not safe to initialise
/// from several threads at once; a heap corruption was seen with three cameras starting together. Opening
/// takes milliseconds, once per episode and camera, so the lock costs nothing measurable.
pub static CODEC_LOCK: parking_lot::Mutex<()> = parking_lot::Mutex::new(());

/// Initialises FFmpeg once per process and keeps its log to errors. (SVT-AV1 logs on its own; see
/// `phone2act_recorder::av::quiet_encoder_library_logs`.)
pub fn init_ffmpeg() {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        let _ = ffmpeg_next::init();
        ffmpeg_next::util::log::set_level(ffmpeg_next::util::log::Level::Error);
    });
}

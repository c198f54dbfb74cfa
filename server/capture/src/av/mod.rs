//! FFmpeg, for the capture side: the one module of this crate that reaches `ffmpeg-next`
//! (`tests/scripts/check-deps.py` keeps it so). Cameras read through libavdevice ([`device`]) and the
//! operator's live H.264 video ([`live`]).

pub mod device;
pub mod live;

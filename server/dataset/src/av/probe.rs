//! What a video file says about itself without decoding it: its duration and its frames' presentation times
//! (`phone2act dataset verify`).

use std::path::Path;

/// Duration of the first video stream in seconds, and its frame count when the container knows it.
pub(crate) fn video_duration_s(path: &Path) -> Result<(f64, i64), String> {
    super::init_ffmpeg();
    let input =
        ffmpeg_next::format::input(path).map_err(|e| format!("{} cannot be opened: {e}", path.display()))?;
    let stream = input
        .streams()
        .best(ffmpeg_next::media::Type::Video)
        .ok_or_else(|| format!("{} has no video stream", path.display()))?;
    let tb = stream.time_base();
    let duration_s = stream.duration() as f64 * f64::from(tb.numerator()) / f64::from(tb.denominator());
    Ok((duration_s, stream.frames()))
}

/// A video's frame presentation times: `(pts in presentation order, time base numerator, denominator)`.
pub(crate) type FrameTimes = (Vec<i64>, i64, i64);

/// Presentation times of the first video stream's frames, in presentation order, as exact fractions of a
/// second. Reads packets only (no decoding).
pub(crate) fn video_frame_times(path: &Path) -> Result<FrameTimes, String> {
    super::init_ffmpeg();
    let mut input =
        ffmpeg_next::format::input(path).map_err(|e| format!("{} cannot be opened: {e}", path.display()))?;
    let (index, tb) = {
        let stream = input
            .streams()
            .best(ffmpeg_next::media::Type::Video)
            .ok_or_else(|| format!("{} has no video stream", path.display()))?;
        (stream.index(), stream.time_base())
    };
    let mut pts: Vec<i64> = input
        .packets()
        .filter(|(s, _)| s.index() == index)
        .filter_map(|(_, p)| p.pts())
        .collect();
    pts.sort_unstable();
    Ok((pts, i64::from(tb.numerator()), i64::from(tb.denominator())))
}

//! Appending whole mp4 files into one, stream copy only (no decode, no re-encode): what a merge or a compact
//! does with videos. Each appended file's packets are shifted to start where the previous file ended, so an
//! episode at `from_timestamp` t in its source file sits at `offset + t` in the output.

use crate::error::RecorderError;
use ffmpeg_next as ffmpeg;
use ffmpeg_next::Rational;
use ffmpeg_next::Rescale as _;
use std::path::{Path, PathBuf};

fn video_error(path: &Path, detail: impl std::fmt::Display) -> RecorderError {
    RecorderError::Video {
        camera: path.display().to_string(),
        detail: detail.to_string(),
    }
}

/// What the output's stream must share with every appended file: the decoder sees one stream.
#[derive(Clone, Debug, PartialEq)]
struct StreamShape {
    codec: ffmpeg::codec::Id,
    width: u32,
    height: u32,
    format: ffmpeg::format::Pixel,
}

fn shape_of(path: &Path, stream: &ffmpeg::format::stream::Stream<'_>) -> Result<StreamShape, RecorderError> {
    let ctx = ffmpeg::codec::context::Context::from_parameters(stream.parameters())
        .map_err(|e| video_error(path, format!("cannot read the codec parameters: {e}")))?;
    let codec = ctx.id();
    let video = ctx
        .decoder()
        .video()
        .map_err(|e| video_error(path, format!("not a video stream: {e}")))?;
    Ok(StreamShape {
        codec,
        width: video.width(),
        height: video.height(),
        format: video.format(),
    })
}

/// An mp4 being assembled from whole files.
pub(crate) struct Concat {
    path: PathBuf,
    output: ffmpeg::format::context::Output,
    shape: StreamShape,
    fps: u32,
    /// The output stream's time base (the muxer's choice, known after the header).
    time_base: Rational,
    /// Where the next appended file starts, in `time_base` units.
    end_ts: i64,
}

impl Concat {
    /// Creates `path` with the stream parameters of `first` (which is not appended yet).
    pub(crate) fn create(path: &Path, first: &Path, fps: u32) -> Result<Self, RecorderError> {
        crate::av::init_ffmpeg();
        let input =
            ffmpeg::format::input(first).map_err(|e| video_error(first, format!("cannot open: {e}")))?;
        let stream = input
            .streams()
            .best(ffmpeg::media::Type::Video)
            .ok_or_else(|| video_error(first, "no video stream"))?;
        let shape = shape_of(first, &stream)?;
        let mut output =
            ffmpeg::format::output(path).map_err(|e| video_error(path, format!("cannot create: {e}")))?;
        {
            let mut out_stream = output
                .add_stream(ffmpeg::encoder::find(ffmpeg::codec::Id::None))
                .map_err(|e| video_error(path, format!("cannot add a stream: {e}")))?;
            out_stream.set_parameters(stream.parameters());
            out_stream.set_time_base(stream.time_base());
            out_stream.set_avg_frame_rate(stream.avg_frame_rate());
            out_stream.set_rate(stream.rate());
        }
        // The index at the front, as lerobot writes its concatenated files: a reader starts without seeking to
        // the end first.
        let mut opts = ffmpeg::Dictionary::new();
        opts.set("movflags", "faststart");
        output
            .write_header_with(opts)
            .map_err(|e| video_error(path, format!("cannot write the header: {e}")))?;
        let time_base = output.stream(0).map_or(stream.time_base(), |s| s.time_base());
        Ok(Concat {
            path: path.to_owned(),
            output,
            shape,
            fps,
            time_base,
            end_ts: 0,
        })
    }

    /// Where the next appended file will start, in seconds.
    pub(crate) fn end_s(&self) -> f64 {
        self.end_ts as f64 * f64::from(self.time_base)
    }

    /// Appends every packet of `src`'s video stream; returns the offset (s) at which it starts. A file whose
    /// codec, size or pixel format differs from the output's is refused (one stream cannot change them).
    pub(crate) fn append(&mut self, src: &Path) -> Result<f64, RecorderError> {
        let mut input =
            ffmpeg::format::input(src).map_err(|e| video_error(src, format!("cannot open: {e}")))?;
        let (index, in_tb, start_ts, shape) = {
            let stream = input
                .streams()
                .best(ffmpeg::media::Type::Video)
                .ok_or_else(|| video_error(src, "no video stream"))?;
            let start = stream.start_time();
            // AV_NOPTS_VALUE (i64::MIN) when the container does not say.
            let start = if start == i64::MIN { 0 } else { start };
            (stream.index(), stream.time_base(), start, shape_of(src, &stream)?)
        };
        if shape != self.shape {
            return Err(video_error(
                src,
                format!(
                    "cannot be appended to {} without re-encoding: {:?} {}x{} {:?}, the file holds {:?} {}x{} {:?}",
                    self.path.display(),
                    shape.codec,
                    shape.width,
                    shape.height,
                    shape.format,
                    self.shape.codec,
                    self.shape.width,
                    self.shape.height,
                    self.shape.format
                ),
            ));
        }
        let offset_ts = self.end_ts;
        let offset_s = self.end_s();
        // One frame in the output's units, for a packet that carries no duration.
        let frame_ts = 1i64.rescale(
            Rational::new(1, i32::try_from(self.fps.max(1)).unwrap_or(i32::MAX)),
            self.time_base,
        );
        let start_out = start_ts.rescale(in_tb, self.time_base);
        let mut end = offset_ts;
        for (stream, mut packet) in input.packets() {
            if stream.index() != index {
                continue;
            }
            packet.rescale_ts(in_tb, self.time_base);
            let shift = offset_ts - start_out;
            let pts = packet.pts().map(|p| p + shift);
            packet.set_pts(pts);
            packet.set_dts(packet.dts().map(|d| d + shift));
            packet.set_stream(0);
            packet.set_position(-1);
            let duration = if packet.duration() > 0 {
                packet.duration()
            } else {
                frame_ts
            };
            if let Some(p) = pts {
                end = end.max(p + duration);
            }
            packet.write_interleaved(&mut self.output).map_err(|e| {
                video_error(&self.path, format!("writing a packet of {}: {e}", src.display()))
            })?;
        }
        // Every file holds whole frames at the dataset's constant rate (lerobot's and phone2act's writers
        // both); a muxer's rounding of the last packet's duration (a tick either way) must not push every
        // later episode off its frame grid, so the end snaps to the nearest whole frame.
        let frame_tb = Rational::new(1, i32::try_from(self.fps.max(1)).unwrap_or(i32::MAX));
        let frames =
            ((end - offset_ts) as f64 * f64::from(self.time_base) * f64::from(self.fps)).round() as i64;
        self.end_ts = offset_ts + frames.rescale(frame_tb, self.time_base);
        Ok(offset_s)
    }

    /// Writes the trailer (and, with faststart, moves the index to the front).
    pub(crate) fn finish(mut self) -> Result<(), RecorderError> {
        self.output
            .write_trailer()
            .map_err(|e| video_error(&self.path, format!("cannot finish: {e}")))
    }
}

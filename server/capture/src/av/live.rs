//! H.264 for the operator's live video (the gateway's WebRTC view): packed RGB frames in, Annex-B access units
//! out, through the same FFmpeg as the recorder's encoders (libx264). Tuned for latency, not size: no B-frames, no lookahead
//! (`tune=zerolatency`), one slice per frame, SPS/PPS repeated before every keyframe so that a viewer who joins
//! late decodes from the next keyframe, and constrained baseline, which every browser's decoder (and hardware
//! decoders) take.

use ffmpeg_next::software::scaling;
use ffmpeg_next::util::format::Pixel;
use ffmpeg_next::util::frame::video::Video as VideoFrame;
use ffmpeg_next::util::picture;
use ffmpeg_next::{Dictionary, Packet, Rational, codec, encoder};
use std::sync::Once;

/// Why the encoder could not be made or used.
#[derive(Debug, thiserror::Error)]
#[error("H.264 encoder: {0}")]
pub struct EncodeError(pub String);

fn ff(what: &str, e: ffmpeg_next::Error) -> EncodeError {
    EncodeError(format!("{what}: {e}"))
}

/// One encoder for one camera at one size.
pub struct H264Encoder {
    encoder: encoder::Video,
    scaler: scaling::Context,
    rgb: VideoFrame,
    /// The camera's size (rounded down to even) and the size sent (the scaler converts between them).
    width: u32,
    height: u32,
    out_width: u32,
    out_height: u32,
    frames: i64,
    packet: Packet,
    bitrate_bps: usize,
}

/// A VBV buffer of two frames at `bitrate_bps`.
fn vbv_buffer_bits(bitrate_bps: usize, fps: u32) -> usize {
    bitrate_bps / fps.max(1) as usize * 2
}

impl std::fmt::Debug for H264Encoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("H264Encoder")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("out_width", &self.out_width)
            .field("out_height", &self.out_height)
            .field("frames", &self.frames)
            .finish_non_exhaustive()
    }
}

impl H264Encoder {
    /// An encoder for `width`x`height` RGB frames at about `fps`, aiming at `bitrate_bps`.
    pub fn new(width: u32, height: u32, fps: u32, bitrate_bps: usize) -> Result<Self, EncodeError> {
        Self::scaled(width, height, (width, height), fps, bitrate_bps)
    }

    /// An encoder for `width`x`height` RGB frames that sends them at `out` (width, height; scaled in the
    /// colour conversion, no extra pass), at about `fps`, aiming at `bitrate_bps`.
    pub fn scaled(
        width: u32,
        height: u32,
        out: (u32, u32),
        fps: u32,
        bitrate_bps: usize,
    ) -> Result<Self, EncodeError> {
        static INIT: Once = Once::new();
        INIT.call_once(|| {
            let _ = ffmpeg_next::init();
        });
        let codec_impl = encoder::find_by_name("libx264").ok_or_else(|| {
            EncodeError("FFmpeg has no libx264 encoder (install an FFmpeg built with it)".into())
        })?;
        let mut enc = codec::context::Context::new_with_codec(codec_impl)
            .encoder()
            .video()
            .map_err(|e| ff("video encoder", e))?;
        // Even sizes: 4:2:0 chroma halves both.
        let (width, height) = (width & !1, height & !1);
        let (out_width, out_height) = ((out.0 & !1).max(2), (out.1 & !1).max(2));
        enc.set_width(out_width);
        enc.set_height(out_height);
        enc.set_format(Pixel::YUV420P);
        enc.set_time_base(Rational::new(1, fps.max(1) as i32));
        enc.set_frame_rate(Some(Rational::new(fps.max(1) as i32, 1)));
        // A keyframe a second: a viewer that lost packets recovers within a second even without asking.
        enc.set_gop(fps.max(1));
        enc.set_max_b_frames(0);
        enc.set_bit_rate(bitrate_bps);
        let mut opts = Dictionary::new();
        opts.set("preset", "ultrafast");
        opts.set("tune", "zerolatency");
        opts.set("profile", "baseline");
        // One thread: the encode shares a small machine with the control path, and x264's default (1.5 threads
        // a core, sliced) wakes a burst of threads for every frame; ultrafast 640x480 takes a few ms on one.
        opts.set("threads", "1");
        // The rate control's buffer of about two frames keeps a burst from queueing on the link. Set on the
        // codec context (`maxrate`, `bufsize`), not in `x264-params`: FFmpeg's libx264 wrapper re-applies the
        // context's values before each frame, which would clear VBV limits given only to x264.
        opts.set("maxrate", &bitrate_bps.to_string());
        opts.set("bufsize", &vbv_buffer_bits(bitrate_bps, fps).to_string());
        opts.set("x264-params", "repeat-headers=1");
        let encoder = enc.open_with(opts).map_err(|e| ff("cannot open libx264", e))?;
        let scaler = scaling::Context::get(
            Pixel::RGB24,
            width,
            height,
            Pixel::YUV420P,
            out_width,
            out_height,
            scaling::Flags::FAST_BILINEAR,
        )
        .map_err(|e| ff("colour conversion", e))?;
        Ok(Self {
            encoder,
            scaler,
            rgb: VideoFrame::new(Pixel::RGB24, width, height),
            width,
            height,
            out_width,
            out_height,
            frames: 0,
            packet: Packet::empty(),
            bitrate_bps,
        })
    }

    /// The bitrate the encoder aims at.
    pub fn bitrate_bps(&self) -> usize {
        self.bitrate_bps
    }

    /// Aims at `bitrate_bps` from the next frame on (x264 reconfigures its rate control in place: no keyframe).
    /// The VBV buffer keeps the size it was opened with, so at a lower rate a frame may burst over more
    /// frame periods; the sender's pacer spreads it.
    pub fn set_bitrate_bps(&mut self, bitrate_bps: usize) {
        self.encoder.set_bit_rate(bitrate_bps);
        self.encoder.set_max_bit_rate(bitrate_bps);
        self.bitrate_bps = bitrate_bps;
    }

    /// The size this encoder takes (the camera's, rounded down to even).
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The size it sends.
    pub fn output_size(&self) -> (u32, u32) {
        (self.out_width, self.out_height)
    }

    /// Encodes one packed RGB frame of the camera's size (`src_width` pixels a row, at least this encoder's
    /// size); returns the access unit (Annex B) and whether it is a keyframe. `keyframe` forces one.
    pub fn encode(
        &mut self,
        rgb: &[u8],
        src_width: u32,
        keyframe: bool,
    ) -> Result<Option<(Vec<u8>, bool)>, EncodeError> {
        let src_row = src_width as usize * 3;
        let row = self.width as usize * 3;
        if src_width < self.width || rgb.len() < src_row * self.height as usize {
            return Err(EncodeError(format!(
                "frame of {} bytes, {src_width} px a row, is smaller than {}x{}",
                rgb.len(),
                self.width,
                self.height
            )));
        }
        let stride = self.rgb.stride(0);
        let data = self.rgb.data_mut(0);
        for (y, src) in rgb.chunks_exact(src_row).take(self.height as usize).enumerate() {
            data[y * stride..y * stride + row].copy_from_slice(&src[..row]);
        }
        // A fresh output frame each time: the encoder may still hold a reference to the previous one.
        let mut yuv = VideoFrame::new(Pixel::YUV420P, self.out_width, self.out_height);
        self.scaler
            .run(&self.rgb, &mut yuv)
            .map_err(|e| ff("colour conversion", e))?;
        yuv.set_pts(Some(self.frames));
        if keyframe {
            yuv.set_kind(picture::Type::I);
        }
        self.frames += 1;
        self.encoder.send_frame(&yuv).map_err(|e| ff("encode", e))?;
        // zerolatency: one frame in, its packet out at once.
        let mut out: Option<(Vec<u8>, bool)> = None;
        while self.encoder.receive_packet(&mut self.packet).is_ok() {
            let bytes = self.packet.data().unwrap_or_default();
            let key = self.packet.is_key();
            match &mut out {
                Some((buf, k)) => {
                    buf.extend_from_slice(bytes);
                    *k |= key;
                }
                None => out = Some((bytes.to_vec(), key)),
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_come_out_as_annex_b_with_parameter_sets_on_keyframes() {
        let mut enc = H264Encoder::new(64, 48, 30, 300_000).unwrap();
        let mut keys = Vec::new();
        for i in 0..40u8 {
            let rgb: Vec<u8> = (0..64 * 48 * 3).map(|j| (j as u8).wrapping_add(i * 3)).collect();
            let (au, key) = enc
                .encode(&rgb, 64, i == 5)
                .unwrap()
                .expect("zerolatency gives one packet per frame");
            assert!(
                au.starts_with(&[0, 0, 0, 1]) || au.starts_with(&[0, 0, 1]),
                "not Annex B"
            );
            // NAL type 7 (SPS) leads every keyframe so a late viewer can start there.
            let has_sps = au.windows(4).any(|w| w[..3] == [0, 0, 1] && w[3] & 0x1f == 7);
            assert_eq!(has_sps, key, "frame {i}: keyframe {key}, SPS {has_sps}");
            if key {
                keys.push(i);
            }
        }
        // The first frame, the forced one, and one a GOP (30 frames) later.
        assert_eq!(keys, vec![0, 5, 35]);
    }

    #[test]
    fn a_scaled_encoder_sends_the_smaller_picture() {
        let mut enc = H264Encoder::scaled(640, 480, (320, 240), 30, 500_000).unwrap();
        assert_eq!((enc.size(), enc.output_size()), ((640, 480), (320, 240)));
        let rgb = vec![128u8; 640 * 480 * 3];
        let (au, key) = enc.encode(&rgb, 640, true).unwrap().unwrap();
        assert!(key);
        // FFmpeg's own decoder reads the picture's size from the stream.
        let mut decoder = codec::context::Context::new_with_codec(
            ffmpeg_next::decoder::find(codec::Id::H264).expect("an H.264 decoder"),
        )
        .decoder()
        .video()
        .unwrap();
        decoder.send_packet(&Packet::copy(&au)).unwrap();
        decoder.send_eof().unwrap();
        let mut frame = VideoFrame::empty();
        decoder.receive_frame(&mut frame).unwrap();
        assert_eq!((frame.width(), frame.height()), (320, 240));
    }

    #[test]
    fn a_lower_bitrate_takes_effect_without_a_keyframe() {
        // Noise does not compress: each frame's size follows the rate control's budget.
        let (w, h) = (320u32, 240u32);
        let mut state = 0x2545_f491_u32;
        let mut noise = || -> Vec<u8> {
            (0..w * h * 3)
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 17;
                    state ^= state << 5;
                    state as u8
                })
                .collect()
        };
        let mut enc = H264Encoder::new(w, h, 30, 2_000_000).unwrap();
        let mut sizes = Vec::new();
        let mut keys = Vec::new();
        for i in 0..90 {
            if i == 30 {
                enc.set_bitrate_bps(200_000);
            }
            let (au, key) = enc.encode(&noise(), w, false).unwrap().unwrap();
            sizes.push(au.len());
            if key {
                keys.push(i);
            }
        }
        assert_eq!(enc.bitrate_bps(), 200_000);
        assert_eq!(
            keys,
            vec![0, 30, 60],
            "a keyframe a second (GOP of 30), none for the change"
        );
        let mean = |r: std::ops::Range<usize>| {
            let p: Vec<usize> = r.filter(|i| i % 30 != 0).map(|i| sizes[i]).collect();
            p.iter().sum::<usize>() as f64 / p.len() as f64
        };
        let (before, after) = (mean(5..30), mean(65..90));
        // 2 Mbit/s at 30 fps is about 8.3 kB a frame, 200 kbit/s about 0.8 kB.
        assert!(
            after * 4.0 < before && after < 2_000.0,
            "P-frames of {before:.0} B at 2 Mbit/s and {after:.0} B at 200 kbit/s"
        );
    }
}

//! What a dataset holds: the format, rate, feature names, cameras and video settings the caller asks for.
//! Validated once at open so that nothing later has to second-guess it.

use crate::error::RecorderError;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::PathBuf;

/// The on-disk LeRobot layout (spelled as its `codebase_version` in configuration files).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Format {
    /// LeRobot v3.0 (lerobot >= 0.4): episodes share chunked files; `meta/modality.json` rides along for GR00T.
    #[serde(rename = "v3.0")]
    V30,
    /// LeRobot v2.1 (lerobot 0.3.x, GR00T's own loader): one file per episode, plus `meta/modality.json`.
    #[serde(rename = "v2.1")]
    V21,
}

impl Format {
    /// The `codebase_version` string of `meta/info.json`.
    pub fn codebase_version(self) -> &'static str {
        match self {
            Format::V30 => "v3.0",
            Format::V21 => "v2.1",
        }
    }

    /// The FFmpeg encoder used when the configuration names none.
    pub fn default_encoder(self) -> &'static str {
        match self {
            Format::V30 => "libsvtav1",
            // GR00T N1.5's default decord backend cannot decode AV1.
            Format::V21 => "libx264",
        }
    }
}

/// One camera of the dataset; frames of other sizes are scaled to this size.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraSpec {
    /// Short name; the feature is `observation.images.<name>`.
    pub name: String,
    pub width: u32,
    pub height: u32,
}

impl CameraSpec {
    /// The LeRobot feature key of this camera.
    pub fn key(&self) -> String {
        format!("observation.images.{}", self.name)
    }
}

/// One GR00T modality group: a slice of the state and of the action vector (half-open ranges).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModalityGroup {
    pub name: String,
    pub state_range: Range<usize>,
    pub action_range: Range<usize>,
    /// Whether the action slice is an absolute target (true) or relative to the observed state (false).
    /// GR00T pads past an episode's end with the last value of an absolute group and with zero for a
    /// relative one, so a delta group marked absolute would keep moving after the episode ends.
    #[serde(default = "absolute_default")]
    pub action_absolute: bool,
}

fn absolute_default() -> bool {
    true
}

/// Everything needed to create or resume a dataset.
#[derive(Clone, Debug)]
pub struct DatasetSpec {
    pub root: PathBuf,
    pub format: Format,
    pub fps: u32,
    pub robot_type: String,
    /// `None` = the format's default (AV1 for v3.0, H.264 for v2.1). Accepts `av1`, `libsvtav1`, `h264`,
    /// `libx264`, `hevc`, `libx265`, optionally followed by `:key=value,key=value` encoder options
    /// (`preset`, `crf`, `g`, and anything else is passed to the encoder).
    pub video_codec: Option<String>,
    pub state_names: Vec<String>,
    pub action_names: Vec<String>,
    pub cameras: Vec<CameraSpec>,
    pub modality: Vec<ModalityGroup>,
    /// Record `next.success` (bool per frame: the task, e.g. the sim's ball in its basket, is done at that
    /// frame), as LeRobot's simulation datasets do.
    pub success: bool,
    /// Record `intervention` (bool per frame: a person drove at least one arm at that frame, a policy or
    /// nobody drove the others), as LeRobot's human-in-the-loop (DAgger) recording does. Which arm a person
    /// drove, and which policy drove when, is in the episode's events sidecar (`clutch_*`, `policy_*`).
    pub intervention: bool,
    /// Free-form configuration copied into the provenance sidecar.
    pub provenance: serde_json::Value,
}

/// SVT-AV1 parameters of the default AV1 settings (see `VideoSettings::parse`).
pub const SVT_LOW_DELAY_PARAMS: &str = "pred-struct=1:irefresh-type=2";

/// Resolved video encoder settings.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct VideoSettings {
    /// FFmpeg encoder name (`libsvtav1`, `libx264`, `libx265`).
    pub encoder: String,
    /// Codec name as PyAV reports it, written to `info.json` (`av1`, `h264`, `hevc`).
    pub codec: String,
    pub gop: u32,
    pub crf: u32,
    pub preset: Option<String>,
    /// Further encoder options, passed through.
    pub extra: Vec<(String, String)>,
}

impl VideoSettings {
    /// LeRobot's defaults for `codec` (g=2, crf=30, yuv420p; SVT-AV1 preset 12).
    pub fn parse(spec: Option<&str>, format: Format) -> Result<Self, RecorderError> {
        let spec = spec
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .unwrap_or(format.default_encoder());
        let (name, opts) = spec.split_once(':').unwrap_or((spec, ""));
        let (encoder, codec) = match name.to_ascii_lowercase().as_str() {
            "av1" | "libsvtav1" | "svtav1" => ("libsvtav1", "av1"),
            "h264" | "libx264" | "x264" => ("libx264", "h264"),
            "hevc" | "h265" | "libx265" | "x265" => ("libx265", "hevc"),
            other => {
                return Err(RecorderError::InvalidSpec(format!(
                    "unknown video codec {other:?} (use av1, h264 or hevc)"
                )));
            }
        };
        let mut settings = VideoSettings {
            encoder: encoder.to_owned(),
            codec: codec.to_owned(),
            gop: 2,
            crf: 30,
            // lerobot's preset for SVT-AV1; for x264 `veryfast` instead of its `medium` default, so that
            // three 640x480 cameras at 30 fps fit in two cores.
            preset: Some(if encoder == "libsvtav1" { "12" } else { "veryfast" }.to_owned()),
            // Low-delay prediction: SVT-AV1 keeps no mini-GOP of future frames: half the memory per encoder
            // (~55 MB instead of ~110 MB at 640x480) and a flush that does not re-encode a backlog at save
            // time. In that mode SVT-AV1 (1.4) makes its periodic intra frames forward key frames, which are
            // not sync samples: the file would have one key frame, and every random access (lerobot's
            // training loader) would decode from the episode's start. `irefresh-type=2` makes them true key
            // frames: the I/P alternation lerobot writes with its GOP of 2.
            extra: if encoder == "libsvtav1" {
                vec![("svtav1-params".to_owned(), SVT_LOW_DELAY_PARAMS.to_owned())]
            } else {
                Vec::new()
            },
        };
        for kv in opts.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (k, v) = kv
                .split_once('=')
                .ok_or_else(|| RecorderError::InvalidSpec(format!("video option {kv:?} is not key=value")))?;
            let bad = |_| RecorderError::InvalidSpec(format!("video option {k}={v} is not a number"));
            match k {
                "preset" => settings.preset = Some(v.to_owned()),
                "crf" => settings.crf = v.parse().map_err(bad)?,
                "g" | "gop" => settings.gop = v.parse().map_err(bad)?,
                _ => {
                    // A given option replaces the default of the same name; an empty value removes it.
                    settings.extra.retain(|(ek, _)| ek != k);
                    if !v.is_empty() {
                        settings.extra.push((k.to_owned(), v.to_owned()));
                    }
                }
            }
        }
        Ok(settings)
    }
}

pub use phone2act_core::config::MAX_TASK_BYTES;

impl DatasetSpec {
    /// The optional per-frame bool columns this dataset carries.
    pub fn flag_columns(&self) -> crate::parquet_io::FlagColumns {
        crate::parquet_io::FlagColumns {
            success: self.success,
            intervention: self.intervention,
        }
    }

    /// Checks what can be checked without touching the disk.
    pub fn validate(&self) -> Result<(), RecorderError> {
        let bad = |m: String| Err(RecorderError::InvalidSpec(m));
        // `create_dir_all("")` succeeds, and every save would then fail on the empty path.
        if self.root.as_os_str().is_empty() {
            return bad("the dataset root is empty: name a directory".into());
        }
        if self.fps == 0 || self.fps > 240 {
            return bad(format!("fps {} is outside 1..=240", self.fps));
        }
        if self.state_names.is_empty() || self.action_names.is_empty() {
            return bad("state and action need at least one named element each".into());
        }
        for (what, names) in [("state", &self.state_names), ("action", &self.action_names)] {
            let mut seen = std::collections::HashSet::new();
            for n in names {
                if n.is_empty() || !seen.insert(n) {
                    return bad(format!("{what} name {n:?} is empty or repeated"));
                }
            }
        }
        for g in &self.modality {
            if g.state_range.end > self.state_names.len()
                || g.action_range.end > self.action_names.len()
                || g.state_range.start > g.state_range.end
                || g.action_range.start > g.action_range.end
            {
                return bad(format!(
                    "modality group {} is out of the state/action range",
                    g.name
                ));
            }
        }
        check_cameras(&self.cameras, self.video_codec.as_deref(), self.format)?;
        Ok(())
    }
}

/// The camera checks of [`DatasetSpec::validate`] (names, sizes, the encoder's smallest frame), on their own so
/// that a configuration can be refused before anything starts, with the rules the recorder applies.
pub fn check_cameras(
    cameras: &[CameraSpec],
    video_codec: Option<&str>,
    format: Format,
) -> Result<(), RecorderError> {
    let bad = |m: String| Err(RecorderError::InvalidSpec(m));
    let mut seen = std::collections::HashSet::new();
    for c in cameras {
        if c.name.is_empty() || c.name.contains('/') || !seen.insert(&c.name) {
            return bad(format!(
                "camera name {:?} is empty, repeated or contains '/'",
                c.name
            ));
        }
        if c.width < 16
            || c.height < 16
            || c.width % 2 != 0
            || c.height % 2 != 0
            || c.width > 8192
            || c.height > 8192
        {
            return bad(format!(
                "camera {} size {}x{} must be even and between 16 and 8192 (yuv420p)",
                c.name, c.width, c.height
            ));
        }
    }
    let video = VideoSettings::parse(video_codec, format)?;
    if video.encoder == "libsvtav1"
        && let Some(c) = cameras.iter().find(|c| c.width < 64 || c.height < 64)
    {
        return bad(format!(
            "camera {} is {}x{}: SVT-AV1 needs at least 64x64 (use h264 for smaller)",
            c.name, c.width, c.height
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_root_is_refused_before_anything_is_written() {
        // `create_dir_all("")` succeeds, so an empty root used to open and then fail every save.
        let spec = DatasetSpec {
            root: PathBuf::new(),
            format: Format::V30,
            fps: 20,
            robot_type: "test".into(),
            video_codec: None,
            state_names: vec!["a".into()],
            action_names: vec!["b".into()],
            cameras: Vec::new(),
            modality: Vec::new(),
            provenance: serde_json::Value::Null,
            success: false,
            intervention: false,
        };
        let err = spec.validate().unwrap_err().to_string();
        assert!(err.contains("dataset root is empty"), "{err}");
        let named = DatasetSpec {
            root: PathBuf::from("ds"),
            ..spec
        };
        assert!(named.validate().is_ok());
    }

    #[test]
    fn codec_defaults_follow_lerobot_and_gr00t() {
        let av1 = VideoSettings::parse(None, Format::V30).unwrap();
        assert_eq!(
            (av1.encoder.as_str(), av1.codec.as_str(), av1.gop, av1.crf),
            ("libsvtav1", "av1", 2, 30)
        );
        assert_eq!(av1.preset.as_deref(), Some("12"));
        assert_eq!(
            av1.extra,
            vec![("svtav1-params".to_owned(), SVT_LOW_DELAY_PARAMS.to_owned())]
        );
        let lerobot_like = VideoSettings::parse(Some("av1:svtav1-params="), Format::V30).unwrap();
        assert!(lerobot_like.extra.is_empty());
        let h264 = VideoSettings::parse(None, Format::V21).unwrap();
        assert_eq!(
            (h264.encoder.as_str(), h264.preset.as_deref()),
            ("libx264", Some("veryfast"))
        );
        let custom =
            VideoSettings::parse(Some("h264:preset=veryfast,crf=23,tune=zerolatency"), Format::V30).unwrap();
        assert_eq!(custom.preset.as_deref(), Some("veryfast"));
        assert_eq!(custom.crf, 23);
        assert_eq!(custom.extra, vec![("tune".to_owned(), "zerolatency".to_owned())]);
        assert!(VideoSettings::parse(Some("mpeg2"), Format::V30).is_err());
        assert!(VideoSettings::parse(Some("h264:crf=x"), Format::V30).is_err());
    }
}

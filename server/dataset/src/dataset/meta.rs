//! The metadata both layouts share: `info.json` (with the feature definitions), `stats.json`, and the
//! statistics of the default columns.

use super::journal::Staging;
use super::{Layout, timestamp_s};
use crate::error::RecorderError;
use crate::quantiles::QuantileStore;
use crate::spec::{DatasetSpec, ModalityGroup, VideoSettings};
use crate::stats::{Aggregate, ColumnStats, StatKind};
use indexmap::IndexMap;
use serde::Serialize;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::path::Path;

const DEFAULT_FEATURES: [&str; 5] = ["timestamp", "frame_index", "episode_index", "index", "task_index"];

/// Pretty JSON with lerobot's four-space indent.
pub(super) fn pretty<T: Serialize + ?Sized>(v: &T) -> Vec<u8> {
    let mut out = Vec::new();
    let fmt = serde_json::ser::PrettyFormatter::with_indent(b"    ");
    let mut ser = serde_json::Serializer::with_formatter(&mut out, fmt);
    v.serialize(&mut ser).expect("JSON values always serialise");
    out
}

/// The `features` of `info.json`, in lerobot's order (state, action, cameras, then the default columns).
pub(super) fn features(spec: &DatasetSpec, video: &VideoSettings) -> IndexMap<String, Value> {
    let s = spec;
    let mut f = IndexMap::new();
    f.insert(
        "observation.state".to_owned(),
        json!({"dtype": "float32", "shape": [s.state_names.len()], "names": s.state_names}),
    );
    f.insert(
        "action".to_owned(),
        json!({"dtype": "float32", "shape": [s.action_names.len()], "names": s.action_names}),
    );
    for name in s.flag_columns().names() {
        f.insert(
            name.to_owned(),
            json!({"dtype": "bool", "shape": [1], "names": null}),
        );
    }
    for c in &s.cameras {
        f.insert(
            c.key(),
            json!({
                "dtype": "video",
                "shape": [c.height, c.width, 3],
                "names": ["height", "width", "channels"],
                "info": {
                    "video.height": c.height, "video.width": c.width, "video.codec": video.codec,
                    "video.pix_fmt": "yuv420p", "video.is_depth_map": false, "video.fps": s.fps,
                    "video.channels": 3, "has_audio": false
                }
            }),
        );
    }
    f.insert(
        "timestamp".to_owned(),
        json!({"dtype": "float32", "shape": [1], "names": null}),
    );
    for k in &DEFAULT_FEATURES[1..] {
        f.insert(
            (*k).to_owned(),
            json!({"dtype": "int64", "shape": [1], "names": null}),
        );
    }
    f
}

/// `meta/info.json`: the head in lerobot's key order, `features` last.
#[derive(Serialize)]
struct Info {
    #[serde(flatten)]
    head: IndexMap<&'static str, Value>,
    features: IndexMap<String, Value>,
}

/// The totals of the committed dataset, as `info.json` states them.
pub(super) struct Totals {
    pub(super) episodes: u64,
    pub(super) frames: u64,
    pub(super) tasks: usize,
}

/// `meta/info.json` for `totals`, keys in lerobot's order.
pub(super) fn info_json(
    spec: &DatasetSpec,
    video: &VideoSettings,
    layout: &dyn Layout,
    totals: &Totals,
) -> Vec<u8> {
    let n = totals.episodes;
    let mut head: IndexMap<&'static str, Value> = IndexMap::new();
    head.insert("codebase_version", json!(spec.format.codebase_version()));
    head.insert("robot_type", json!(spec.robot_type));
    head.insert("total_episodes", json!(n));
    head.insert("total_frames", json!(totals.frames));
    head.insert("total_tasks", json!(totals.tasks));
    head.extend(layout.info_fields(n, spec.cameras.len() as u64));
    head.insert("fps", json!(spec.fps));
    head.insert("splits", json!({"train": format!("0:{n}")}));
    let (data_path, video_path) = layout.path_templates();
    head.insert("data_path", json!(data_path));
    head.insert(
        "video_path",
        if spec.cameras.is_empty() {
            Value::Null
        } else {
            json!(video_path)
        },
    );
    let mut out = pretty(&Info {
        head,
        features: features(spec, video),
    });
    out.push(b'\n');
    out
}

/// Checks that the features of an existing `info.json` are the ones `spec` would write.
pub(super) fn check_features(
    root: &Path,
    spec: &DatasetSpec,
    video: &VideoSettings,
    found: &Value,
) -> Result<(), RecorderError> {
    let mismatch = |detail: String| RecorderError::FeatureMismatch {
        root: root.to_owned(),
        detail,
    };
    let Some(found) = found.as_object() else {
        return Err(mismatch("info.json has no features".into()));
    };
    let want = features(spec, video);
    let mut found_keys: Vec<&String> = found.keys().collect();
    found_keys.sort();
    let mut wk: Vec<&String> = want.keys().collect();
    wk.sort();
    if wk != found_keys {
        return Err(mismatch(format!("dataset has {found_keys:?}, config has {wk:?}")));
    }
    for (k, w) in &want {
        let f = &found[k];
        for field in ["dtype", "shape"] {
            if f[field] != w[field] {
                return Err(mismatch(format!(
                    "{k}.{field} is {} in the dataset, {} in the config",
                    f[field], w[field]
                )));
            }
        }
        if w["dtype"] != "video" && f["names"] != w["names"] {
            return Err(mismatch(format!(
                "{k}.names are {} in the dataset, {} in the config",
                f["names"], w["names"]
            )));
        }
    }
    Ok(())
}

/// The dataset's `meta/stats.json`: the running aggregates, with the numeric columns' quantiles taken from
/// the dataset's sketches, each feature in the layout's dialect (see [`Layout::stats_entry`]).
pub(super) fn stats_json(
    agg: &BTreeMap<String, Aggregate>,
    quantiles: &QuantileStore,
    layout: &dyn Layout,
) -> Value {
    let map: serde_json::Map<String, Value> = agg
        .iter()
        .filter_map(|(k, a)| {
            let mut s = a.finish()?;
            quantiles.apply(k, &mut s);
            Some((k.clone(), layout.stats_entry(k, &s)?))
        })
        .collect();
    Value::Object(map)
}

/// The default features' values over one episode, as the parquet holds them.
pub(super) fn default_feature_columns(
    frames: u64,
    fps: u32,
    episode: u64,
    first_index: u64,
    task_index: i64,
) -> [(&'static str, ColumnStats); 5] {
    let mut ts = ColumnStats::new(StatKind::Float, 1);
    let mut fi = ColumnStats::new(StatKind::Int, 1);
    let mut ei = ColumnStats::new(StatKind::Int, 1);
    let mut ix = ColumnStats::new(StatKind::Int, 1);
    let mut ti = ColumnStats::new(StatKind::Int, 1);
    for i in 0..frames {
        ts.push(&[f64::from(timestamp_s(i, fps))]);
        fi.push(&[i as f64]);
        ei.push(&[episode as f64]);
        ix.push(&[(first_index + i) as f64]);
        ti.push(&[task_index as f64]);
    }
    [
        ("timestamp", ts),
        ("frame_index", fi),
        ("episode_index", ei),
        ("index", ix),
        ("task_index", ti),
    ]
}

/// GR00T's `meta/modality.json`: which slices of state and action form each body part, and the camera keys.
/// Both formats carry it (GR00T's own loader, and LeRobot's GR00T training, find the body parts there); it
/// depends only on the spec, so every save writes the same bytes.
pub(super) fn modality_json(spec: &DatasetSpec) -> Value {
    let mut state = serde_json::Map::new();
    let mut action = serde_json::Map::new();
    let groups = if spec.modality.is_empty() {
        vec![ModalityGroup {
            name: "arm".into(),
            state_range: 0..spec.state_names.len(),
            action_range: 0..spec.action_names.len(),
            action_absolute: true,
        }]
    } else {
        spec.modality.clone()
    };
    for g in &groups {
        if !g.state_range.is_empty() {
            state.insert(
                g.name.clone(),
                json!({"start": g.state_range.start, "end": g.state_range.end}),
            );
        }
        if !g.action_range.is_empty() {
            action.insert(
                g.name.clone(),
                json!({
                    "start": g.action_range.start,
                    "end": g.action_range.end,
                    "absolute": g.action_absolute,
                }),
            );
        }
    }
    let video: serde_json::Map<String, Value> = spec
        .cameras
        .iter()
        .map(|c| (c.name.clone(), json!({"original_key": c.key()})))
        .collect();
    let mut annotation = serde_json::Map::new();
    annotation.insert(
        "human.task_description".into(),
        json!({"original_key": "task_index"}),
    );
    if spec.intervention {
        // GR00T resolves `annotation.<key>` through `original_key` to the parquet column; a data config
        // that does not name it ignores it.
        annotation.insert(
            "human.intervention".into(),
            json!({"original_key": crate::parquet_io::INTERVENTION_FEATURE}),
        );
    }
    if spec.success {
        // The outcome the operator gave at Stop (or the scene's flag), for data configs that filter or weight
        // episodes by it.
        annotation.insert(
            "human.success".into(),
            json!({"original_key": crate::parquet_io::SUCCESS_FEATURE}),
        );
    }
    json!({
        "state": state,
        "action": action,
        "video": video,
        "annotation": annotation,
    })
}

/// Writes `meta/modality.json` into a save's staging and queues it with the other metadata (before
/// `info.json`, like every file of the save).
pub(super) fn stage_modality(spec: &DatasetSpec, staging: &mut Staging) -> Result<(), RecorderError> {
    staging.write(
        "modality.json",
        &pretty(&modality_json(spec)),
        "meta/modality.json",
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{v21::V21, v30::V30};
    use crate::spec::{CameraSpec, Format};
    use std::path::PathBuf;

    fn spec(format: Format) -> DatasetSpec {
        DatasetSpec {
            root: PathBuf::from("/nonexistent"),
            format,
            fps: 30,
            robot_type: "test".into(),
            video_codec: None,
            state_names: vec!["a".into(), "b".into()],
            action_names: vec!["c".into()],
            cameras: ["front", "wrist"]
                .map(|name| CameraSpec {
                    name: name.into(),
                    width: 64,
                    height: 48,
                })
                .to_vec(),
            modality: Vec::new(),
            provenance: Value::Null,
            success: false,
            intervention: false,
        }
    }

    /// Keys of a JSON object and of its `features`, in file order.
    fn key_order(text: &[u8]) -> (Vec<String>, Vec<String>) {
        let top: IndexMap<String, Value> = serde_json::from_slice(text).unwrap();
        let features: IndexMap<String, Value> = serde_json::from_value(top["features"].clone()).unwrap();
        (top.into_keys().collect(), features.into_keys().collect())
    }

    /// The key order lerobot's own writers produce (the fixtures are lerobot 0.4.4 and 0.3.3 datasets, see
    /// tests/fixtures/README.md); their extra `next.done` feature is not one phone2act records.
    #[test]
    fn info_json_keys_are_in_lerobot_order() {
        let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures");
        let v30 = V30::new(1);
        let v21 = V21::default();
        let cases: [(Format, &dyn Layout, &str); 2] = [
            (Format::V30, &v30, "lerobot_sample_v30"),
            (Format::V21, &v21, "lerobot_sample_v21"),
        ];
        for (format, layout, fixture) in cases {
            let spec = spec(format);
            let video = VideoSettings::parse(None, format).unwrap();
            let totals = Totals {
                episodes: 2,
                frames: 40,
                tasks: 1,
            };
            let ours = info_json(&spec, &video, layout, &totals);
            assert!(ours.ends_with(b"}\n"));
            let theirs = std::fs::read(fixtures.join(fixture).join("meta/info.json")).unwrap();
            let (our_top, our_features) = key_order(&ours);
            let (their_top, mut their_features) = key_order(&theirs);
            assert_eq!(our_top, their_top, "{fixture}");
            their_features.retain(|k| k != "next.done");
            assert_eq!(our_features, their_features, "{fixture}");
        }
    }
}

//! Reading one episode of a LeRobot dataset back (v3.0 or v2.1, written by phone2act or by lerobot): its
//! state and action rows, where its camera videos are, and its task. `phone2act dataset plot` uses it; the
//! file locations come from `info.json`'s path templates and, in v3.0, the episode's metadata row, as
//! lerobot's loader finds them.

use crate::error::RecorderError;
use crate::parquet_io::{float_values, int_column, read_batches};
use arrow_array::ArrayRef;
use arrow_array::cast::AsArray;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Why an episode cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{0} does not exist")]
    NoDirectory(PathBuf),
    #[error("{0} is not a LeRobot dataset (no readable meta/info.json)")]
    NotADataset(PathBuf),
    #[error("the dataset has {total} episodes (0..{total}); there is no episode {index}")]
    NoEpisode { index: u64, total: u64 },
    #[error("unsupported dataset: {0}")]
    Unsupported(String),
    #[error("the video of camera {key} for episode {index} is missing: {path} does not exist")]
    MissingVideo { key: String, index: u64, path: PathBuf },
    #[error(transparent)]
    Recorder(#[from] RecorderError),
}

/// A vector feature (`observation.state`, `action`) of one episode.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VectorFeature {
    pub key: String,
    /// One per dimension: from `info.json` (`names` as a list, or the list inside a `{"motors": [...]}`
    /// map), else `key[i]`.
    pub names: Vec<String>,
    /// Per frame, one value per dimension.
    pub rows: Vec<Vec<f64>>,
}

/// One camera's video of the episode.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeVideo {
    pub key: String,
    pub path: PathBuf,
    /// Where the episode starts in the file, s (v3.0 files can hold several episodes; 0 in v2.1).
    pub from_s: f64,
}

/// One episode as read back.
#[derive(Clone, Debug, PartialEq)]
pub struct Episode {
    pub version: String,
    pub robot_type: String,
    pub fps: f64,
    pub total_episodes: u64,
    pub index: u64,
    pub task: String,
    /// `frame_index` of every row, in order.
    pub frame_index: Vec<i64>,
    /// The episode's vector features, `observation.state` first, then `action` (those it has).
    pub vectors: Vec<VectorFeature>,
    pub videos: Vec<EpisodeVideo>,
}

/// Row `row` of a list or fixed-size-list column of floats.
fn vector_at(column: &ArrayRef, row: usize) -> Option<Vec<f64>> {
    if let Some(l) = column.as_fixed_size_list_opt() {
        return float_values(&l.value(row));
    }
    if let Some(l) = column.as_list_opt::<i32>() {
        return float_values(&l.value(row));
    }
    None
}

/// `info.json`'s path template with `values` filled in (`{name}` and `{name:03d}`, Python's format).
fn fill(template: &str, values: &[(&str, String)]) -> String {
    let mut out = template.to_owned();
    for (name, value) in values {
        for width in 0..=9 {
            let (pattern, text) = if width == 0 {
                (format!("{{{name}}}"), value.clone())
            } else {
                (format!("{{{name}:0{width}d}}"), format!("{value:0>width$}"))
            };
            out = out.replace(&pattern, &text);
        }
    }
    out
}

fn dimension_names(key: &str, feature: &Value, dims: usize) -> Vec<String> {
    let listed = match &feature["names"] {
        Value::Array(a) => Some(a.clone()),
        // v2.x datasets converted from older ones: `{"motors": ["..."]}`.
        Value::Object(m) if m.len() == 1 => m.values().next().and_then(|v| v.as_array().cloned()),
        _ => None,
    };
    let listed: Vec<String> = listed
        .unwrap_or_default()
        .iter()
        .filter_map(|n| n.as_str().map(str::to_owned))
        .collect();
    if listed.len() == dims {
        listed
    } else {
        (0..dims).map(|i| format!("{key}[{i}]")).collect()
    }
}

/// Reads episode `index` of the dataset at `root`.
pub fn read_episode(root: &Path, index: u64) -> Result<Episode, ReadError> {
    if !root.is_dir() {
        return Err(ReadError::NoDirectory(root.to_owned()));
    }
    let info: Value = std::fs::read_to_string(root.join("meta/info.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .ok_or_else(|| ReadError::NotADataset(root.to_owned()))?;
    let version = info["codebase_version"].as_str().unwrap_or("?").to_owned();
    let v30 = match version.as_str() {
        "v3.0" => true,
        "v2.1" | "v2.0" => false,
        other => return Err(ReadError::Unsupported(format!("codebase_version {other:?}"))),
    };
    let fps = info["fps"]
        .as_f64()
        .filter(|f| *f > 0.0)
        .ok_or_else(|| ReadError::Unsupported("info.json has no positive fps".into()))?;
    let total_episodes = info["total_episodes"].as_u64().unwrap_or(0);
    if index >= total_episodes {
        return Err(ReadError::NoEpisode {
            index,
            total: total_episodes,
        });
    }
    let chunks_size = info["chunks_size"].as_u64().unwrap_or(1000).max(1);
    let features = info["features"].as_object().cloned().unwrap_or_default();
    let video_keys: Vec<String> = features
        .iter()
        .filter(|(_, f)| f["dtype"] == "video")
        .map(|(k, _)| k.clone())
        .collect();
    let (data_template, video_template) = (
        info["data_path"].as_str().unwrap_or_default(),
        info["video_path"].as_str().unwrap_or_default(),
    );

    let mut task_index = None;
    let (data_path, mut videos) = if v30 {
        locate_v30(root, index, &video_keys, data_template, video_template)?
    } else {
        let chunk = (index / chunks_size).to_string();
        let values = |key: &str| {
            vec![
                ("episode_chunk", chunk.clone()),
                ("episode_index", index.to_string()),
                ("video_key", key.to_owned()),
            ]
        };
        let data = root.join(fill(data_template, &values("")));
        let videos = video_keys
            .iter()
            .map(|key| EpisodeVideo {
                key: key.clone(),
                path: root.join(fill(video_template, &values(key))),
                from_s: 0.0,
            })
            .collect();
        (data, videos)
    };
    for v in &mut videos {
        if !v.path.is_file() {
            return Err(ReadError::MissingVideo {
                key: v.key.clone(),
                index,
                path: v.path.clone(),
            });
        }
    }

    let keys: Vec<&str> = ["observation.state", "action"]
        .into_iter()
        .filter(|k| features.contains_key(*k))
        .collect();
    let mut vectors: Vec<VectorFeature> = keys
        .iter()
        .map(|k| VectorFeature {
            key: (*k).to_owned(),
            ..VectorFeature::default()
        })
        .collect();
    let mut frame_index = Vec::new();
    for batch in read_batches(&data_path)? {
        let bad = |detail: String| RecorderError::Parquet {
            path: data_path.clone(),
            detail,
        };
        let episodes =
            int_column(&batch, "episode_index").ok_or_else(|| bad("no int64 episode_index".into()))?;
        let frames = int_column(&batch, "frame_index").ok_or_else(|| bad("no int64 frame_index".into()))?;
        let tasks = int_column(&batch, "task_index");
        let columns: Vec<ArrayRef> = keys
            .iter()
            .map(|k| {
                batch
                    .column_by_name(k)
                    .cloned()
                    .ok_or_else(|| bad(format!("no column {k}")))
            })
            .collect::<Result<_, _>>()?;
        for row in (0..batch.num_rows()).filter(|&r| episodes[r] == index as i64) {
            frame_index.push(frames[row]);
            task_index = task_index.or_else(|| tasks.as_ref().map(|t| t[row]));
            for (v, column) in vectors.iter_mut().zip(&columns) {
                v.rows.push(
                    vector_at(column, row)
                        .ok_or_else(|| bad(format!("{} is not a list of floats", v.key)))?,
                );
            }
        }
    }
    if frame_index.is_empty() {
        return Err(ReadError::Recorder(RecorderError::CorruptDataset {
            root: root.to_owned(),
            detail: format!("{} holds no row of episode {index}", data_path.display()),
        }));
    }
    for v in &mut vectors {
        let dims = v.rows.first().map_or(0, Vec::len);
        v.names = dimension_names(&v.key, &features[&v.key], dims);
    }
    let task = task_index
        .and_then(|t| usize::try_from(t).ok())
        .and_then(|t| read_task_table(root, v30).get(t).cloned())
        .unwrap_or_default();
    Ok(Episode {
        version,
        robot_type: info["robot_type"].as_str().unwrap_or_default().to_owned(),
        fps,
        total_episodes,
        index,
        task,
        frame_index,
        vectors,
        videos,
    })
}

/// v3.0: the data file and each camera's file and start time, from the episode's metadata row.
fn locate_v30(
    root: &Path,
    index: u64,
    video_keys: &[String],
    data_template: &str,
    video_template: &str,
) -> Result<(PathBuf, Vec<EpisodeVideo>), ReadError> {
    let mut meta_files: Vec<PathBuf> = Vec::new();
    let meta_dir = root.join("meta/episodes");
    for chunk in std::fs::read_dir(&meta_dir)
        .map_err(|e| RecorderError::io(&meta_dir, e))?
        .flatten()
    {
        for file in std::fs::read_dir(chunk.path()).into_iter().flatten().flatten() {
            if file.path().extension().is_some_and(|e| e == "parquet") {
                meta_files.push(file.path());
            }
        }
    }
    meta_files.sort();
    for path in meta_files {
        for batch in read_batches(&path)? {
            let Some(row) =
                int_column(&batch, "episode_index").and_then(|e| e.iter().position(|&e| e == index as i64))
            else {
                continue;
            };
            let int_at = |name: &str| int_column(&batch, name).map(|v| v[row]);
            let location = |prefix: &str| -> Result<Vec<(&'static str, String)>, ReadError> {
                match (
                    int_at(&format!("{prefix}/chunk_index")),
                    int_at(&format!("{prefix}/file_index")),
                ) {
                    (Some(c), Some(f)) => Ok(vec![
                        ("chunk_index", c.to_string()),
                        ("file_index", f.to_string()),
                    ]),
                    _ => Err(ReadError::Unsupported(format!(
                        "{}: episode {index} has no {prefix}/chunk_index and file_index",
                        path.display()
                    ))),
                }
            };
            let data = root.join(fill(data_template, &location("data")?));
            let mut videos = Vec::new();
            for key in video_keys {
                let prefix = format!("videos/{key}");
                let mut values = location(&prefix)?;
                values.push(("video_key", key.clone()));
                let from_s = batch
                    .column_by_name(&format!("{prefix}/from_timestamp"))
                    .and_then(float_values)
                    .map_or(0.0, |v| v[row]);
                videos.push(EpisodeVideo {
                    key: key.clone(),
                    path: root.join(fill(video_template, &values)),
                    from_s,
                });
            }
            return Ok((data, videos));
        }
    }
    Err(ReadError::Recorder(RecorderError::CorruptDataset {
        root: root.to_owned(),
        detail: format!("meta/episodes lists no episode {index}"),
    }))
}

/// The task texts by index (empty when the table cannot be read: the task is a label, not essential).
fn read_task_table(root: &Path, v30: bool) -> Vec<String> {
    if v30 {
        return crate::parquet_io::read_tasks(&root.join("meta/tasks.parquet")).unwrap_or_default();
    }
    let mut tasks: Vec<(i64, String)> = std::fs::read_to_string(root.join("meta/tasks.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter_map(|v| Some((v["task_index"].as_i64()?, v["task"].as_str()?.to_owned())))
        .collect();
    tasks.sort_by_key(|t| t.0);
    tasks.into_iter().map(|t| t.1).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/fixtures")
            .join(name)
    }

    #[test]
    fn lerobot_written_episodes_read_back_in_both_formats() {
        // The fixtures' README: episodes of 10, 12 and 8 frames; episode 1's task is "place it in the bowl".
        for name in ["lerobot_sample_v30", "lerobot_sample_v21"] {
            let ep = read_episode(&fixture(name), 1).unwrap();
            assert_eq!(ep.frame_index, (0..12).collect::<Vec<i64>>(), "{name}");
            assert_eq!(ep.task, "place it in the bowl", "{name}");
            assert_eq!(ep.vectors.len(), 2);
            assert_eq!(ep.vectors[0].names[0], "j0");
            assert!(
                ep.vectors
                    .iter()
                    .all(|v| v.rows.len() == 12 && v.rows[0].len() == 6)
            );
            assert_eq!(ep.videos.len(), 2);
        }
        // In v3.0 the three episodes share one video file: episode 1 starts after episode 0's 10 frames.
        let ep = read_episode(&fixture("lerobot_sample_v30"), 1).unwrap();
        assert!(
            (ep.videos[0].from_s - 1.0).abs() < 1e-6,
            "{}",
            ep.videos[0].from_s
        );
    }

    #[test]
    fn bad_requests_say_what_is_wrong() {
        let err = read_episode(&fixture("lerobot_sample_v30"), 3).unwrap_err();
        assert!(err.to_string().contains("has 3 episodes"), "{err}");
        let err = read_episode(Path::new("/nonexistent/ds"), 0).unwrap_err();
        assert!(err.to_string().contains("does not exist"), "{err}");
        let err = read_episode(&fixture(""), 0).unwrap_err();
        assert!(err.to_string().contains("not a LeRobot dataset"), "{err}");
    }

    #[test]
    fn templates_fill_like_python_format() {
        let t = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";
        let got = fill(
            t,
            &[
                ("video_key", "observation.images.front".into()),
                ("chunk_index", "1".into()),
                ("file_index", "12".into()),
            ],
        );
        assert_eq!(got, "videos/observation.images.front/chunk-001/file-012.mp4");
    }
}

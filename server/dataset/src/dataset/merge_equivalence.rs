//! The streaming merge against the whole-list reading it replaced: each input's episode metadata, data rows
//! and provenance are read whole here, the merged metadata, statistics and provenance are worked out from
//! them as a merge that holds every episode would, and the merge's output must be exactly that, for v3.0
//! (several output files, so rows roll over) and v2.1, on three inputs made from lerobot's sample dataset: one
//! with a provenance sidecar, one without, one that is itself a merge (its entries keep where they first came
//! from).
//!

use super::*;
use crate::{EpisodeSummary, Format};

const CAMERAS: [&str; 2] = ["observation.images.front", "observation.images.wrist"];

fn copy_dir(src: &Path, dst: &Path) {
    fs::create_dir_all(dst).unwrap();
    for e in fs::read_dir(src).unwrap().flatten() {
        let to = dst.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            fs::copy(e.path(), &to).unwrap();
        }
    }
}

/// Three inputs from lerobot's own sample dataset (three episodes, two cameras, several episodes per file):
/// `a` with a provenance sidecar naming its station and operator, `b` without one, `c` a merge of the sample
/// (its entries keep where they first came from).
fn inputs(format: Format, dir: &Path) -> Vec<MergeInput> {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join(match format {
        Format::V30 => "../../tests/fixtures/lerobot_sample_v30",
        Format::V21 => "../../tests/fixtures/lerobot_sample_v21",
    });
    for n in ["a", "b", "c0"] {
        copy_dir(&fixture, &dir.join(n));
    }
    let lengths: Vec<u64> = if format == Format::V30 {
        all_rows(&dir.join("a"), "meta/episodes")
            .iter()
            .flat_map(|b| int_column(b, "length").unwrap())
            .map(|l| l as u64)
            .collect()
    } else {
        fs::read_to_string(dir.join("a/meta/episodes.jsonl"))
            .unwrap()
            .lines()
            .map(|l| {
                serde_json::from_str::<Value>(l).unwrap()["length"]
                    .as_u64()
                    .unwrap()
            })
            .collect()
    };
    let provenance = Provenance {
        software: "phone2act-recorder".into(),
        version: "0".into(),
        format: "v3.0".into(),
        video: json!({"codec": "av1"}),
        config: json!({"station_id": "st-a"}),
        sync: Value::Null,
        episodes: lengths
            .iter()
            .enumerate()
            .map(|(i, l)| EpisodeSummary {
                index: i as u64,
                length_frames: *l,
                duration_s: *l as f64 / 3.0,
                operator: "ana".into(),
                task: "from the sidecar".into(),
                ..EpisodeSummary::default()
            })
            .collect(),
        stats: BTreeMap::new(),
    };
    let path = dir.join("a").join(PROVENANCE_FILE);
    fs::create_dir_all(path.parent().unwrap()).unwrap();
    fs::write(&path, pretty(&provenance)).unwrap();
    let c0 = MergeInput {
        root: dir.join("c0"),
        label: "s3://bucket/st-c".into(),
    };
    merge(&[c0], &dir.join("c"), &MergeOptions::default()).unwrap();
    ["a", "b", "c"]
        .map(|n| MergeInput {
            root: dir.join(n),
            label: format!("station {n}"),
        })
        .to_vec()
}

/// Provenance entries as they read back from a file (a float printed and parsed again may move by an ulp,
/// so both sides of a comparison take that trip).
fn as_read(entries: &[EpisodeSummary]) -> Vec<EpisodeSummary> {
    serde_json::from_str(&serde_json::to_string(entries).unwrap()).unwrap()
}

/// What a merge holding every input's provenance list gives episode `index` (of `length` frames) of `input`.
fn expected_entry(input: &MergeInput, index: u64, length: u64, task: String, new: u64) -> EpisodeSummary {
    let prov: Option<Provenance> = fs::read(input.root.join(PROVENANCE_FILE))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok());
    let fps = read_json(&input.root.join("meta/info.json")).unwrap()["fps"]
        .as_f64()
        .unwrap();
    let same = |e: &&EpisodeSummary| e.index == index && e.length_frames == length;
    let mut e = prov
        .as_ref()
        .and_then(|p| p.episodes.iter().find(same).cloned())
        .unwrap_or_else(|| EpisodeSummary {
            length_frames: length,
            duration_s: length as f64 / fps,
            task,
            ..EpisodeSummary::default()
        });
    if e.station_id.is_empty()
        && let Some(p) = &prov
    {
        e.station_id = p.config["station_id"].as_str().unwrap_or_default().to_owned();
    }
    e.merged_from.get_or_insert(MergedFrom {
        dataset: input.label.clone(),
        episode_index: index,
    });
    e.index = new;
    e
}

fn merged_provenance(dst: &Path) -> Provenance {
    serde_json::from_slice(&fs::read(dst.join(PROVENANCE_FILE)).unwrap()).unwrap()
}

/// Every numeric column's stats over all episodes, worked out from whole data tables (the rows of each
/// episode, in merge order, with their new indices), in the format's JSON, as they read back from a file.
fn expected_stats(
    episodes: &[RecordBatch],
    to_json: fn(&FeatureStats) -> Value,
    extra: BTreeMap<String, Aggregate>,
) -> Value {
    let mut aggregates = extra;
    let mut quantiles = QuantileStore::default();
    for rows in episodes {
        let cols: Vec<(String, ColumnStats)> = numeric_columns(&rows.schema())
            .iter()
            .map(|c| (c.name.clone(), column_stats(c, rows.column(c.index))))
            .collect();
        let refs: Vec<(&str, &ColumnStats)> = cols.iter().map(|(k, c)| (k.as_str(), c)).collect();
        quantiles.add_episode(rows.num_rows() as u64, &refs);
        for (k, c) in &cols {
            aggregates.entry(k.clone()).or_default().add(&c.finish());
        }
    }
    let mut stats = serde_json::Map::new();
    for (k, a) in &aggregates {
        if let Some(mut s) = a.finish() {
            quantiles.apply(k, &mut s);
            stats.insert(k.clone(), to_json(&s));
        }
    }
    serde_json::from_slice(&pretty(&Value::Object(stats))).unwrap()
}

/// The rows of `batches` whose `episode_index` is `e`.
fn episode_rows(batches: &[RecordBatch], e: u64) -> RecordBatch {
    let all = arrow_select::concat::concat_batches(&batches[0].schema(), batches).unwrap();
    let idx = int_column(&all, "episode_index").unwrap();
    let first = idx.iter().position(|x| *x == e as i64).unwrap();
    let n = idx.iter().filter(|x| **x == e as i64).count();
    all.slice(first, n)
}

/// The same values in the same columns (field metadata aside: a parquet round trip names list items its way).
fn assert_same_rows(written: &RecordBatch, expected: &RecordBatch, episode: u64) {
    assert_eq!(written.num_columns(), expected.num_columns(), "episode {episode}");
    for (i, f) in expected.schema().fields().iter().enumerate() {
        let (w, e) = (written.column(i), expected.column(i));
        let same = match (w.data_type(), e.data_type()) {
            (DataType::FixedSizeList(..), DataType::FixedSizeList(..)) => {
                let (w, e) = (w.as_fixed_size_list(), e.as_fixed_size_list());
                (0..e.len()).all(|r| w.value(r).to_data() == e.value(r).to_data())
            }
            _ => w.to_data() == e.to_data(),
        };
        assert!(
            same,
            "episode {episode}'s {}: {w:?} written, {e:?} expected",
            f.name()
        );
    }
}

fn all_rows(root: &Path, top: &str) -> Vec<RecordBatch> {
    parquet_files(&root.join(top))
        .flat_map(|f| parquet_io::read_batches(&f).unwrap())
        .collect()
}

fn meta_column(row: &RecordBatch, name: &str) -> i64 {
    int_column(row, name).unwrap()[0]
}

#[test]
fn v30_streaming_merge_writes_what_the_whole_lists_give() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = inputs(Format::V30, dir.path());
    let dst = dir.path().join("merged");
    // Small files, so the data, metadata and video files roll over mid-input.
    let opts = MergeOptions {
        data_file_size_mb: 0.02,
        video_file_size_mb: 0.02,
    };
    let report = merge(&inputs, &dst, &opts).unwrap();
    assert_eq!(report.episodes, 9);
    assert!(report.files_out > 4, "{report:?}");

    let out_meta = all_rows(&dst, "meta/episodes");
    let out_rows: Vec<RecordBatch> = out_meta
        .iter()
        .flat_map(|b| (0..b.num_rows()).map(|r| b.slice(r, 1)))
        .collect();
    assert_eq!(out_rows.len(), 9);
    let mut tasks: Vec<String> = Vec::new();
    let (mut new, mut frames) = (0u64, 0u64);
    let mut data_by_episode = Vec::new();
    let mut provenance = Vec::new();
    for input in &inputs {
        // `index` runs on over the inputs: each input's rows move by the frames before it.
        let input_offset = frames;
        let src_meta = all_rows(&input.root, "meta/episodes");
        let src_data = all_rows(&input.root, "data");
        let src_tasks = parquet_io::read_tasks(&input.root.join("meta/tasks.parquet")).unwrap();
        let task_map: Vec<i64> = src_tasks
            .iter()
            .map(|t| {
                tasks.iter().position(|x| x == t).unwrap_or_else(|| {
                    tasks.push(t.clone());
                    tasks.len() - 1
                }) as i64
            })
            .collect();
        for src in src_meta
            .iter()
            .flat_map(|b| (0..b.num_rows()).map(|r| b.slice(r, 1)))
        {
            let out = &out_rows[usize::try_from(new).unwrap()];
            let old = meta_column(&src, "episode_index") as u64;
            let length = meta_column(&src, "length") as u64;
            let rows = renumber_rows(&episode_rows(&src_data, old), new, input_offset, &task_map).unwrap();

            // The places the merge chose: its data file holds the episode's rows, each video file exists and
            // holds a span as long as the source's.
            let data_file = dst.join(format!(
                "data/chunk-{:03}/file-{:03}.parquet",
                meta_column(out, "data/chunk_index"),
                meta_column(out, "data/file_index")
            ));
            let written = episode_rows(&parquet_io::read_batches(&data_file).unwrap(), new);
            assert_same_rows(&written, &rows, new);
            for key in CAMERAS {
                let video = dst.join(format!(
                    "videos/{key}/chunk-{:03}/file-{:03}.mp4",
                    meta_column(out, &format!("videos/{key}/chunk_index")),
                    meta_column(out, &format!("videos/{key}/file_index"))
                ));
                assert!(video.exists(), "{}", video.display());
                let span = |r: &RecordBatch| {
                    float_at(r, &format!("videos/{key}/to_timestamp"), 0).unwrap()
                        - float_at(r, &format!("videos/{key}/from_timestamp"), 0).unwrap()
                };
                assert!(
                    (span(out) - span(&src)).abs() < 1e-9,
                    "episode {new}'s video span"
                );
            }

            // The rest of the row: the source's, with its indices, places and renumbered stats replaced.
            let mut expect = src.clone();
            expect = set_column(&expect, "episode_index", one_int(new));
            for c in [
                "data/chunk_index",
                "data/file_index",
                "meta/episodes/chunk_index",
                "meta/episodes/file_index",
            ] {
                expect = set_column(&expect, c, Arc::clone(out.column_by_name(c).unwrap()));
            }
            for (key, c) in CAMERAS
                .iter()
                .flat_map(|k| ["chunk_index", "file_index", "from_timestamp", "to_timestamp"].map(|c| (k, c)))
            {
                let c = format!("videos/{key}/{c}");
                expect = set_column(&expect, &c, Arc::clone(out.column_by_name(&c).unwrap()));
            }
            expect = set_column(&expect, "dataset_from_index", one_int(frames));
            expect = set_column(&expect, "dataset_to_index", one_int(frames + length));
            for c in numeric_columns(&rows.schema()) {
                if ["episode_index", "index", "task_index"].contains(&c.name.as_str()) {
                    expect = set_stats(&expect, &c.name, &column_stats(&c, rows.column(c.index)).finish());
                }
            }
            let names = |b: &RecordBatch| -> Vec<String> {
                b.schema().fields().iter().map(|f| f.name().clone()).collect()
            };
            assert_eq!(names(out), names(&expect), "episode {new}'s columns");
            for (i, name) in names(out).iter().enumerate() {
                assert_eq!(
                    out.column(i).to_data(),
                    expect.column(i).to_data(),
                    "episode {new}'s {name}"
                );
            }
            let task = parquet_io::episode_task(&src, 0);
            provenance.push(expected_entry(input, old, length, task, new));
            data_by_episode.push(rows);
            new += 1;
            frames += length;
        }
    }
    assert_eq!(
        parquet_io::read_tasks(&dst.join("meta/tasks.parquet")).unwrap(),
        tasks
    );

    let mut cameras = BTreeMap::new();
    for key in CAMERAS {
        let mut agg = Aggregate::default();
        for input in &inputs {
            let s = read_json(&input.root.join("meta/stats.json")).unwrap();
            agg.add(&image_stats_from_json(&s[key]).unwrap());
        }
        cameras.insert(key.to_owned(), agg);
    }
    assert_eq!(
        read_json(&dst.join("meta/stats.json")).unwrap(),
        expected_stats(&data_by_episode, FeatureStats::to_json_v30, cameras)
    );
    let merged = merged_provenance(&dst);
    assert_eq!(merged.episodes, as_read(&provenance));
    assert_eq!(
        (
            merged.episodes[0].station_id.as_str(),
            merged.episodes[0].operator.as_str()
        ),
        ("st-a", "ana")
    );
    assert_eq!(merged.episodes[3].station_id, "", "b has no sidecar");
    assert_eq!(
        merged.episodes[6].merged_from.as_ref().unwrap().dataset,
        "s3://bucket/st-c",
        "an episode merged twice keeps where it was recorded"
    );
}

#[test]
fn v21_streaming_merge_writes_what_the_whole_lists_give() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = inputs(Format::V21, dir.path());
    let dst = dir.path().join("merged");
    let report = merge(&inputs, &dst, &MergeOptions::default()).unwrap();
    assert_eq!(report.episodes, 9);

    let lines = |root: &Path, rel: &str| -> Vec<Value> {
        fs::read_to_string(root.join(rel))
            .unwrap()
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let (out_episodes, out_stats) = (
        lines(&dst, "meta/episodes.jsonl"),
        lines(&dst, "meta/episodes_stats.jsonl"),
    );
    let mut tasks: Vec<String> = Vec::new();
    let (mut new, mut frames) = (0u64, 0u64);
    let (mut episodes, mut stats_lines, mut data_by_episode, mut provenance) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for input in &inputs {
        let input_offset = frames;
        let mut src_tasks: Vec<(u64, String)> = lines(&input.root, "meta/tasks.jsonl")
            .iter()
            .map(|v| {
                (
                    v["task_index"].as_u64().unwrap(),
                    v["task"].as_str().unwrap().to_owned(),
                )
            })
            .collect();
        src_tasks.sort();
        let task_map: Vec<i64> = src_tasks
            .iter()
            .map(|(_, t)| {
                tasks.iter().position(|x| x == t).unwrap_or_else(|| {
                    tasks.push(t.clone());
                    tasks.len() - 1
                }) as i64
            })
            .collect();
        let src_stats = lines(&input.root, "meta/episodes_stats.jsonl");
        for line in lines(&input.root, "meta/episodes.jsonl") {
            let old = line["episode_index"].as_u64().unwrap();
            let length = line["length"].as_u64().unwrap();
            let data = input
                .root
                .join(format!("data/chunk-000/episode_{old:06}.parquet"));
            let rows = renumber_rows(
                &episode_rows(&parquet_io::read_batches(&data).unwrap(), old),
                new,
                input_offset,
                &task_map,
            )
            .unwrap();
            let written = dst.join(format!("data/chunk-000/episode_{new:06}.parquet"));
            let written = episode_rows(&parquet_io::read_batches(&written).unwrap(), new);
            assert_same_rows(&written, &rows, new);
            let mut stats = src_stats
                .iter()
                .find(|s| s["episode_index"] == old)
                .map_or_else(|| json!({}), |s| s["stats"].clone());
            for c in numeric_columns(&rows.schema()) {
                if ["episode_index", "index", "task_index"].contains(&c.name.as_str()) {
                    stats[c.name.as_str()] = column_stats(&c, rows.column(c.index)).finish().to_json_v21();
                }
            }
            stats_lines.push(json!({"episode_index": new, "stats": stats}));
            let task = line["tasks"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(Value::as_str)
                .collect::<Vec<_>>()
                .join("; ");
            let mut line = line.clone();
            line["episode_index"] = json!(new);
            episodes.push(line);
            provenance.push(expected_entry(input, old, length, task, new));
            data_by_episode.push(rows);
            new += 1;
            frames += length;
        }
    }
    let as_read_values = |v: &[Value]| -> Vec<Value> {
        v.iter()
            .map(|x| serde_json::from_str(&x.to_string()).unwrap())
            .collect()
    };
    assert_eq!(out_episodes, as_read_values(&episodes));
    assert_eq!(out_stats, as_read_values(&stats_lines));
    let out_tasks: Vec<String> = lines(&dst, "meta/tasks.jsonl")
        .iter()
        .map(|v| v["task"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(out_tasks, tasks);
    assert_eq!(
        read_json(&dst.join("meta/stats.json")).unwrap(),
        expected_stats(&data_by_episode, FeatureStats::to_json_gr00t, BTreeMap::new())
    );
    let merged = merged_provenance(&dst);
    assert_eq!(merged.episodes, as_read(&provenance));
    assert_eq!(merged.episodes[3].station_id, "", "b has no sidecar");
}

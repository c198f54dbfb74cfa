//! The order in which a dataset's files become visible remotely, for uploads that are not one commit (a
//! push, or catching up on episodes committed while storage was off): the order of the recorder's own
//! commit (see `phone2act_dataset::dataset`), applied to whole sets of files.

use std::path::Path;

/// Rank of a dataset-relative path: lower goes first; `meta/info.json` is always last.
pub fn rank(rel: &str) -> u8 {
    match rel {
        "meta/info.json" => 9,
        "meta/tasks.parquet" | "meta/tasks.jsonl" => 1,
        // v2.1: after its data files (a line must not name a data file that is not there yet).
        "meta/episodes.jsonl" => 4,
        _ if rel.starts_with("videos/") => 0,
        _ if rel.starts_with("meta/episodes/") => 2,
        _ if rel.starts_with("data/") => 3,
        // phone2act's sidecars (events, quantiles, provenance), ignored by lerobot.
        // (`meta/stats.json`, GR00T's `meta/modality.json` and v2.1's `episodes_stats.jsonl` fall through to 5:
        // after the data they describe, before `info.json`, the one file that counts episodes.)
        _ if rel.starts_with("meta/phone2act") => 6,
        _ => 5,
    }
}

/// Whether a dataset-relative path is one of the dataset's files (not a phone2act working file: staging,
/// journals, the upload directory, the station id, temp files).
pub fn is_dataset_file(rel: &str) -> bool {
    !rel.split('/').any(|s| s.starts_with('.'))
}

/// Whether the file, once written, is never replaced (data, videos, v3.0 episode metadata, v2.1's
/// per-episode files): two datasets with the same such path must have the same content there.
pub fn is_immutable(rel: &str) -> bool {
    rel.starts_with("data/") || rel.starts_with("videos/") || rel.starts_with("meta/episodes/")
}

/// Sorts paths into upload order.
pub fn sort_for_upload(rels: &mut [String]) {
    rels.sort_by(|a, b| rank(a).cmp(&rank(b)).then_with(|| a.cmp(b)));
}

/// Every dataset file under `root` (relative, `/`-separated), in upload order.
pub fn dataset_files(root: &Path) -> std::io::Result<Vec<String>> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_owned()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir)? {
            let e = e?;
            let p = e.path();
            let rel = p
                .strip_prefix(root)
                .unwrap_or(&p)
                .to_string_lossy()
                .replace('\\', "/");
            if !is_dataset_file(&rel) {
                continue;
            }
            if e.file_type()?.is_dir() {
                stack.push(p);
            } else {
                out.push(rel);
            }
        }
    }
    sort_for_upload(&mut out);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn info_json_goes_last_and_data_before_the_lines_that_count_it() {
        let mut v: Vec<String> = [
            "meta/info.json",
            "meta/stats.json",
            "meta/modality.json",
            "meta/episodes.jsonl",
            "data/chunk-000/episode_000000.parquet",
            "meta/phone2act_provenance.json",
            "meta/phone2act/events/episode_000000.jsonl",
            "meta/episodes/chunk-000/file-000.parquet",
            "videos/observation.images.front/chunk-000/file-000.mp4",
            "meta/tasks.parquet",
        ]
        .map(String::from)
        .to_vec();
        sort_for_upload(&mut v);
        assert_eq!(
            v,
            [
                "videos/observation.images.front/chunk-000/file-000.mp4",
                "meta/tasks.parquet",
                "meta/episodes/chunk-000/file-000.parquet",
                "data/chunk-000/episode_000000.parquet",
                "meta/episodes.jsonl",
                "meta/modality.json",
                "meta/stats.json",
                "meta/phone2act/events/episode_000000.jsonl",
                "meta/phone2act_provenance.json",
                "meta/info.json",
            ]
        );
        assert!(!is_dataset_file(".phone2act-upload/journal.json"));
        assert!(!is_dataset_file("meta/.info.json.tmp"));
    }
}

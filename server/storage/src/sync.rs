//! One-shot `push` (a local dataset to a URL, appending the episodes the remote copy lacks) and `pull` (a
//! remote dataset to a local directory, consistent even while a station is still uploading into it).

use crate::order::{self, is_immutable};
use crate::remote::{RateLimiter, Remote};
use crate::{StorageError, sha256_file};
use futures_util::StreamExt;
use serde_json::Value;
use std::collections::HashMap;
use std::path::Path;

/// What a push did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PushReport {
    pub episodes_before: u64,
    pub episodes_after: u64,
    pub objects_put: u64,
    pub objects_skipped: u64,
    pub bytes_put: u64,
}

fn read_info(root: &Path) -> Result<Value, StorageError> {
    let path = root.join("meta/info.json");
    let bytes = std::fs::read(&path).map_err(|e| StorageError::io(&path, e))?;
    serde_json::from_slice(&bytes).map_err(|e| StorageError::Corrupt(format!("{}: {e}", path.display())))
}

/// The first key in which two `info.json` disagree on what the dataset *is* (not on how many episodes).
fn incompatibility(local: &Value, remote: &Value) -> Option<String> {
    for key in ["codebase_version", "fps", "robot_type", "chunks_size"] {
        if local[key] != remote[key] {
            return Some(format!(
                "{key} differs: local {} vs remote {}",
                local[key], remote[key]
            ));
        }
    }
    let (lf, rf) = (&local["features"], &remote["features"]);
    if lf != rf {
        let names = |v: &Value| -> Vec<String> {
            v.as_object()
                .map(|m| m.keys().cloned().collect())
                .unwrap_or_default()
        };
        let (ln, rn) = (names(lf), names(rf));
        if ln != rn {
            return Some(format!("features differ: local {ln:?} vs remote {rn:?}"));
        }
        for k in ln {
            if lf[&k] != rf[&k] {
                return Some(format!(
                    "feature {k} differs: local {} vs remote {}",
                    lf[&k], rf[&k]
                ));
            }
        }
    }
    None
}

/// Objects a push has in flight at once: enough to hide a request's round trip (HEAD, PUT, multipart
/// completion) on a loopback or LAN store, and a memory bound of this many 8 MiB parts.
pub const PUSH_CONCURRENCY: usize = 4;

/// Pushes the dataset at `root` to `remote`. A remote copy that already exists must be the same dataset
/// (format, fps, robot type, features) with no episode the local one lacks, and every file both have that
/// never changes once written (data, videos, episode metadata) must be byte-identical; otherwise nothing
/// is written. Then the missing files go up, skipping every object already there intact: first the files
/// that are never replaced ([`is_immutable`]), [`PUSH_CONCURRENCY`] at a time (no reader reaches them
/// before a later `info.json` names their episodes), then the replaceable metadata one at a time in
/// commit order, `info.json` last, so a remote reader sees the old dataset or the new one, never a mix.
pub async fn push(
    root: &Path,
    remote: &Remote,
    max_bytes_per_s: Option<u64>,
) -> Result<PushReport, StorageError> {
    let local_info = read_info(root)?;
    let local_episodes = local_info["total_episodes"].as_u64().unwrap_or(0);
    let files = order::dataset_files(root).map_err(|e| StorageError::io(root, e))?;
    let mismatch = |detail: String| StorageError::Mismatch {
        local: root.to_owned(),
        url: remote.url().to_string(),
        detail,
    };
    let mut report = PushReport::default();
    let mut hashes = Vec::with_capacity(files.len());
    for rel in &files {
        hashes.push(sha256_file(&root.join(rel))?);
    }
    // One listing answers "absent" and "different size" for every object, so only objects present with the
    // same size cost a HEAD (their sha256 is in the object's metadata).
    let listed: HashMap<String, u64> = remote.list().await?.into_iter().collect();
    let same_size = |rel: &str, size: u64| listed.get(rel) == Some(&size);
    // A station with `retain_local = false` keeps only metadata for uploaded episodes: pushing that elsewhere
    // would publish an info.json counting episodes whose rows and videos the destination never gets.
    let removed = crate::journal::removed_locally(root)?;
    if let Some(gone) = removed.iter().find(|r| !listed.contains_key(r.as_str())) {
        return Err(mismatch(format!(
            "{} data and video files of this dataset (first {gone}) were removed locally after their upload \
             (storage.retain_local = false) and are not at this URL: pull the complete dataset from its \
             storage and push that copy",
            removed.len()
        )));
    }
    if let Some(bytes) = remote.get_bytes("meta/info.json").await? {
        let remote_info: Value = serde_json::from_slice(&bytes)
            .map_err(|e| mismatch(format!("the remote meta/info.json is not JSON: {e}")))?;
        if let Some(d) = incompatibility(&local_info, &remote_info) {
            return Err(mismatch(d));
        }
        let remote_episodes = remote_info["total_episodes"].as_u64().unwrap_or(0);
        report.episodes_before = remote_episodes;
        if remote_episodes > local_episodes {
            return Err(mismatch(format!(
                "the remote copy has {remote_episodes} episodes, the local one {local_episodes}: pull it first"
            )));
        }
        for (rel, (size, sha)) in files.iter().zip(&hashes) {
            if !is_immutable(rel) || !listed.contains_key(rel) {
                continue;
            }
            if !(same_size(rel, *size) && remote.intact(rel, *size, sha).await?) {
                return Err(mismatch(format!(
                    "{rel} exists on both sides with different content (an episode recorded twice \
                     under the same index?)"
                )));
            }
        }
    }
    let limiter = RateLimiter::new(max_bytes_per_s);
    let (bulk, ordered): (Vec<_>, Vec<_>) = files.iter().zip(&hashes).partition(|(rel, _)| is_immutable(rel));
    let mut count = |sent: Option<u64>| match sent {
        Some(size) => {
            report.objects_put += 1;
            report.bytes_put += size;
        }
        None => report.objects_skipped += 1,
    };
    let mut bulk = futures_util::stream::iter(bulk)
        .map(|(rel, (size, sha))| send(remote, root, &limiter, rel, *size, sha, same_size(rel, *size)))
        .buffer_unordered(PUSH_CONCURRENCY);
    while let Some(sent) = bulk.next().await {
        count(sent?);
    }
    drop(bulk);
    for (rel, (size, sha)) in ordered {
        count(send(remote, root, &limiter, rel, *size, sha, same_size(rel, *size)).await?);
    }
    report.episodes_after = local_episodes;
    Ok(report)
}

/// Sends one file unless it is remote and intact (`listed_same_size`: the listing has it at this size, so a
/// HEAD decides). The size sent, or `None` when skipped.
async fn send(
    remote: &Remote,
    root: &Path,
    limiter: &RateLimiter,
    rel: &str,
    size: u64,
    sha: &str,
    listed_same_size: bool,
) -> Result<Option<u64>, StorageError> {
    if listed_same_size && remote.intact(rel, size, sha).await? {
        return Ok(None);
    }
    remote.put_file(rel, &root.join(rel), sha, limiter).await?;
    Ok(Some(size))
}

/// Downloads the remote dataset into `dest` (created if needed). `info.json` is read first and again at
/// the end; if a station committed in between, the pull repeats (fetching only what changed), so the copy
/// is one committed state, never a mix. `info.json` is written last locally, like the recorder's commit.
pub async fn pull(remote: &Remote, dest: &Path) -> Result<u64, StorageError> {
    for _attempt in 0..5 {
        let Some(info) = remote.get_bytes("meta/info.json").await? else {
            return Err(StorageError::Remote {
                url: remote.url().to_string(),
                detail: "no meta/info.json: not a dataset (or nothing committed yet)".into(),
            });
        };
        let listed = remote.list().await?;
        for (rel, size) in &listed {
            if rel == "meta/info.json" || !order::is_dataset_file(rel) {
                continue;
            }
            let path = dest.join(rel);
            let same = std::fs::metadata(&path).is_ok_and(|m| m.len() == *size)
                && match remote.head(rel).await?.and_then(|o| o.sha256) {
                    Some(s) => sha256_file(&path)?.1 == s,
                    None => false,
                };
            if !same {
                remote.get_to_file(rel, &path).await?;
            }
        }
        if remote.get_bytes("meta/info.json").await?.as_deref() == Some(&info[..]) {
            crate::journal::write_atomic(&dest.join("meta/info.json"), &info)?;
            let v: Value = serde_json::from_slice(&info).unwrap_or(Value::Null);
            return Ok(v["total_episodes"].as_u64().unwrap_or(0));
        }
        tracing::info!("pull: the remote dataset changed while it was read; reading it again");
    }
    Err(StorageError::Remote {
        url: remote.url().to_string(),
        detail: "the remote dataset kept changing during 5 pulls".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn incompatibility_names_the_first_difference() {
        let a = json!({"codebase_version": "v3.0", "fps": 30, "robot_type": "so101", "features": {"action": {"shape": [7]}}});
        let mut b = a.clone();
        assert_eq!(incompatibility(&a, &b), None);
        b["fps"] = json!(15);
        assert!(incompatibility(&a, &b).unwrap().starts_with("fps differs"));
        let mut c = a.clone();
        c["features"]["action"]["shape"] = json!([6]);
        assert!(
            incompatibility(&a, &c)
                .unwrap()
                .contains("feature action differs")
        );
    }
}

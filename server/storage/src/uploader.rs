//! The background uploader: one thread with its own single-threaded tokio runtime, one request at a time,
//! paced by the bandwidth cap, so it competes with recording and control for neither cores nor memory
//! (at most one [`PART_BYTES`](crate::remote::PART_BYTES) buffer in flight). The recorder's commit hook
//! calls [`Uploader::committed`] (hard links and a journal write: milliseconds); everything else happens
//! here, batch after batch in commit order, retrying with exponential backoff until the storage answers.

use crate::journal::{Batch, UploadJournal, note_removed};
use crate::remote::{RateLimiter, Remote};
use crate::{StorageError, order, sha256_file};
use parking_lot::Mutex;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::sync::Notify;

/// First retry delay after an error; doubled up to [`MAX_BACKOFF`].
const FIRST_BACKOFF: Duration = Duration::from_millis(500);
const MAX_BACKOFF: Duration = Duration::from_secs(30);

/// One episode's upload state.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum EpisodeUpload {
    /// Committed, waiting behind earlier episodes.
    Pending,
    Uploading,
    Uploaded,
    /// The last attempt failed (it is retried); the reason as the operator should read it.
    Failed(String),
}

impl EpisodeUpload {
    pub fn as_str(&self) -> &'static str {
        match self {
            EpisodeUpload::Pending => "pending",
            EpisodeUpload::Uploading => "uploading",
            EpisodeUpload::Uploaded => "uploaded",
            EpisodeUpload::Failed(_) => "failed",
        }
    }
}

/// The uploader as a whole.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct UploadStatus {
    /// `s3://bucket/prefix/<station_id>`.
    pub url: String,
    pub station_id: String,
    pub episodes_uploaded: u64,
    pub episodes_pending: u64,
    /// The error the current batch last failed with (cleared when it succeeds).
    pub last_error: Option<String>,
    pub objects_put: u64,
    pub objects_skipped: u64,
    pub bytes_put: u64,
    /// Local data and video files removed after their upload (`retain_local = false`), and their bytes.
    pub local_files_removed: u64,
    pub local_bytes_freed: u64,
}

struct State {
    journal: UploadJournal,
    last_error: Option<String>,
    objects_put: u64,
    objects_skipped: u64,
    bytes_put: u64,
    local_files_removed: u64,
    local_bytes_freed: u64,
}

struct Shared {
    root: PathBuf,
    retain_local: bool,
    url: String,
    station_id: String,
    state: Mutex<State>,
    wake: Notify,
    stop: AtomicBool,
}

/// Uploads a dataset's committed episodes. Dropping it stops the thread between two requests (or aborts
/// the one in flight); the journal keeps what is left for the next start.
pub struct Uploader {
    shared: Arc<Shared>,
    thread: Mutex<Option<JoinHandle<()>>>,
}

impl Uploader {
    /// Starts uploading the dataset at `root` to `remote`. Call it after the recorder has opened the
    /// dataset and before any episode can be committed: episodes committed while storage was off (or
    /// before a crash, between a commit and its snapshot) are caught up from the files as they are now.
    /// With `retain_local` false, each uploaded episode's data and video files are then removed locally
    /// (see [`prune_batch`]).
    pub fn start(
        root: &Path,
        remote: Remote,
        station_id: &str,
        max_upload_bytes_per_s: Option<u64>,
        retain_local: bool,
    ) -> Result<Self, StorageError> {
        let mut journal = UploadJournal::load(root)?;
        journal.remove_orphans(root);
        let committed = committed_episodes(root)?;
        let covered = journal.covered();
        if committed > covered {
            let files = order::dataset_files(root).map_err(|e| StorageError::io(root, e))?;
            journal.snapshot(root, &files, covered, committed)?;
            tracing::info!(
                episodes = committed - covered,
                files = files.len(),
                "storage: catching up on episodes not uploaded yet"
            );
        }
        journal.save(root)?;
        let shared = Arc::new(Shared {
            root: root.to_owned(),
            retain_local,
            url: remote.url().to_string(),
            station_id: station_id.to_owned(),
            state: Mutex::new(State {
                journal,
                last_error: None,
                objects_put: 0,
                objects_skipped: 0,
                bytes_put: 0,
                local_files_removed: 0,
                local_bytes_freed: 0,
            }),
            wake: Notify::new(),
            stop: AtomicBool::new(false),
        });
        let s2 = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("storage-upload".into())
            .spawn(move || run(&s2, &remote, max_upload_bytes_per_s))
            .map_err(|e| StorageError::Start(e.to_string()))?;
        Ok(Uploader {
            shared,
            thread: Mutex::new(Some(thread)),
        })
    }

    /// The recorder committed `episode`, making `files` (dataset-relative, in the order the commit renamed
    /// them) visible. Runs on the recorder's thread under its dataset lock: hard links and one journal
    /// write. On error the episode is left to the catch-up of the next start (logged, never fatal).
    pub fn committed(&self, episode: u64, files: &[String]) {
        let mut st = self.shared.state.lock();
        let first = st.journal.covered().min(episode);
        let rels: Vec<String> = files
            .iter()
            .filter(|r| order::is_dataset_file(r))
            .cloned()
            .collect();
        let r = st
            .journal
            .snapshot(&self.shared.root, &rels, first, episode + 1)
            .map(|_| ())
            .and_then(|()| st.journal.save(&self.shared.root));
        if let Err(e) = r {
            tracing::error!(episode, error = %e, "storage: cannot queue the episode for upload");
            st.last_error = Some(format!("cannot queue episode {episode}: {e}"));
            // Drop the batch again so the journal in memory matches the one on disk.
            st.journal.batches.retain(|b| b.end_episode != episode + 1);
            return;
        }
        drop(st);
        self.shared.wake.notify_one();
    }

    pub fn status(&self) -> UploadStatus {
        let st = self.shared.state.lock();
        let j = &st.journal;
        UploadStatus {
            url: self.shared.url.clone(),
            station_id: self.shared.station_id.clone(),
            episodes_uploaded: j.episodes_uploaded,
            episodes_pending: j.covered() - j.episodes_uploaded,
            last_error: st.last_error.clone(),
            objects_put: st.objects_put,
            objects_skipped: st.objects_skipped,
            bytes_put: st.bytes_put,
            local_files_removed: st.local_files_removed,
            local_bytes_freed: st.local_bytes_freed,
        }
    }

    /// The upload state of a committed episode.
    pub fn episode(&self, index: u64) -> EpisodeUpload {
        let st = self.shared.state.lock();
        let j = &st.journal;
        if index < j.episodes_uploaded {
            return EpisodeUpload::Uploaded;
        }
        match j.batches.first() {
            Some(b) if index < b.end_episode => match &st.last_error {
                Some(e) => EpisodeUpload::Failed(e.clone()),
                None => EpisodeUpload::Uploading,
            },
            _ => EpisodeUpload::Pending,
        }
    }

    /// Stops the thread (the journal keeps what is left).
    pub fn shutdown(&self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        self.shared.wake.notify_one();
        let thread = self.thread.lock().take();
        if let Some(h) = thread {
            let _ = h.join();
        }
    }
}

impl Drop for Uploader {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// `total_episodes` of the committed `meta/info.json` (0 when there is none yet).
pub fn committed_episodes(root: &Path) -> Result<u64, StorageError> {
    let path = root.join("meta/info.json");
    match std::fs::read(&path) {
        Ok(b) => {
            let v: serde_json::Value = serde_json::from_slice(&b)
                .map_err(|e| StorageError::Corrupt(format!("{}: {e}", path.display())))?;
            Ok(v["total_episodes"].as_u64().unwrap_or(0))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(0),
        Err(e) => Err(StorageError::io(path, e)),
    }
}

/// Lowers the calling thread's CPU priority (nice +10) so hashing and TLS never compete with the control
/// path or the encoders on a busy machine. Linux only; a failure just leaves the default priority.
#[allow(unsafe_code)]
fn lower_thread_priority() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: gettid and setpriority take and return plain integers; on Linux PRIO_PROCESS with a thread id
    // changes that thread only.
    unsafe {
        let tid = libc::gettid();
        if libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 10) != 0 {
            tracing::debug!("storage: could not lower the upload thread's priority");
        }
    }
}

fn run(shared: &Arc<Shared>, remote: &Remote, rate: Option<u64>) {
    lower_thread_priority();
    let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            shared.state.lock().last_error = Some(format!("cannot start the upload runtime: {e}"));
            return;
        }
    };
    rt.block_on(async {
        let limiter = RateLimiter::new(rate);
        let mut backoff = FIRST_BACKOFF;
        while !shared.stop.load(Ordering::Relaxed) {
            let batch = shared.state.lock().journal.batches.first().cloned();
            let Some(batch) = batch else {
                shared.wake.notified().await;
                continue;
            };
            let r = tokio::select! {
                r = upload_batch(shared, remote, &batch, &limiter) => r,
                () = stopped(shared) => return,
            };
            match r {
                Ok(()) => {
                    backoff = FIRST_BACKOFF;
                    if !shared.retain_local {
                        tokio::select! {
                            () = prune_batch(shared, remote) => {}
                            () = stopped(shared) => return,
                        }
                    }
                    finish_batch(shared, &batch);
                }
                Err(e) => {
                    let msg = e.to_string();
                    tracing::warn!(batch = batch.id, error = %msg, retry_in_s = backoff.as_secs_f64(), "storage: upload failed");
                    {
                        let mut st = shared.state.lock();
                        st.last_error = Some(msg);
                        // Re-check the whole batch next time: the storage may have lost what it acknowledged.
                        if let Some(b) = st.journal.batches.first_mut() {
                            b.files.iter_mut().for_each(|f| f.done = false);
                        }
                    }
                    tokio::select! {
                        () = tokio::time::sleep(backoff) => {}
                        () = stopped(shared) => return,
                    }
                    backoff = (backoff * 2).min(MAX_BACKOFF);
                }
            }
        }
    });
}

/// Resolves once the uploader is asked to stop.
async fn stopped(shared: &Shared) {
    while !shared.stop.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn upload_batch(
    shared: &Shared,
    remote: &Remote,
    batch: &Batch,
    limiter: &RateLimiter,
) -> Result<(), StorageError> {
    let dir = UploadJournal::dir(&shared.root);
    for (i, f) in batch.files.iter().enumerate() {
        let done = shared.state.lock().journal.batches[0].files[i].done;
        if done {
            continue;
        }
        let local = dir.join(&f.link);
        let sha = match &f.sha256 {
            Some(s) => s.clone(),
            None => sha256_file(&local)?.1,
        };
        let skipped = remote.intact(&f.rel, f.size_bytes, &sha).await?;
        if !skipped {
            remote.put_file(&f.rel, &local, &sha, limiter).await?;
        }
        let mut st = shared.state.lock();
        if skipped {
            st.objects_skipped += 1;
        } else {
            st.objects_put += 1;
            st.bytes_put += f.size_bytes;
        }
        let bf = &mut st.journal.batches[0].files[i];
        bf.sha256 = Some(sha);
        bf.done = true;
        st.journal.save(&shared.root)?;
    }
    Ok(())
}

/// Whether a committed file is bulk an uploaded episode can do without locally: its rows and its videos.
/// Metadata stays, so the recorder keeps appending to the dataset and `episode list` keeps answering.
fn removable(rel: &str) -> bool {
    rel.starts_with("data/") || rel.starts_with("videos/")
}

/// `retain_local = false`: removes the uploaded batch's data and video files from the dataset. A file goes
/// only if its bytes are still those the batch uploaded (same size and sha256 as the batch's snapshot) and
/// the storage still holds them intact (asked again now, not taken from the upload), so nothing leaves the
/// disk that is not remote. Any doubt (an error, a changed file, a missing object) keeps the file: removal
/// is an optimisation, never a condition of the upload. The batch's own hard links go with the batch.
async fn prune_batch(shared: &Shared, remote: &Remote) {
    let files = match shared.state.lock().journal.batches.first() {
        Some(b) => b.files.clone(),
        None => return,
    };
    let mut checked = Vec::new();
    for f in files.iter().filter(|f| removable(&f.rel)) {
        let Some(sha) = &f.sha256 else { continue };
        let local = shared.root.join(&f.rel);
        let same = match sha256_file(&local) {
            Ok((size, local_sha)) => size == f.size_bytes && &local_sha == sha,
            Err(_) => false,
        };
        if !same {
            tracing::warn!(file = %f.rel, "storage: kept locally: the file is not the one uploaded");
            continue;
        }
        match remote.intact(&f.rel, f.size_bytes, sha).await {
            Ok(true) => checked.push((f.rel.clone(), f.size_bytes)),
            Ok(false) => {
                tracing::warn!(file = %f.rel, "storage: kept locally: the storage does not hold it intact");
            }
            Err(e) => {
                tracing::warn!(file = %f.rel, error = %e, "storage: kept locally: cannot check the stored copy");
            }
        }
    }
    if checked.is_empty() {
        return;
    }
    let rels: Vec<String> = checked.iter().map(|(r, _)| r.clone()).collect();
    if let Err(e) = note_removed(&shared.root, &rels) {
        tracing::warn!(error = %e, "storage: kept the uploaded files locally: cannot record their removal");
        return;
    }
    for (rel, size_bytes) in checked {
        let local = shared.root.join(&rel);
        match std::fs::remove_file(&local) {
            Ok(()) => {
                let mut st = shared.state.lock();
                st.local_files_removed += 1;
                st.local_bytes_freed += size_bytes;
            }
            Err(e) => tracing::warn!(file = %rel, error = %e, "storage: cannot remove the uploaded file"),
        }
    }
}

fn finish_batch(shared: &Shared, batch: &Batch) {
    let mut st = shared.state.lock();
    st.last_error = None;
    st.journal.batches.remove(0);
    st.journal.episodes_uploaded = st.journal.episodes_uploaded.max(batch.end_episode);
    if let Err(e) = st.journal.save(&shared.root) {
        st.last_error = Some(e.to_string());
        return;
    }
    drop(st);
    let dir = UploadJournal::dir(&shared.root).join(format!("b{}", batch.id));
    let _ = std::fs::remove_dir_all(dir);
    tracing::info!(
        episodes = ?(batch.first_episode..batch.end_episode),
        retain_local = shared.retain_local,
        "storage: episodes uploaded"
    );
}

//! Episodes flow to S3-compatible storage (issue 26), against a real S3 server on loopback (moto, see
//! `phone2act_tests::s3`): an episode recorded with `[storage]` appears remotely complete; wrong
//! credentials and a missing bucket are clear errors that leave everything local and complete once fixed;
//! the storage server killed mid-upload and restarted finishes the upload with nothing half-visible; a v2.1
//! station's remote `episodes.jsonl` never lists an episode before its files.
//!
//! Timing: every wait below is a liveness bound (generous: a minute or more, for work that takes about a
//! second on an idle machine), never a performance assertion, so a loaded two-core machine slows these tests
//! down without failing them.

use phone2act_sdk::proto as v1;
use phone2act_storage::remote::RemoteOptions;
use phone2act_storage::{Remote, StorageConfig, StorageUrl};
use phone2act_tests::s3::{Moto, moto_server_path};
use phone2act_tests::{TestServer, default_config};
use std::path::Path;
use std::time::{Duration, Instant};

const BUCKET: &str = "fleet";

fn storage(moto: &Moto, creds: &Path, station: &str) -> StorageConfig {
    let mut s = StorageConfig::new(format!("s3://{BUCKET}/lab"));
    s.endpoint = Some(moto.endpoint());
    s.credentials_file = Some(creds.to_owned());
    s.station_id = Some(station.to_owned());
    s
}

fn remote(moto: &Moto, station: &str) -> Remote {
    let url = StorageUrl::parse(&format!("s3://{BUCKET}/lab/{station}")).unwrap();
    let creds = phone2act_storage::Credentials::resolve(None, &|k| match k {
        "AWS_ACCESS_KEY_ID" => Some(moto.key_id.clone()),
        "AWS_SECRET_ACCESS_KEY" => Some(moto.secret.clone()),
        _ => None,
    })
    .unwrap();
    Remote::new(
        &url,
        &RemoteOptions {
            endpoint: Some(moto.endpoint()),
            credentials: creds,
            max_retries: Some(0),
            request_timeout: Some(Duration::from_secs(10)),
            ..RemoteOptions::default()
        },
    )
    .unwrap()
}

async fn record(client: &phone2act_sdk::Client, task: &str, operator: &str, ms: u64) -> u64 {
    let mut episodes = client.episodes();
    episodes.start_by(task, operator).await.unwrap();
    tokio::time::sleep(Duration::from_millis(ms)).await;
    episodes.stop().await.unwrap().episode.unwrap().episode_index
}

/// Polls `Episodes.List` until `done` holds for it (or panics after `limit`, showing the last answer).
async fn wait_list(
    client: &phone2act_sdk::Client,
    limit: Duration,
    what: &str,
    mut done: impl FnMut(&v1::ListEpisodesResponse) -> bool,
) -> v1::ListEpisodesResponse {
    let deadline = Instant::now() + limit;
    loop {
        let list = client.episodes().list().await.unwrap();
        if done(&list) {
            return list;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: not within {limit:?}: {list:#?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn all_uploaded(list: &v1::ListEpisodesResponse, n: usize) -> bool {
    list.episodes.len() == n
        && list
            .episodes
            .iter()
            .all(|e| e.upload_state() == v1::UploadState::Uploaded)
}

/// A reader's view: when `meta/info.json` is remote, every file of the episodes it counts is remote too
/// (phone2act's v3.0 layout: one data, one episode-metadata and one video file per camera per episode).
async fn remote_is_consistent(remote: &Remote, cameras: usize) -> Result<(), String> {
    let listed = remote.list().await.map_err(|e| e.to_string())?;
    let Some(info) = remote
        .get_bytes("meta/info.json")
        .await
        .map_err(|e| e.to_string())?
    else {
        return Ok(());
    };
    let info: serde_json::Value = serde_json::from_slice(&info).unwrap();
    let n = info["total_episodes"].as_u64().unwrap() as usize;
    let count = |prefix: &str| listed.iter().filter(|(k, _)| k.starts_with(prefix)).count();
    let (data, meta, videos) = (count("data/"), count("meta/episodes/"), count("videos/"));
    if data < n || meta < n || videos < n * cameras {
        return Err(format!(
            "info.json counts {n} episodes but only {data} data, {meta} episode-metadata and {videos} video files are remote"
        ));
    }
    Ok(())
}

async fn pull_and_verify(remote: &Remote, dest: &Path, episodes: u64) {
    let n = phone2act_storage::pull(remote, dest).await.unwrap();
    assert_eq!(n, episodes);
    let report = phone2act_dataset::verify::verify(dest);
    assert!(report.ok(), "{:?}", report.problems);
    assert_eq!(report.episodes, episodes);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_episode_recorded_with_storage_appears_remotely_complete() {
    let Some(bin) = moto_server_path("an_episode_recorded_with_storage_appears_remotely_complete") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    let creds = moto.credentials_file(dir.path(), None);
    let root = dir.path().join("ds");
    let mut config = default_config(&root);
    config.storage = Some(storage(&moto, &creds, "st-a"));
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();

    assert_eq!(record(&client, "pick the cube", "alice", 800).await, 0);
    assert_eq!(record(&client, "place the cube", "bob", 600).await, 1);
    let list = wait_list(&client, Duration::from_mins(2), "both episodes uploaded", |l| {
        all_uploaded(l, 2)
    })
    .await;
    let st = list.storage.as_ref().expect("storage status");
    assert_eq!(st.url, format!("s3://{BUCKET}/lab/st-a"));
    assert_eq!((st.episodes_uploaded, st.episodes_pending), (2, 0));
    assert!(st.last_error.is_empty(), "{}", st.last_error);
    assert_eq!(list.episodes[0].operator, "alice");
    assert_eq!(list.episodes[1].station_id, "st-a");

    // Only dataset files are remote (no journal, staging or station-id file), all under the station.
    let keys = moto.list(BUCKET, "");
    assert!(!keys.is_empty());
    for (k, _) in &keys {
        assert!(k.starts_with("lab/st-a/") && !k.contains("/."), "{k}");
    }
    let remote = remote(&moto, "st-a");
    remote_is_consistent(&remote, 1).await.unwrap();
    let back = dir.path().join("back");
    pull_and_verify(&remote, &back, 2).await;
    // Provenance names station, operator and version, and never the secret.
    let prov = std::fs::read_to_string(back.join("meta/phone2act_provenance.json")).unwrap();
    let p: serde_json::Value = serde_json::from_str(&prov).unwrap();
    assert_eq!(p["episodes"][0]["operator"], "alice");
    assert_eq!(p["episodes"][1]["operator"], "bob");
    assert_eq!(p["episodes"][0]["station_id"], "st-a");
    assert_eq!(p["episodes"][0]["software_version"], env!("CARGO_PKG_VERSION"));
    assert!(!prov.contains(&moto.secret));
    // The remote copy is the local one, file for file.
    for rel in phone2act_storage::order::dataset_files(&root).unwrap() {
        assert_eq!(
            std::fs::read(root.join(&rel)).unwrap(),
            std::fs::read(back.join(&rel)).unwrap(),
            "{rel}"
        );
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_credentials_and_a_missing_bucket_fail_clearly_and_complete_once_fixed() {
    let test = "wrong_credentials_and_a_missing_bucket_fail_clearly_and_complete_once_fixed";
    let Some(bin) = moto_server_path(test) else { return };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    let root = dir.path().join("ds");

    // Wrong secret: the episode is saved locally, its upload fails with a clear reason, retried.
    let wrong = moto.credentials_file(dir.path(), Some("not-the-secret"));
    let mut config = default_config(&root);
    config.storage = Some(storage(&moto, &wrong, "st-b"));
    let server = TestServer::start(config.clone()).await.unwrap();
    let client = server.client().await.unwrap();
    record(&client, "pick", "carol", 500).await;
    let list = wait_list(&client, Duration::from_mins(1), "a failed upload", |l| {
        l.episodes
            .first()
            .is_some_and(|e| e.upload_state() == v1::UploadState::Failed)
    })
    .await;
    let err = &list.episodes[0].upload_error;
    assert!(
        err.contains("access denied") && err.contains("AWS_SECRET_ACCESS_KEY"),
        "{err}"
    );
    assert!(!err.contains("not-the-secret"), "{err}");
    assert!(list.storage.unwrap().last_error.contains("access denied"));
    server.shutdown().await.unwrap();
    assert!(phone2act_dataset::verify::verify(&root).ok());

    // Right key, missing bucket: the same episode (from the journal) now fails on the bucket.
    let right = moto.credentials_file(dir.path(), None);
    config.storage = Some(storage(&moto, &right, "st-b"));
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let list = wait_list(&client, Duration::from_mins(1), "a missing-bucket error", |l| {
        l.episodes
            .first()
            .is_some_and(|e| e.upload_error.contains("bucket does not exist"))
    })
    .await;
    assert_eq!(list.episodes[0].upload_state(), v1::UploadState::Failed);
    record(&client, "place", "carol", 500).await;

    // Create it: both episodes go up without anyone touching the server (backoff is capped at 30 s).
    moto.create_bucket(BUCKET);
    wait_list(&client, Duration::from_mins(2), "uploads after the fix", |l| {
        all_uploaded(l, 2)
    })
    .await;
    let remote = remote(&moto, "st-b");
    pull_and_verify(&remote, &dir.path().join("back"), 2).await;
    server.shutdown().await.unwrap();
}

/// The data and video files under `root`, dataset-relative, sorted.
fn bulk_files(root: &Path) -> Vec<String> {
    phone2act_storage::order::dataset_files(root)
        .unwrap()
        .into_iter()
        .filter(|r| r.starts_with("data/") || r.starts_with("videos/"))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retain_local_false_removes_an_episodes_files_only_once_they_are_stored_and_recording_goes_on() {
    let test = "retain_local_false_removes_an_episodes_files_only_once_they_are_stored_and_recording_goes_on";
    let Some(bin) = moto_server_path(test) else { return };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    let creds = moto.credentials_file(dir.path(), None);
    let root = dir.path().join("ds");
    let mut config = default_config(&root);
    let mut s = storage(&moto, &creds, "st-r");
    s.retain_local = false;
    config.storage = Some(s);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();

    // No bucket yet: the upload fails, and the episode's files stay.
    assert_eq!(record(&client, "pick", "alice", 600).await, 0);
    wait_list(&client, Duration::from_mins(1), "a failed upload", |l| {
        l.episodes
            .first()
            .is_some_and(|e| e.upload_state() == v1::UploadState::Failed)
    })
    .await;
    let first = bulk_files(&root);
    assert_eq!(first.len(), 2, "one data file and one video: {first:?}");

    // Stored: an episode's files leave the disk before it is reported uploaded; its metadata stays.
    moto.create_bucket(BUCKET);
    assert_eq!(record(&client, "place", "bob", 600).await, 1);
    wait_list(&client, Duration::from_mins(2), "uploads after the fix", |l| {
        all_uploaded(l, 2)
    })
    .await;
    assert_eq!(bulk_files(&root), Vec::<String>::new());
    assert!(root.join("meta/episodes/chunk-000/file-001.parquet").exists());
    let removed = phone2act_storage::removed_locally(&root).unwrap();
    assert_eq!(removed.len(), 4, "{removed:?}");

    // Recording goes on into the same dataset, with new file indices (never one that is in storage).
    assert_eq!(record(&client, "pick", "carol", 600).await, 2);
    wait_list(&client, Duration::from_mins(2), "the third upload", |l| {
        all_uploaded(l, 3)
    })
    .await;
    let stored = remote(&moto, "st-r");
    remote_is_consistent(&stored, 1).await.unwrap();
    let data: Vec<String> = stored
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|(k, _)| k)
        .filter(|k| k.starts_with("data/"))
        .collect();
    assert_eq!(
        data,
        [
            "data/chunk-000/file-000.parquet",
            "data/chunk-000/file-001.parquet",
            "data/chunk-000/file-002.parquet"
        ]
    );
    pull_and_verify(&stored, &dir.path().join("back"), 3).await;
    assert_eq!(client.episodes().list().await.unwrap().episodes.len(), 3);

    // The station's copy is not a whole dataset any more: pushing it anywhere else is refused.
    let err = phone2act_storage::push(&root, &remote(&moto, "elsewhere"), None)
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("removed locally after their upload"), "{err}");
    assert!(moto.list(BUCKET, "lab/elsewhere/").is_empty());
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_storage_killed_mid_upload_and_restarted_shows_no_half_episode() {
    let test = "the_storage_killed_mid_upload_and_restarted_shows_no_half_episode";
    let Some(bin) = moto_server_path(test) else { return };
    let dir = tempfile::tempdir().unwrap();
    // Without authentication: a restarted moto forgets its IAM users, not the station.
    let mut moto = Moto::start(&bin, dir.path(), false);
    moto.create_bucket(BUCKET);
    let creds = moto.credentials_file(dir.path(), None);
    let root = dir.path().join("ds");
    let mut config = default_config(&root);
    let mut s = storage(&moto, &creds, "st-c");
    // Slow enough that the episode's files take seconds to go up, so the kill lands between two of them.
    s.max_upload_bytes_per_s = Some(8_000);
    config.storage = Some(s);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    record(&client, "pick", "dan", 1000).await;

    // Kill the storage as soon as the first object of the episode is there.
    let remote = remote(&moto, "st-c");
    let deadline = Instant::now() + Duration::from_mins(2);
    let first = loop {
        let listed = remote.list().await.unwrap_or_default();
        if !listed.is_empty() {
            break listed;
        }
        assert!(Instant::now() < deadline, "no object uploaded in 120 s");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    moto.kill();
    assert!(
        !first.iter().any(|(k, _)| k == "meta/info.json"),
        "the upload finished before the kill (the test did not test anything): {first:?}"
    );
    // A reader of what was remote saw no episode: the files before info.json count none.
    assert!(first.len() < phone2act_storage::order::dataset_files(&root).unwrap().len());
    wait_list(&client, Duration::from_mins(1), "the outage reported", |l| {
        l.episodes
            .first()
            .is_some_and(|e| e.upload_state() == v1::UploadState::Failed)
    })
    .await;

    // Back (empty: moto keeps nothing), bucket re-created: the upload completes from the journal; at
    // every poll a reader sees whole episodes only.
    moto.restart();
    moto.create_bucket(BUCKET);
    let deadline = Instant::now() + Duration::from_mins(3);
    loop {
        remote_is_consistent(&remote, 1).await.unwrap();
        let list = client.episodes().list().await.unwrap();
        if all_uploaded(&list, 1) {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "upload not finished after the restart: {list:#?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    pull_and_verify(&remote, &dir.path().join("back"), 1).await;
    server.shutdown().await.unwrap();
}

/// A station recording into `root` whose storage is `moto` behind a relay that stalls until told otherwise.
async fn station_behind_a_stalled_relay(
    moto: &Moto,
    dir: &Path,
    root: &Path,
    station: &str,
) -> (Relay, TestServer, phone2act_sdk::Client) {
    let target: std::net::SocketAddr = moto
        .endpoint()
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .parse()
        .unwrap();
    let relay = Relay::start(target);
    relay.stall(true);
    let creds = moto.credentials_file(dir, None);
    let mut config = default_config(root);
    let mut s = storage(moto, &creds, station);
    s.endpoint = Some(format!("http://{}", relay.addr));
    // Two seconds a request: a stalled one is abandoned quickly enough for the test, and a loopback request
    // to moto takes milliseconds even on a loaded machine.
    s.request_timeout_s = Some(2.0);
    config.storage = Some(s);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    (relay, server, client)
}

/// A TCP relay in front of the storage that can be told to stop forwarding: connections are still accepted
/// and kept open, but nothing more is read from or written to either side (a hung middlebox or storage).
struct Relay {
    addr: std::net::SocketAddr,
    stalled: std::sync::Arc<std::sync::atomic::AtomicBool>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl Relay {
    fn start(target: std::net::SocketAddr) -> Relay {
        use std::sync::Arc;
        use std::sync::atomic::{AtomicBool, Ordering};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap();
        let stalled = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let (st, sp) = (Arc::clone(&stalled), Arc::clone(&stop));
        std::thread::spawn(move || {
            while !sp.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((client, _)) => {
                        client.set_nonblocking(false).unwrap();
                        let Ok(server) = std::net::TcpStream::connect(target) else {
                            continue;
                        };
                        for (from, to) in [
                            (client.try_clone().unwrap(), server.try_clone().unwrap()),
                            (server, client),
                        ] {
                            let (st, sp) = (Arc::clone(&st), Arc::clone(&sp));
                            std::thread::spawn(move || pump(from, to, &st, &sp));
                        }
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
        });
        Relay { addr, stalled, stop }
    }

    fn stall(&self, on: bool) {
        self.stalled.store(on, std::sync::atomic::Ordering::Relaxed);
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

fn pump(
    mut from: std::net::TcpStream,
    mut to: std::net::TcpStream,
    stalled: &std::sync::atomic::AtomicBool,
    stop: &std::sync::atomic::AtomicBool,
) {
    use std::io::{Read, Write};
    use std::sync::atomic::Ordering;
    from.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    let mut buf = vec![0u8; 64 * 1024];
    while !stop.load(Ordering::Relaxed) {
        if stalled.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(20));
            continue;
        }
        match from.read(&mut buf) {
            Ok(0) => {
                let _ = to.shutdown(std::net::Shutdown::Write);
                return;
            }
            Ok(n) => {
                if to.write_all(&buf[..n]).is_err() {
                    return;
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => return,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_relay_times_uploads_out_recording_goes_on_and_the_upload_completes_once_it_forwards() {
    let test =
        "a_stalled_relay_times_uploads_out_recording_goes_on_and_the_upload_completes_once_it_forwards";
    let Some(bin) = moto_server_path(test) else { return };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    let root = dir.path().join("ds");
    let (relay, server, client) = station_behind_a_stalled_relay(&moto, dir.path(), &root, "st-s").await;

    // Recording is not held up by the stalled storage: both episodes save while nothing can be uploaded.
    assert_eq!(record(&client, "pick", "dana", 600).await, 0);
    let list = wait_list(
        &client,
        Duration::from_mins(2),
        "a timed-out upload reported",
        |l| l.storage.as_ref().is_some_and(|s| !s.last_error.is_empty()),
    )
    .await;
    let err = list.storage.unwrap().last_error.to_lowercase();
    assert!(err.contains("timed out") || err.contains("timeout"), "{err}");
    // What the phone page shows under its recording line.
    let summary = client.episodes().status().await.unwrap().upload_summary;
    assert!(
        summary.starts_with("0 uploaded, 1 pending; failing: ") && summary.to_lowercase().contains("time"),
        "{summary}"
    );
    assert_eq!(record(&client, "place", "dana", 600).await, 1);
    let list = client.episodes().list().await.unwrap();
    assert_eq!(list.episodes.len(), 2);
    assert!(
        list.episodes
            .iter()
            .all(|e| e.upload_state() != v1::UploadState::Uploaded)
    );
    let remote = remote(&moto, "st-s");
    assert!(
        remote.get_bytes("meta/info.json").await.unwrap().is_none(),
        "nothing counted remotely while the relay forwards nothing"
    );

    // The relay forwards again: both episodes go up, whole.
    relay.stall(false);
    wait_list(
        &client,
        Duration::from_mins(3),
        "both uploaded after the stall",
        |l| all_uploaded(l, 2),
    )
    .await;
    assert_eq!(
        client.episodes().status().await.unwrap().upload_summary,
        "2 uploaded, 0 pending"
    );
    remote_is_consistent(&remote, 1).await.unwrap();
    pull_and_verify(&remote, &dir.path().join("back"), 2).await;
    server.shutdown().await.unwrap();
}

struct Unmount(std::path::PathBuf);

impl Drop for Unmount {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

/// Writes `filler` until the file system refuses more (ENOSPC).
fn fill_disk(filler: &Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(filler).unwrap();
    let block = vec![0xa5u8; 64 * 1024];
    while f.write_all(&block).is_ok() {}
    let small = [0xa5u8; 512];
    while f.write_all(&small).is_ok() {}
    let _ = f.sync_all();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_with_uploads_pending_is_a_clear_error_and_loses_no_committed_episode() {
    let test = "a_full_disk_with_uploads_pending_is_a_clear_error_and_loses_no_committed_episode";
    let Some(bin) = moto_server_path(test) else { return };
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("mnt");
    std::fs::create_dir_all(&mnt).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=32m", "tmpfs"])
        .arg(&mnt)
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("SKIPPED: {test}: cannot mount a tmpfs here (needs root) to fill a disk");
        return;
    }
    let _unmount = Unmount(mnt.clone());
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    // The storage is unreachable at first, so the first episode's upload is still pending when the disk fills.
    let root = mnt.join("ds");
    let (relay, server, client) = station_behind_a_stalled_relay(&moto, dir.path(), &root, "st-f").await;
    assert_eq!(record(&client, "pick", "fay", 600).await, 0);

    let filler = mnt.join("filler");
    fill_disk(&filler);
    relay.stall(false);
    // An episode recorded on the full disk is refused with a clear error; the committed one stays.
    let mut episodes = client.episodes();
    let stopped = match episodes.start_by("place", "fay").await {
        Ok(_) => {
            tokio::time::sleep(Duration::from_millis(600)).await;
            episodes.stop().await.map(|_| ())
        }
        Err(e) => Err(e),
    };
    let err = stopped
        .expect_err("an episode saved on a full disk")
        .to_string()
        .to_lowercase();
    assert!(err.contains("disk full") || err.contains("no space"), "{err}");
    let list = client.episodes().list().await.unwrap();
    assert_eq!(list.episodes.len(), 1, "{list:#?}");

    // Space again: the pending upload completes, whole, and the dataset records on.
    std::fs::remove_file(&filler).unwrap();
    assert_eq!(record(&client, "place", "fay", 600).await, 1);
    wait_list(
        &client,
        Duration::from_mins(3),
        "both uploaded after the disk was freed",
        |l| all_uploaded(l, 2),
    )
    .await;
    let remote = remote(&moto, "st-f");
    remote_is_consistent(&remote, 1).await.unwrap();
    pull_and_verify(&remote, &dir.path().join("back"), 2).await;
    server.shutdown().await.unwrap();
}

/// A reader's view of a v2.1 prefix: every episode `meta/episodes.jsonl` lists has its data file and its
/// videos remote, and `meta/info.json` counts no more episodes than that. Returns the episodes listed.
async fn remote_v21_is_consistent(remote: &Remote, camera_keys: &[String]) -> Result<usize, String> {
    let listed = remote.list().await.map_err(|e| e.to_string())?;
    let has = |k: &str| listed.iter().any(|(key, _)| key == k);
    let lines = match remote
        .get_bytes("meta/episodes.jsonl")
        .await
        .map_err(|e| e.to_string())?
    {
        Some(b) => String::from_utf8(b.to_vec()).map_err(|e| e.to_string())?,
        None => String::new(),
    };
    let mut episodes = 0;
    for line in lines.lines().filter(|l| !l.trim().is_empty()) {
        let v: serde_json::Value = serde_json::from_str(line).map_err(|e| format!("{e}: {line}"))?;
        let i = v["episode_index"].as_u64().ok_or("no episode_index")?;
        let data = format!("data/chunk-000/episode_{i:06}.parquet");
        if !has(&data) {
            return Err(format!(
                "episodes.jsonl lists episode {i} but {data} is not remote"
            ));
        }
        for key in camera_keys {
            let video = format!("videos/chunk-000/{key}/episode_{i:06}.mp4");
            if !has(&video) {
                return Err(format!(
                    "episodes.jsonl lists episode {i} but {video} is not remote"
                ));
            }
        }
        episodes += 1;
    }
    if let Some(info) = remote
        .get_bytes("meta/info.json")
        .await
        .map_err(|e| e.to_string())?
    {
        let info: serde_json::Value = serde_json::from_slice(&info).map_err(|e| e.to_string())?;
        let n = info["total_episodes"].as_u64().unwrap_or(0) as usize;
        if n > episodes {
            return Err(format!(
                "info.json counts {n} episodes, episodes.jsonl lists {episodes}"
            ));
        }
    }
    Ok(episodes)
}

/// v2.1 (GR00T) datasets replace `meta/episodes.jsonl` whole at each save: uploaded slowly, the remote copy
/// never lists an episode whose data or video is not there yet, and it ends equal to the local one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_v21_dataset_uploads_so_that_every_listed_episode_is_remote() {
    let test = "a_v21_dataset_uploads_so_that_every_listed_episode_is_remote";
    let Some(bin) = moto_server_path(test) else { return };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    let creds = moto.credentials_file(dir.path(), None);
    let root = dir.path().join("ds");
    let mut config = default_config(&root);
    config.recorder.format = phone2act_server::config::DatasetFormat::V21;
    let mut s = storage(&moto, &creds, "st-v21");
    // Slow enough that each episode's files go up over seconds, so the polls below see it part-way.
    s.max_upload_bytes_per_s = Some(20_000);
    config.storage = Some(s);
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    record(&client, "pick", "eve", 700).await;
    record(&client, "place", "eve", 700).await;
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("meta/info.json")).unwrap()).unwrap();
    let camera_keys: Vec<String> = info["features"]
        .as_object()
        .unwrap()
        .iter()
        .filter(|(_, f)| f["dtype"] == "video")
        .map(|(k, _)| k.clone())
        .collect();
    assert!(!camera_keys.is_empty());

    let remote = remote(&moto, "st-v21");
    let total = phone2act_storage::order::dataset_files(&root).unwrap().len();
    let (mut partial_polls, mut listed_max) = (0, 0);
    let deadline = Instant::now() + Duration::from_mins(3);
    loop {
        let listed = remote_v21_is_consistent(&remote, &camera_keys).await.unwrap();
        listed_max = listed_max.max(listed);
        let objects = remote.list().await.unwrap().len();
        partial_polls += usize::from(objects > 0 && objects < total);
        let list = client.episodes().list().await.unwrap();
        if all_uploaded(&list, 2) {
            break;
        }
        assert!(Instant::now() < deadline, "upload not finished: {list:#?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(remote_v21_is_consistent(&remote, &camera_keys).await.unwrap(), 2);
    assert!(
        partial_polls > 0,
        "no poll saw the upload part-way (the test did not test anything)"
    );
    pull_and_verify(&remote, &dir.path().join("back"), 2).await;
    server.shutdown().await.unwrap();
}

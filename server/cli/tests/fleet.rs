//! The `phone2act` binary and S3-compatible storage (issue 26), against moto on loopback: `kill -9` of a
//! server during an upload, then a restart that finishes it without sending an intact object again; the
//! secret never in `serve --check`, logs or provenance; `dataset push` appending the missing episodes and
//! refusing a different dataset with nothing written; `dataset pull` giving back a dataset that verifies.
//!
//! Timing: every wait is a liveness bound (a minute or more for about a second of work when idle), never a
//! performance assertion, so a loaded two-core machine makes these tests slower, not red.

#[path = "../../../tests/src/s3.rs"]
#[allow(dead_code, unreachable_pub)]
mod s3;

mod common;
use common::Served;
use parking_lot::Mutex;
use phone2act_storage::remote::RemoteOptions;
use phone2act_storage::{Credentials, Remote, StorageUrl};
use s3::{Moto, moto_server_path};
use std::collections::BTreeSet;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_phone2act");
const BUCKET: &str = "fleet";

fn write_config(dir: &Path, root: &Path, storage: &str) -> std::path::PathBuf {
    let path = dir.join(format!(
        "phone2act-{}.toml",
        root.file_name().unwrap().to_string_lossy()
    ));
    let mut text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/default.toml"))
        .unwrap()
        .replace("./datasets/phone2act", &root.display().to_string());
    text.push_str(storage);
    std::fs::write(&path, text).unwrap();
    path
}

fn aws_env(cmd: &mut Command, moto: &Moto) {
    cmd.env("AWS_ACCESS_KEY_ID", &moto.key_id)
        .env("AWS_SECRET_ACCESS_KEY", &moto.secret)
        .env_remove("AWS_PROFILE")
        .env_remove("AWS_SESSION_TOKEN");
}

/// `phone2act serve` with the station's AWS key in its environment; its stderr lines go to `log`.
fn serve(config: &Path, moto: &Moto, log: &Arc<Mutex<Vec<String>>>) -> Served {
    let mut cmd = Command::new(BIN);
    cmd.args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(config)
        .env_remove("SVT_LOG")
        .env("PHONE2ACT_GATEWAY__ENABLED", "false")
        .env("PHONE2ACT_LOG", "info")
        .stderr(Stdio::piped())
        .stdout(Stdio::null());
    aws_env(&mut cmd, moto);
    let child = cmd.spawn().unwrap();
    common::served(child, Arc::clone(log), Duration::from_mins(2))
}

fn run(args: &[&str], moto: &Moto) -> (bool, String, String) {
    let mut cmd = Command::new(BIN);
    cmd.args(args);
    aws_env(&mut cmd, moto);
    let out = cmd.output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn record(server: &Served, moto: &Moto, task: &str, ms: u64) {
    let (ok, _, err) = run(
        &[
            "episode",
            "start",
            "--task",
            task,
            "--operator",
            "erin",
            "--url",
            &server.url,
        ],
        moto,
    );
    assert!(ok, "{err}");
    std::thread::sleep(Duration::from_millis(ms));
    let (ok, _, err) = run(&["episode", "stop", "--url", &server.url], moto);
    assert!(ok, "{err}");
}

fn remote(moto: &Moto, url: &str) -> Remote {
    let creds = Credentials::resolve(None, &|k| match k {
        "AWS_ACCESS_KEY_ID" => Some(moto.key_id.clone()),
        "AWS_SECRET_ACCESS_KEY" => Some(moto.secret.clone()),
        _ => None,
    })
    .unwrap();
    Remote::new(
        &StorageUrl::parse(url).unwrap(),
        &RemoteOptions {
            endpoint: Some(moto.endpoint()),
            credentials: creds,
            max_retries: Some(0),
            ..RemoteOptions::default()
        },
    )
    .unwrap()
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

/// Object paths (`/bucket/key`) of the PUTs in moto's log from byte `offset` on.
fn puts_since(log: &Path, offset: usize) -> Vec<String> {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    text.get(offset..)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| l.split_once("\"PUT ").map(|(_, r)| r))
        .filter_map(|r| r.split_whitespace().next())
        .map(|p| p.split('?').next().unwrap_or_default().to_owned())
        .filter(|p| p.trim_matches('/').contains('/'))
        .collect()
}

#[test]
fn kill_9_during_an_upload_resumes_without_reuploading_intact_objects() {
    let Some(bin) = moto_server_path("kill_9_during_an_upload_resumes_without_reuploading_intact_objects")
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    let root = dir.path().join("ds");
    let storage = format!(
        "\n[storage]\nurl = \"s3://{BUCKET}/lab\"\nendpoint = \"{}\"\nstation_id = \"st-k\"\n\
         max_upload_bytes_per_s = 8000\n",
        moto.endpoint()
    );
    let config = write_config(dir.path(), &root, &storage);

    // `serve --check` shows the storage table, never the secret (which only the environment holds).
    let (ok, out, err) = run(&["serve", "--check", "--config", config.to_str().unwrap()], &moto);
    assert!(ok, "{err}");
    assert!(out.contains("[storage]") && out.contains("st-k"), "{out}");
    assert!(!out.contains(&moto.secret) && !err.contains(&moto.secret));

    let log = Arc::new(Mutex::new(Vec::new()));
    let mut server = serve(&config, &moto, &log);
    record(&server, &moto, "pick", 1000);

    // kill -9 as soon as the first object of the episode is remote (the cap makes the rest take seconds).
    let station = remote(&moto, &format!("s3://{BUCKET}/lab/st-k"));
    let rt = rt();
    let deadline = Instant::now() + Duration::from_mins(2);
    loop {
        if !rt.block_on(station.list()).unwrap_or_default().is_empty() {
            break;
        }
        assert!(Instant::now() < deadline, "no object uploaded within 2 minutes");
        std::thread::sleep(Duration::from_millis(20));
    }
    server.child.kill().unwrap(); // SIGKILL
    server.child.wait().unwrap();
    let intact: BTreeSet<String> = rt
        .block_on(station.list())
        .unwrap()
        .into_iter()
        .map(|(k, _)| k)
        .collect();
    assert!(
        !intact.contains("meta/info.json"),
        "the upload finished before the kill: {intact:?}"
    );
    let all: BTreeSet<String> = phone2act_storage::order::dataset_files(&root)
        .unwrap()
        .into_iter()
        .collect();
    assert!(intact.len() < all.len());
    let moto_log = dir.path().join("moto.log");
    let offset = std::fs::read_to_string(&moto_log).unwrap().len();

    // The next start finishes from the journal.
    drop(server);
    let server = serve(&config, &moto, &log);
    let deadline = Instant::now() + Duration::from_mins(3);
    loop {
        let (ok, out, err) = run(&["episode", "list", "--url", &server.url], &moto);
        assert!(ok, "{err}");
        if out.contains("[uploaded]") {
            assert!(out.contains("by erin"), "{out}");
            break;
        }
        assert!(Instant::now() < deadline, "not uploaded after the restart: {out}");
        std::thread::sleep(Duration::from_millis(200));
    }
    let (ok, out, _) = run(&["status", "--url", &server.url], &moto);
    assert!(
        ok && out.contains("storage: s3://fleet/lab/st-k") && out.contains("1 episodes uploaded"),
        "{out}"
    );
    // Exactly what was missing was PUT again (an interrupted PUT may be logged twice); nothing intact was.
    let again: BTreeSet<String> = puts_since(&moto_log, offset)
        .into_iter()
        .map(|p| p.trim_start_matches("/fleet/lab/st-k/").to_owned())
        .collect();
    let missing: BTreeSet<String> = all.difference(&intact).cloned().collect();
    assert_eq!(again, missing, "intact before the restart: {intact:?}");

    let back = dir.path().join("back");
    let (ok, out, err) = run(
        &[
            "dataset",
            "pull",
            "s3://fleet/lab/st-k",
            back.to_str().unwrap(),
            "--endpoint",
            &moto.endpoint(),
        ],
        &moto,
    );
    assert!(ok, "{err}");
    assert!(out.contains("1 episodes"), "{out}");
    let (ok, out, err) = run(&["dataset", "verify", back.to_str().unwrap()], &moto);
    assert!(ok, "{out}{err}");
    drop(server);
    for line in log.lock().iter() {
        assert!(!line.contains(&moto.secret), "secret in a log line: {line}");
    }
    let prov = std::fs::read_to_string(back.join("meta/phone2act_provenance.json")).unwrap();
    assert!(!prov.contains(&moto.secret) && prov.contains("\"station_id\": \"st-k\""));
}

fn copy_dir(from: &Path, to: &Path) {
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            std::fs::create_dir_all(&dst).unwrap();
            copy_dir(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), dst).unwrap();
        }
    }
}

#[test]
fn push_appends_missing_episodes_and_refuses_a_different_dataset() {
    let Some(bin) = moto_server_path("push_appends_missing_episodes_and_refuses_a_different_dataset") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    let log = Arc::new(Mutex::new(Vec::new()));
    let ep = moto.endpoint();
    let push = |ds: &Path, url: &str| {
        run(
            &["dataset", "push", ds.to_str().unwrap(), url, "--endpoint", &ep],
            &moto,
        )
    };
    let moto_log = dir.path().join("moto.log");
    let log_len = || std::fs::read_to_string(&moto_log).unwrap().len();

    // Two datasets recorded by the same configuration: `a` (one episode, then two), `b` (one, other content:
    // another task, since the sim's idle arm and synthetic camera may give byte-identical episodes of equal
    // length, and on a loaded machine 700 and 900 ms of recording can come out the same number of frames).
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let a_one = dir.path().join("a-one");
    {
        let server = serve(&write_config(dir.path(), &a, ""), &moto, &log);
        record(&server, &moto, "pick", 700);
        std::fs::create_dir_all(&a_one).unwrap();
        copy_dir(&a, &a_one);
        record(&server, &moto, "place", 700);
    }
    {
        let server = serve(&write_config(dir.path(), &b, ""), &moto, &log);
        record(&server, &moto, "pick up", 900);
    }

    let url = "s3://fleet/pushed/a";
    let offset = log_len();
    let (ok, out, err) = push(&a_one, url);
    assert!(ok, "{err}");
    assert!(out.contains("1 episodes remote (was 0)"), "{out}");
    // Data, videos and episode metadata go up several at once, then the replaceable metadata, info.json last:
    // whatever a reader catches mid-push, the info.json it finds names only episodes already complete.
    let first = puts_since(&moto_log, offset);
    assert!(
        first.last().is_some_and(|p| p.ends_with("meta/info.json")),
        "{first:?}"
    );
    let bulk = |p: &String| {
        ["/data/", "/videos/", "/meta/episodes/"]
            .iter()
            .any(|d| p.contains(d))
    };
    let first_meta = first.iter().position(|p| !bulk(p)).unwrap();
    assert!(first[first_meta..].iter().all(|p| !bulk(p)), "{first:?}");
    // GR00T's layout file goes up with the replaceable metadata, after the files it describes.
    let modality = first.iter().position(|p| p.ends_with("meta/modality.json"));
    assert!(modality.is_some_and(|m| m >= first_meta), "{first:?}");
    // Appending: only episode 1's files and the metadata that changed go up; episode 0's never again.
    let offset = log_len();
    let (ok, out, err) = push(&a, url);
    assert!(ok, "{err}");
    assert!(out.contains("2 episodes remote (was 1)"), "{out}");
    let again = puts_since(&moto_log, offset);
    assert!(!again.is_empty());
    for p in &again {
        assert!(
            !p.ends_with("file-000.parquet") && !p.ends_with("file-000.mp4"),
            "re-sent {p}"
        );
    }
    let (ok, out, err) = push(&a, url);
    assert!(ok && out.contains("0 objects put"), "{out}{err}");

    // Refusals write nothing: a remote copy with more episodes, different fps, a different episode 0.
    let offset = log_len();
    let (ok, _, err) = push(&b, url);
    assert!(
        !ok && err.contains("the remote copy has 2 episodes, the local one 1"),
        "{err}"
    );
    let fps = dir.path().join("a-fps");
    std::fs::create_dir_all(&fps).unwrap();
    copy_dir(&a, &fps);
    let info_path = fps.join("meta/info.json");
    let mut info: serde_json::Value = serde_json::from_slice(&std::fs::read(&info_path).unwrap()).unwrap();
    info["fps"] = serde_json::json!(info["fps"].as_u64().unwrap() + 5);
    std::fs::write(&info_path, serde_json::to_vec_pretty(&info).unwrap()).unwrap();
    let (ok, _, err) = push(&fps, url);
    assert!(
        !ok && err.contains("fps differs") && err.contains("nothing was written"),
        "{err}"
    );
    let (ok, _, err) = push(&b, "s3://fleet/pushed/a-one");
    assert!(ok, "{err}"); // a fresh prefix takes it
    let (ok, _, err) = push(&a_one, "s3://fleet/pushed/a-one");
    assert!(!ok && err.contains("different content"), "{err}");
    let after_refusals = puts_since(&moto_log, offset);
    let b_upload: Vec<_> = after_refusals
        .iter()
        .filter(|p| p.starts_with("/fleet/pushed/a-one/"))
        .collect();
    assert_eq!(
        after_refusals.len(),
        b_upload.len(),
        "a refused push wrote: {after_refusals:?}"
    );

    // What is remote pulls back whole.
    let back = dir.path().join("back");
    let (ok, out, err) = run(
        &["dataset", "pull", url, back.to_str().unwrap(), "--endpoint", &ep],
        &moto,
    );
    assert!(ok && out.contains("2 episodes"), "{out}{err}");
    let (ok, out, err) = run(&["dataset", "verify", back.to_str().unwrap()], &moto);
    assert!(ok, "{out}{err}");
}

#[test]
fn three_stations_upload_concurrently_into_one_prefix_and_merge_from_their_urls() {
    let Some(bin) =
        moto_server_path("three_stations_upload_concurrently_into_one_prefix_and_merge_from_their_urls")
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(&bin, dir.path(), true);
    moto.create_bucket(BUCKET);
    let ep = moto.endpoint();
    let log = Arc::new(Mutex::new(Vec::new()));
    let stations = ["st-1", "st-2", "st-3"];
    let servers: Vec<Served> = stations
        .iter()
        .map(|st| {
            let storage = format!(
                "\n[storage]\nurl = \"s3://{BUCKET}/lab\"\nendpoint = \"{ep}\"\nstation_id = \"{st}\"\n"
            );
            serve(
                &write_config(dir.path(), &dir.path().join(st), &storage),
                &moto,
                &log,
            )
        })
        .collect();
    // All three record at once (and so upload at once, into the same bucket prefix).
    std::thread::scope(|s| {
        for (i, server) in servers.iter().enumerate() {
            let moto = &moto;
            s.spawn(move || {
                record(server, moto, "pick", 700);
                record(server, moto, &format!("task of station {i}"), 700);
            });
        }
    });
    // Liveness bound: six short episodes on loopback take seconds; minutes leave room for a loaded machine.
    let deadline = Instant::now() + Duration::from_mins(3);
    for server in &servers {
        loop {
            let (ok, out, err) = run(&["episode", "list", "--url", &server.url], &moto);
            assert!(ok, "{err}");
            if out.matches("[uploaded]").count() == 2 {
                break;
            }
            assert!(Instant::now() < deadline, "not uploaded within 3 minutes: {out}");
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    drop(servers);

    // info and verify read a URL.
    let (ok, out, err) = run(
        &["dataset", "info", "s3://fleet/lab/st-2", "--endpoint", &ep],
        &moto,
    );
    assert!(ok, "{err}");
    assert!(
        out.contains("s3://fleet/lab/st-2") && out.contains("episodes  2"),
        "{out}"
    );
    let (ok, out, err) = run(
        &["dataset", "verify", "s3://fleet/lab/st-3", "--endpoint", &ep],
        &moto,
    );
    assert!(ok, "{out}{err}");
    assert!(out.contains("valid LeRobot v3.0 dataset, 2 episodes"), "{out}");

    // The three station prefixes merged, straight from storage into storage.
    let urls: Vec<String> = stations
        .iter()
        .map(|st| format!("s3://{BUCKET}/lab/{st}"))
        .collect();
    let mut args = vec!["dataset", "merge"];
    args.extend(urls.iter().map(String::as_str));
    args.extend(["--out", "s3://fleet/lab-merged", "--endpoint", &ep]);
    let (ok, out, err) = run(&args, &moto);
    assert!(ok, "{out}{err}");
    assert!(out.contains("6 episodes") && out.contains("4 tasks"), "{out}");
    let back = dir.path().join("merged-back");
    let (ok, _, err) = run(
        &[
            "dataset",
            "pull",
            "s3://fleet/lab-merged",
            back.to_str().unwrap(),
            "--endpoint",
            &ep,
        ],
        &moto,
    );
    assert!(ok, "{err}");
    let (ok, out, err) = run(&["dataset", "verify", back.to_str().unwrap()], &moto);
    assert!(ok, "{out}{err}");
    let prov: serde_json::Value =
        serde_json::from_slice(&std::fs::read(back.join("meta/phone2act_provenance.json")).unwrap()).unwrap();
    let who: Vec<(&str, &str, &str)> = prov["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["station_id"].as_str().unwrap_or_default(),
                e["operator"].as_str().unwrap_or_default(),
                e["merged_from"]["dataset"].as_str().unwrap_or_default(),
            )
        })
        .collect();
    let expect: Vec<(&str, &str, &str)> = urls
        .iter()
        .zip(stations)
        .flat_map(|(u, st)| [(st, "erin", u.as_str()), (st, "erin", u.as_str())])
        .collect();
    assert_eq!(who, expect);
    // Nothing left behind by the downloads.
    let leftovers: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(".phone2act-merge-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

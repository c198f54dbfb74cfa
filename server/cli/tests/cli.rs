//! The `phone2act` binary as a user runs it: `serve` in a subprocess, the episode/status/dataset commands
//! against it, bad config files, a taken port, and SIGTERM.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_phone2act");

struct Served {
    child: Child,
    url: String,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A token the server requires in the end-to-end test; it must never reach a dataset or stdout.
const SECRET_TOKEN: &str = "tok-3f9a1c77e2";

fn serve(config: &std::path::Path) -> Served {
    serve_logging(config, Arc::default())
}

/// Like [`serve`], without `SVT_LOG` in the environment, collecting the server's stderr lines in `log`.
fn serve_logging(config: &std::path::Path, log: Arc<Mutex<Vec<String>>>) -> Served {
    let mut child = Command::new(BIN)
        .args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(config)
        .env("PHONE2ACT_SERVER__TOKEN", SECRET_TOKEN)
        .env_remove("SVT_LOG")
        // Phone ports are fixed (9090, 8443); other tests and servers may hold them.
        .env("PHONE2ACT_GATEWAY__ENABLED", "false")
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(addr) = line.strip_prefix("phone2act: gRPC on ") {
                let _ = tx.send(addr.to_owned());
            }
            log.lock().unwrap().push(line);
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_mins(1))
        .expect("server printed its address");
    Served {
        child,
        url: format!("http://{addr}"),
    }
}

fn run(args: &[&str], url: &str) -> (bool, String, String) {
    let out = Command::new(BIN)
        .args(args)
        .args(["--url", url])
        .env("PHONE2ACT_TOKEN", SECRET_TOKEN)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn write_config(dir: &std::path::Path) -> std::path::PathBuf {
    let path = dir.join("phone2act.toml");
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/default.toml"))
        .unwrap()
        .replace("./datasets/phone2act", &dir.join("ds").display().to_string());
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn episode_status_and_dataset_commands_against_a_served_binary() {
    let dir = tempfile::tempdir().unwrap();
    let server = serve(&write_config(dir.path()));

    let (ok, out, err) = run(&["status"], &server.url);
    assert!(ok, "{err}");
    assert!(out.contains("arm main") && out.contains("camera front"), "{out}");

    let (ok, out, err) = run(&["episode", "start", "--task", "stack the cube"], &server.url);
    assert!(ok, "{err}");
    assert!(out.contains("recording episode 0"), "{out}");
    std::thread::sleep(Duration::from_millis(700));
    let (ok, out, err) = run(&["episode", "stop"], &server.url);
    assert!(ok, "{err}");
    assert!(out.contains("saved episode 0"), "{out}");
    let (ok, out, _) = run(&["episode", "list"], &server.url);
    assert!(
        ok && out.contains("1 episodes") && out.contains("stack the cube"),
        "{out}"
    );
    // Stopping twice is a clear error, not a crash, said once (no "code: ..., message: ..." echo).
    let (ok, _, err) = run(&["episode", "stop"], &server.url);
    assert!(!ok && err.contains("no episode is being recorded"), "{err}");
    assert_eq!(err.matches("no episode is being recorded").count(), 1, "{err}");
    assert!(!err.contains("code:") && !err.contains("message:"), "{err}");

    // The same server under every URL form a user may type; only the scheme-less one is new to tonic.
    let host_port = server.url.strip_prefix("http://").unwrap().to_owned();
    for url in [host_port.as_str(), server.url.as_str()] {
        let (ok, out, err) = run(&["status"], url);
        assert!(ok && out.contains("arm main"), "--url {url}: {out}{err}");
    }
    // https:// to this plaintext port fails in the TLS handshake: an error about TLS, not about the URL.
    let (ok, _, err) = run(&["status"], &format!("https://{host_port}"));
    assert!(!ok && !err.contains("scheme"), "{err}");

    // The dataset records the configuration, and not the token.
    let provenance = std::fs::read_to_string(dir.path().join("ds/meta/phone2act_provenance.json")).unwrap();
    assert!(provenance.contains("<redacted>"), "{provenance}");
    assert!(!provenance.contains(SECRET_TOKEN), "{provenance}");

    let out = Command::new(BIN)
        .args(["dataset", "info"])
        .arg(dir.path().join("ds"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        text.contains("LeRobot v3.0") && text.contains("observation.state"),
        "{text}"
    );
    // Per episode: length, task and success (the default sim arm has a scene; the ball never reached the
    // basket in this episode, so it ends without success).
    let row = text
        .lines()
        .find(|l| l.trim_start().starts_with("0 "))
        .unwrap_or_else(|| panic!("no row for episode 0: {text}"));
    let cells: Vec<&str> = row.split_whitespace().collect();
    assert!(cells[1].parse::<u64>().unwrap() > 0, "{row}");
    assert_eq!(cells[3], "no", "{row}");
    assert!(row.ends_with("stack the cube"), "{row}");
    let out = Command::new(BIN)
        .args(["dataset", "verify"])
        .arg(dir.path().join("ds"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("valid LeRobot v3.0 dataset, 1 episodes"), "{text}");

    // SIGTERM: gone within a second.
    let mut server = server;
    let pid = server.child.id().to_string();
    let sent = Instant::now();
    assert!(
        Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap()
            .success()
    );
    loop {
        if let Some(status) = server.child.try_wait().unwrap() {
            assert!(status.success(), "exit status {status}");
            break;
        }
        assert!(
            sent.elapsed() < Duration::from_secs(1),
            "still running 1 s after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn a_server_that_is_down_is_a_one_line_hint() {
    let (ok, _, err) = run(&["status"], "http://127.0.0.1:9");
    assert!(!ok);
    assert!(err.contains("is `phone2act serve` running"), "{err}");
    // Each cause once: no "transport error: transport error: ..." from wrapped transport errors.
    let parts: Vec<&str> = err.trim().split(": ").collect();
    assert!(parts.windows(2).all(|w| w[0] != w[1]), "{err}");
    assert_eq!(err.matches("cannot connect to").count(), 1, "{err}");
}

/// `serve --check` on `config` with extra environment: the exit code and stderr. `--check` loads and
/// validates exactly as `serve` does but never starts a server, so a config that wrongly passes cannot hang.
fn check_config(config: &std::path::Path, env: &[(&str, &str)]) -> (Option<i32>, String) {
    let out = Command::new(BIN)
        .args(["serve", "--check", "--config"])
        .arg(config)
        .envs(env.iter().copied())
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_config_files_name_file_line_and_expectation() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.toml");
    std::fs::write(
        &path,
        "[server]\nlisten = \"127.0.0.1:0\"\n\n[[arms]]\nname = \"main\"\nbridge = \"sim\"\nspeed = 3\n",
    )
    .unwrap();
    let (code, err) = check_config(&path, &[]);
    assert_eq!(code, Some(1));
    assert!(err.contains(&format!("{}:7:", path.display())), "{err}");
    assert!(err.contains("unknown field `speed`"), "{err}");

    std::fs::write(&path, "[recorder]\nfps = \"twenty\"\n").unwrap();
    let (_, err) = check_config(&path, &[]);
    assert!(err.contains(":2:") && err.contains("expected"), "{err}");
}

#[test]
fn a_taken_port_is_a_one_line_error() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(BIN)
        .env("PHONE2ACT_GATEWAY__ENABLED", "false")
        .args(["serve", "--listen", &addr, "--config"])
        .arg(write_config(dir.path()))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let error_lines: Vec<_> = err.lines().filter(|l| l.contains("error")).collect();
    assert_eq!(error_lines.len(), 1, "{err}");
    assert!(
        error_lines[0].contains(&addr) && error_lines[0].contains("in use"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn check_prints_the_effective_configuration_as_toml_without_secrets() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_config(dir.path());
    let text = std::fs::read_to_string(&path).unwrap() + "\n[gateway]\ntoken = \"pairing-9d2e41\"\n";
    std::fs::write(&path, text).unwrap();
    let out = Command::new(BIN)
        .args(["serve", "--check", "--config"])
        .arg(&path)
        .env("PHONE2ACT_SERVER__TOKEN", SECRET_TOKEN)
        .env("PHONE2ACT_ARMS__0__TELEOP__GATE__JUMP_POSITION_M", "0.02")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for secret in [SECRET_TOKEN, "pairing-9d2e41"] {
        assert!(!stdout.contains(secret) && !String::from_utf8_lossy(&out.stderr).contains(secret));
    }
    // It is TOML a user can save and run: same values, defaults filled in, the override applied.
    let back: toml::Table = toml::from_str(&stdout).unwrap_or_else(|e| panic!("{e}\n{stdout}"));
    assert_eq!(back["server"]["token"].as_str(), Some("<redacted>"));
    assert_eq!(
        back["arms"][0]["teleop"]["gate"]["jump_position_m"].as_float(),
        Some(0.02)
    );
    assert_eq!(back["arms"][0]["chunk"]["max_steps"].as_integer(), Some(10_000));
}

#[test]
fn start_up_config_errors_name_the_file_and_never_abort() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cam.toml");
    std::fs::write(
        &path,
        "[[arms]]\nname = \"main\"\nbridge = \"sim\"\n[[cameras]]\nname = \"big\"\nkind = \"test_pattern\"\nwidth = 100000\nheight = 100000\n",
    )
    .unwrap();
    let (code, err) = check_config(&path, &[]);
    // Exit code 1, not a signal: a 30 GB frame allocation used to abort the process.
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "{}: camera \"big\": 100000x100000 is larger than",
            path.display()
        )),
        "{err}"
    );

    std::fs::write(&path, "[server]\nlisten = \"127.0.0.1:0\"\n").unwrap();
    let (code, err) = check_config(&path, &[]);
    assert_eq!(code, Some(1));
    assert!(
        err.contains(&format!("{}: no arms", path.display())) && err.contains("[[arms]]"),
        "{err}"
    );

    // A bad value from the environment names the variable, not a line of a file the user never wrote.
    let (code, err) = check_config(&write_config(dir.path()), &[("PHONE2ACT_RECORDER__FPS", "fast")]);
    assert!(
        code == Some(1) && err.contains("environment override PHONE2ACT_RECORDER__FPS"),
        "{err}"
    );
}

#[test]
fn output_into_a_closed_pipe_ends_quietly() {
    // `phone2act dataset info X | head -1`: the reader is gone before the first line is written, so every
    // write fails with EPIPE; the reader end is closed before the process starts, so this is not a race.
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    std::fs::create_dir_all(root.join("meta")).unwrap();
    std::fs::write(
        root.join("meta/info.json"),
        r#"{"codebase_version": "v3.0", "fps": 20, "features": {"action": {"dtype": "float32", "shape": [7]}}}"#,
    )
    .unwrap();
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let out = Command::new(BIN)
        .args(["dataset", "info"])
        .arg(&root)
        .stdout(writer)
        .stderr(Stdio::piped())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{:?} {err}", out.status);
    assert!(!err.contains("panicked"), "{err}");
}

/// Issue 13: a fresh dataset is nothing on disk until its first episode (an empty one was a dataset no
/// reader accepts); the encoder library's banner stays out of the log; and `episode list` after a restart
/// lists the dataset's episodes even when phone2act's own sidecar file is gone.
#[test]
fn empty_until_the_first_episode_quiet_encoders_and_a_resumed_list() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let config = write_config(dir.path());
    let log = Arc::new(Mutex::new(Vec::new()));
    let server = serve_logging(&config, Arc::clone(&log));
    let (ok, out, err) = run(&["status"], &server.url);
    assert!(ok, "{out}{err}");
    assert!(
        !ds.join("meta/info.json").exists(),
        "info.json before any episode"
    );
    for task in ["one", "two"] {
        let (ok, _, err) = run(&["episode", "start", "--task", task], &server.url);
        assert!(ok, "{err}");
        std::thread::sleep(Duration::from_millis(500));
        let (ok, _, err) = run(&["episode", "stop"], &server.url);
        assert!(ok, "{err}");
    }
    drop(server);
    let svt: Vec<String> = log
        .lock()
        .unwrap()
        .iter()
        .filter(|l| l.starts_with("Svt["))
        .cloned()
        .collect();
    assert!(svt.is_empty(), "SVT-AV1 logged {} lines: {svt:?}", svt.len());

    std::fs::remove_file(ds.join("meta/phone2act_provenance.json")).unwrap();
    let server = serve(&config);
    let (ok, out, err) = run(&["episode", "list"], &server.url);
    assert!(ok, "{err}");
    assert!(out.contains("2 episodes"), "{out}");
    assert!(out.contains("one") && out.contains("two"), "{out}");
}

#[test]
fn status_watch_into_a_pipe_keeps_every_snapshot_with_rates_and_gate_counters() {
    let dir = tempfile::tempdir().unwrap();
    let server = serve(&write_config(dir.path()));
    let mut watch = Command::new(BIN)
        .args(["status", "--watch", "0.2", "--url", &server.url])
        .env("PHONE2ACT_TOKEN", SECRET_TOKEN)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = watch.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    // Three whole snapshots (read until the fourth begins): the second and third carry a rate (they have a
    // previous one). A minute is far more than four 0.2 s intervals even when a loaded 2-core machine starves
    // the debug binaries.
    let deadline = Instant::now() + Duration::from_mins(1);
    let mut lines = Vec::new();
    while lines
        .iter()
        .filter(|l: &&String| l.starts_with("phone2act "))
        .count()
        < 4
    {
        let left = deadline.saturating_duration_since(Instant::now());
        let line = rx
            .recv_timeout(left)
            .unwrap_or_else(|e| panic!("fewer than four snapshots within a minute ({e}): {lines:#?}"));
        lines.push(line);
    }
    let _ = watch.kill();
    let _ = watch.wait();
    let all = lines.join("\n");
    let text = &all[..all.rfind("\n\nphone2act ").unwrap()];
    // Into a pipe: no terminal control codes, snapshots separated by a blank line.
    assert!(!text.contains('\x1b'), "{text}");
    assert_eq!(text.matches("\n\nphone2act ").count(), 2, "{text}");
    assert_eq!(text.matches("gate: sent ").count(), 3, "{text}");
    // The first snapshot has no previous one to take a rate from; the next two have.
    assert_eq!(text.matches(" cmd/s  gate: sent ").count(), 2, "{text}");
}

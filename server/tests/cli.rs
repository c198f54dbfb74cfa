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

fn serve(config: &std::path::Path) -> Served {
    serve_logging(config, Arc::default())
}

/// Like [`serve`], without `SVT_LOG` in the environment, collecting the server's stderr lines in `log`.
fn serve_logging(config: &std::path::Path, log: Arc<Mutex<Vec<String>>>) -> Served {
    let mut child = Command::new(BIN)
        .args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(config)
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
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/default.toml"))
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
    // Stopping twice is a clear error, not a crash.
    let (ok, _, err) = run(&["episode", "stop"], &server.url);
    assert!(!ok && err.contains("no episode is being recorded"), "{err}");

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
    let out = Command::new(BIN)
        .args(["serve", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains(&format!("{}:7:", path.display())), "{err}");
    assert!(err.contains("unknown field `speed`"), "{err}");

    std::fs::write(&path, "[recorder]\nfps = \"twenty\"\n").unwrap();
    let out = Command::new(BIN)
        .args(["serve", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
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

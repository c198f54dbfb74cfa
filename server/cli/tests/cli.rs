//! The `phone2act` binary as a user runs it: `serve` in a subprocess, the episode/status/dataset commands
//! against it, bad config files, a taken port, and SIGTERM.

mod common;
use common::Served;
use parking_lot::Mutex;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_phone2act");

/// A token the server requires in the end-to-end test; it must never reach a dataset or stdout.
const SECRET_TOKEN: &str = "tok-3f9a1c77e2";

fn serve(config: &std::path::Path) -> Served {
    serve_logging(config, Arc::default())
}

/// Like [`serve`], without `SVT_LOG` in the environment, collecting the server's stderr lines in `log`.
fn serve_logging(config: &std::path::Path, log: Arc<Mutex<Vec<String>>>) -> Served {
    let child = Command::new(BIN)
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
    common::served(child, log, Duration::from_mins(1))
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
    // The operator's outcome: given with stop, listed, and both flags at once refused by the parser.
    let (ok, _, err) = run(&["episode", "start", "--task", "stack the cube"], &server.url);
    assert!(ok, "{err}");
    std::thread::sleep(Duration::from_millis(700));
    let (ok, _, err) = run(&["episode", "stop", "--success", "--failure"], &server.url);
    assert!(!ok && err.contains("cannot be used with"), "{err}");
    let (ok, out, err) = run(&["episode", "stop", "--success"], &server.url);
    assert!(
        ok && out.contains("saved episode 1") && out.contains("[success]"),
        "{out}{err}"
    );
    let (ok, out, _) = run(&["episode", "list"], &server.url);
    assert!(ok && out.contains("2 episodes"), "{out}");
    assert_eq!(out.matches("[success]").count(), 1, "{out}");
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
    // Episode 1 was stopped with --success: the operator's word is its last frame's `next.success`.
    let row = text
        .lines()
        .find(|l| l.trim_start().starts_with("1 "))
        .unwrap_or_else(|| panic!("no row for episode 1: {text}"));
    assert_eq!(row.split_whitespace().nth(3), Some("yes"), "{row}");
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
    assert!(text.contains("valid LeRobot v3.0 dataset, 2 episodes"), "{text}");

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

/// `(kind, frame)` of every event the plot page lists, in page order.
fn plotted_events(html: &str) -> Vec<(String, u64)> {
    html.split("<li class=\"event\" data-kind=\"")
        .skip(1)
        .map(|rest| {
            let (kind, rest) = rest.split_once('"').unwrap();
            let frame = rest.split("data-frame=\"").nth(1).unwrap();
            (
                kind.to_owned(),
                frame[..frame.find('"').unwrap()].parse().unwrap(),
            )
        })
        .collect()
}

/// The values of attribute `attr` of every `<figure class="panel"`, in page order.
fn panel_attr(html: &str, attr: &str) -> Vec<String> {
    html.split("<figure class=\"panel\"")
        .skip(1)
        .map(|p| {
            let v = p.split(&format!("{attr}=\"")).nth(1).unwrap();
            v[..v.find('"').unwrap()].to_owned()
        })
        .collect()
}

/// Every inline camera frame of the page, decoded: `(width, height)` as the JPEG says.
fn plotted_frames(html: &str) -> Vec<(u32, u32)> {
    use base64::Engine as _;
    html.split("src=\"data:image/jpeg;base64,")
        .skip(1)
        .map(|rest| {
            let bytes = base64::engine::general_purpose::STANDARD
                .decode(&rest[..rest.find('"').unwrap()])
                .unwrap();
            let frame = phone2act_capture::jpeg::decode_jpeg(&bytes).unwrap();
            (frame.width, frame.height)
        })
        .collect()
}

fn plot(args: &[&str], dir: &std::path::Path) -> (bool, String, String) {
    let out = Command::new(BIN)
        .args(["dataset", "plot"])
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Issue 18: an episode teleoperated over a real socket (two clutch cycles, one 12 cm jump the gate rejects)
/// is recorded on a served binary; its events sidecar holds the clutch and gate events at frames the recorded
/// action agrees with, and `dataset plot` draws a panel per dimension, the events, and camera frames.
#[test]
fn a_teleoperated_episode_is_plotted_with_its_clutch_and_gate_events() {
    use phone2act_dataset::events::EventKind;
    use phone2act_sdk::buttons;
    use phone2act_sdk::proto as v1;
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let server = serve(&write_config(dir.path()));
    let pose = |z: f64| v1::Pose::from_parts([0.0, 0.0, z], [0.0, 0.0, 0.0, 1.0]);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let client = phone2act_sdk::Client::connect(&server.url, Some(SECRET_TOKEN))
            .await
            .unwrap();
        // The sim's first feedback, so that the arm is ready to engage.
        tokio::time::sleep(Duration::from_millis(400)).await;
        let mut episodes = client.episodes();
        episodes.start("plot me").await.unwrap();
        // A few frames before the first engage, so that the action before it is on record. A minute is far
        // more than two 50 ms ticks even when a loaded 2-core machine starves the debug binary.
        let deadline = Instant::now() + Duration::from_mins(1);
        while episodes.status().await.unwrap().frames_recorded < 2 {
            assert!(
                Instant::now() < deadline,
                "the recorder recorded nothing for a minute"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let mut phone = client
            .teleop("main", phone2act_sdk::TeleopOptions::default())
            .await
            .unwrap();
        // Pauses long enough for the 20 fps recorder to tick between the steps (it holds the newest sample, so a
        // late tick only moves an event by the frames it was late, which the checks below allow).
        let pause = || tokio::time::sleep(Duration::from_millis(300));
        pause().await;
        let mut send = async |z: f64, buttons: Vec<v1::ButtonEvent>| {
            let seq = phone.send_pose(pose(z), buttons, 0).await.unwrap();
            let fb = phone.feedback_for(seq).await.unwrap();
            assert!(fb.error.is_empty(), "{}", fb.error);
            fb.arm_state.unwrap()
        };
        assert!(send(0.0, vec![buttons::clutch_engage()]).await.engaged);
        for i in 1..=4 {
            send(-0.01 * f64::from(i), vec![]).await;
        }
        // 12 cm in one sample: over the default 60 mm jump threshold (right after the walk: after 0.3 s of
        // silence the gate counts the input as stale and takes the next pose as its new reference).
        let state = send(-0.16, vec![]).await;
        assert_eq!(
            state.last_decision.unwrap().verdict(),
            v1::GateVerdict::RejectedJump
        );
        pause().await;
        assert!(!send(-0.04, vec![buttons::clutch_disengage()]).await.engaged);
        pause().await;
        assert!(send(0.0, vec![buttons::clutch_engage()]).await.engaged);
        for i in 1..=3 {
            send(0.01 * f64::from(i), vec![]).await;
        }
        pause().await;
        assert!(!send(0.03, vec![buttons::clutch_disengage()]).await.engaged);
        pause().await;
        drop(phone);
        episodes.stop().await.unwrap();
    });

    // The sidecar: engage, rejection, release, engage, release, in that order (besides the recorder's own
    // timeline events, which depend on how fast this machine renders the camera, and the joint-limit events,
    // which depend on how fast the phone's 1 cm steps follow each other: a step per round trip is faster
    // than the arm's joints may follow, on a fast machine more so).
    let all_events = phone2act_dataset::events::read_events(&ds, 0).unwrap().unwrap();
    let events: Vec<_> = all_events
        .iter()
        .filter(|e| {
            !matches!(
                e.kind,
                EventKind::LateTick | EventKind::Paused | EventKind::JointLimited
            )
        })
        .cloned()
        .collect();
    let kinds: Vec<EventKind> = events.iter().map(|e| e.kind).collect();
    assert_eq!(
        kinds,
        [
            EventKind::ClutchEngage,
            EventKind::GateRejected,
            EventKind::ClutchRelease,
            EventKind::ClutchEngage,
            EventKind::ClutchRelease
        ],
        "{events:#?}"
    );
    let frame = |i: usize| usize::try_from(events[i].frame_index).unwrap();
    assert!(
        events.windows(2).all(|w| w[0].frame_index <= w[1].frame_index),
        "{events:#?}"
    );
    // At the right frames: the recorded action is the gated target, which moves only while the clutch is in.
    // So it holds still before the first engage and from each release to the next engage, and over the first
    // engaged span it moved the 4 cm walked (the engage frame may already hold the first steps: the phone
    // sends faster than the recorder ticks). A marker late by even one frame would put a moving frame
    // before it. (One early cannot be told from the action: the clutch may engage a frame before the first
    // step; `events::tests` pin the exact frame of a change.)
    let episode = phone2act_dataset::readback::read_episode(&ds, 0).unwrap();
    let action = &episode.vectors.iter().find(|v| v.key == "action").unwrap().rows;
    let x = episode.vectors[1].names.iter().position(|n| n == "x").unwrap();
    let still = |from: usize, to: usize| action[from..to].iter().all(|a| a == &action[from]);
    assert!(still(0, frame(0)), "moved before the clutch engaged");
    assert!(still(frame(2), frame(3)), "moved while the clutch was released");
    assert!(still(frame(4), action.len()), "moved after the last release");
    let moved_m = (0..3)
        .map(|k| (action[frame(2)][x + k] - action[frame(0) - 1][x + k]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        (moved_m - 0.04).abs() < 0.005,
        "the first engaged span moved {moved_m} m, not 4 cm: {events:#?}"
    );

    let (ok, out, err) = plot(&["ds", "--episode", "0", "--out", "ep0.html"], dir.path());
    assert!(ok, "{err}");
    assert_eq!(out.trim(), "ep0.html");
    let html = std::fs::read_to_string(dir.path().join("ep0.html")).unwrap();
    let listed: Vec<(String, u64)> = events
        .iter()
        .map(|e| {
            let kind = serde_json::to_value(e.kind).unwrap();
            (kind.as_str().unwrap().to_owned(), e.frame_index)
        })
        .collect();
    let plotted: Vec<(String, u64)> = plotted_events(&html)
        .into_iter()
        .filter(|(kind, _)| !["late_tick", "paused", "joint_limited"].contains(&kind.as_str()))
        .collect();
    assert_eq!(plotted, listed);
    // The joint-limit events are plotted too, each at its frame.
    let limited: Vec<u64> = all_events
        .iter()
        .filter(|e| e.kind == EventKind::JointLimited)
        .map(|e| e.frame_index)
        .collect();
    let plotted_limited: Vec<u64> = plotted_events(&html)
        .into_iter()
        .filter(|(kind, _)| kind == "joint_limited")
        .map(|(_, frame)| frame)
        .collect();
    assert_eq!(plotted_limited, limited);
    assert!(!html.contains("No events recorded"));
    // A panel per dimension: every state and every action dimension is drawn, the measured end-effector pose
    // and gripper with the commanded ones (`ee_x` with `x`, ...), the joints alone.
    let state_names = &episode.vectors[0].names;
    let action_names = &episode.vectors[1].names;
    let (states, actions) = (panel_attr(&html, "data-state"), panel_attr(&html, "data-action"));
    assert_eq!(
        states.iter().filter(|s| !s.is_empty()).collect::<Vec<_>>(),
        state_names.iter().collect::<Vec<_>>()
    );
    let mut drawn: Vec<&String> = actions.iter().filter(|a| !a.is_empty()).collect();
    drawn.sort();
    let mut want: Vec<&String> = action_names.iter().collect();
    want.sort();
    assert_eq!(drawn, want);
    let both = states
        .iter()
        .zip(&actions)
        .filter(|(s, a)| !s.is_empty() && !a.is_empty())
        .count();
    assert_eq!(
        both,
        action_names.len(),
        "every commanded quantity meets its measured one"
    );
    assert!(html.contains("ee_x / x [m]"), "units from the layout");
    // Five frames (fewer only for a shorter episode) of the one camera (640x480), scaled to 240 px wide, that
    // decode as JPEGs.
    let shown = episode.frame_index.len().min(5);
    assert_eq!(plotted_frames(&html), vec![(240, 180); shown]);
    assert_eq!(html.matches("<svg").count(), states.len());
}

/// lerobot's own datasets (v3.0 and v2.1) plot without markers, and say why; bad requests are clear errors.
#[test]
fn lerobot_datasets_plot_without_events_and_bad_requests_are_clear_errors() {
    let fixtures = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures");
    let dir = tempfile::tempdir().unwrap();
    for name in ["lerobot_sample_v30", "lerobot_sample_v21"] {
        let (ok, out, err) = plot(&[&format!("{fixtures}/{name}"), "--episode", "2"], dir.path());
        assert!(ok, "{name}: {err}");
        assert_eq!(out.trim(), "episode_000002.html");
        let html = std::fs::read_to_string(dir.path().join("episode_000002.html")).unwrap();
        // The fixture: 6 joints j0..j5 on both sides, two 128x96 cameras, episode 2 has 8 frames.
        assert_eq!(
            panel_attr(&html, "data-state"),
            ["j0", "j1", "j2", "j3", "j4", "j5"],
            "{name}"
        );
        assert_eq!(
            panel_attr(&html, "data-action"),
            ["j0", "j1", "j2", "j3", "j4", "j5"],
            "{name}"
        );
        assert!(html.contains("8 frames at 10 fps"), "{name}");
        assert!(html.contains("No events recorded"), "{name}");
        assert!(plotted_events(&html).is_empty());
        assert_eq!(plotted_frames(&html), vec![(128, 96); 10], "{name}");
    }

    let (ok, _, err) = plot(
        &[&format!("{fixtures}/lerobot_sample_v30"), "--episode", "3"],
        dir.path(),
    );
    assert!(
        !ok && err.contains("has 3 episodes") && err.contains("no episode 3"),
        "{err}"
    );
    let (ok, _, err) = plot(&["missing-dir", "--episode", "0"], dir.path());
    assert!(!ok && err.contains("missing-dir does not exist"), "{err}");
    // A dataset whose video is gone: named, not a decoder's message.
    let copy = dir.path().join("novideo");
    copy_dir(
        std::path::Path::new(&format!("{fixtures}/lerobot_sample_v21")),
        &copy,
    );
    std::fs::remove_dir_all(copy.join("videos")).unwrap();
    let (ok, _, err) = plot(&["novideo", "--episode", "0"], dir.path());
    assert!(
        !ok && err.contains("video of camera observation.images.front for episode 0 is missing"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(
        !dir.path().join("episode_000000.html").exists(),
        "a refused plot writes nothing"
    );
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let dest = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &dest);
        } else {
            std::fs::copy(entry.path(), dest).unwrap();
        }
    }
}

/// phone2act's v2.1 (GR00T) layout plots too: its episode files, its (empty) events sidecar, and the dataset
/// with the sidecar still verifies.
#[test]
fn a_v21_episode_of_ours_plots_and_verifies_with_its_sidecar() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path());
    let text = std::fs::read_to_string(&config).unwrap();
    assert!(text.contains("format = \"v3.0\""), "{text}");
    std::fs::write(&config, text.replace("format = \"v3.0\"", "format = \"v2.1\"")).unwrap();
    let server = serve(&config);
    let (ok, _, err) = run(&["episode", "start", "--task", "hold still"], &server.url);
    assert!(ok, "{err}");
    std::thread::sleep(Duration::from_millis(500));
    let (ok, _, err) = run(&["episode", "stop"], &server.url);
    assert!(ok, "{err}");
    drop(server);
    let ds = dir.path().join("ds");
    // Nobody touched the clutch: a sidecar with no arm events (not a missing one). The recorder's own
    // timeline events depend on how fast this machine renders the camera.
    let events = phone2act_dataset::events::read_events(&ds, 0).unwrap().unwrap();
    assert!(events.iter().all(|e| e.arm.is_empty()), "{events:?}");
    let (ok, out, err) = plot(&["ds", "--episode", "0"], dir.path());
    assert!(ok, "{err}");
    let html = std::fs::read_to_string(dir.path().join(out.trim())).unwrap();
    assert!(
        html.contains("LeRobot v2.1") && html.contains("hold still"),
        "no facts"
    );
    assert!(html.contains(&format!(
        "{} events from meta/phone2act/events/episode_000000.jsonl",
        events.len()
    )));
    assert!(!panel_attr(&html, "data-state").is_empty());
    let frames = phone2act_dataset::readback::read_episode(&ds, 0)
        .unwrap()
        .frame_index
        .len();
    assert_eq!(plotted_frames(&html).len(), frames.min(5));
    let out = Command::new(BIN)
        .args(["dataset", "verify"])
        .arg(&ds)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("valid LeRobot v2.1 dataset, 1 episodes"), "{text}");
}

/// The default config with `extra` appended (tables after the file's own), its dataset under `dir`.
fn config_with(dir: &std::path::Path, name: &str, extra: &str) -> std::path::PathBuf {
    let path = dir.join(name);
    let text = std::fs::read_to_string(write_config(dir)).unwrap() + extra;
    std::fs::write(&path, text).unwrap();
    path
}

/// Text appended to the default config, environment overrides, and what the one-line error must say.
type Case = (String, Vec<(&'static str, String)>, &'static str);

#[test]
fn check_refuses_what_serve_refuses() {
    // Each of these used to pass `--check` and fail only in `serve` (or, for the empty root, in every save).
    let dir = tempfile::tempdir().unwrap();
    let a_file = dir.path().join("a-file");
    std::fs::write(&a_file, "x").unwrap();
    let cases: Vec<Case> = vec![
        (
            String::new(),
            vec![("PHONE2ACT_RECORDER__FPS", "20.5".to_owned())],
            "recorder.fps must be a whole number",
        ),
        (
            "[[cameras]]\nname = \"scene\"\nkind = \"sim_render\"\narm = \"nope\"\n".into(),
            vec![],
            "arm = \"nope\" is not a simulated arm",
        ),
        (
            "[[arms]]\nname = \"cr5\"\nbridge = \"dobot\"\n".into(),
            vec![],
            "bridge \"dobot\" needs an [arms.dobot] table",
        ),
        (
            "[[cameras]]\nname = \"tiny\"\nkind = \"test_pattern\"\nwidth = 64\nheight = 48\n".into(),
            vec![],
            "SVT-AV1 needs at least 64x64",
        ),
        (
            String::new(),
            vec![("PHONE2ACT_RECORDER__ROOT", a_file.display().to_string())],
            "is a file, not a directory",
        ),
        (
            String::new(),
            vec![("PHONE2ACT_RECORDER__ROOT", String::new())],
            "(with PHONE2ACT_RECORDER__ROOT): recorder.root is empty",
        ),
    ];
    for (i, (extra, env, needle)) in cases.iter().enumerate() {
        let path = config_with(dir.path(), &format!("case{i}.toml"), extra);
        let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (*k, v.as_str())).collect();
        let (code, err) = check_config(&path, &env);
        assert_eq!(code, Some(1), "{extra} {env:?}: {err}");
        assert!(err.contains(needle), "{extra} {env:?}: {err}");
        assert_eq!(err.lines().count(), 1, "one line: {err}");
    }
}

#[test]
fn serve_with_an_empty_root_refuses_to_start_and_writes_nothing() {
    // `PHONE2ACT_RECORDER__ROOT= phone2act serve`: it used to start, fail every Stop with "I/O error on : No such
    // file or directory" and leave a commit journal in the working directory.
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path());
    let cwd = dir.path().join("cwd");
    std::fs::create_dir(&cwd).unwrap();
    let mut child = Command::new(BIN)
        .args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(&config)
        .current_dir(&cwd)
        .env("PHONE2ACT_RECORDER__ROOT", "")
        .env("PHONE2ACT_GATEWAY__ENABLED", "false")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // A server that starts runs until killed: give a refusal (milliseconds) a minute before calling it started.
    let deadline = Instant::now() + Duration::from_mins(1);
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("serve started with an empty recorder root");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("(with PHONE2ACT_RECORDER__ROOT): recorder.root is empty"),
        "{err}"
    );
    assert!(!err.contains("gRPC on"), "{err}");
    assert_eq!(std::fs::read_dir(&cwd).unwrap().count(), 0, "nothing written");
}

#[test]
fn gateway_errors_name_their_line_and_overrides_their_variable() {
    let dir = tempfile::tempdir().unwrap();
    let path = config_with(
        dir.path(),
        "gw.toml",
        "\n[gateway]\nprint_qr = false\nmax_message_bytes = \"big\"\n",
    );
    let text = std::fs::read_to_string(&path).unwrap();
    let line = text
        .lines()
        .position(|l| l.starts_with("max_message_bytes"))
        .unwrap()
        + 1;
    let (code, err) = check_config(&path, &[]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!("{}:{line}:", path.display())) && err.contains("expected usize"),
        "line {line}: {err}"
    );
    let path = config_with(dir.path(), "gw2.toml", "\n[gateway]\nprint_qr = false\n");
    let (code, err) = check_config(&path, &[("PHONE2ACT_GATEWAY__MAX_MESSAGE_BYTES", "big")]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("environment override PHONE2ACT_GATEWAY__MAX_MESSAGE_BYTES"),
        "{err}"
    );
    assert!(
        !err.contains(&path.display().to_string()),
        "the file is not to blame: {err}"
    );
    let (code, err) = check_config(&path, &[("PHONE2ACT_GATEWAY__MAX_MESSAGE_BYTES", "10")]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("(with PHONE2ACT_GATEWAY__MAX_MESSAGE_BYTES)") && err.contains("got 10"),
        "{err}"
    );
}

#[test]
fn check_shows_the_video_keys_and_refuses_bad_ones() {
    let dir = tempfile::tempdir().unwrap();
    let path = config_with(
        dir.path(),
        "video.toml",
        "\n[gateway]\nprint_qr = false\n\n[gateway.video]\nmax_bitrate_kbps = 800\nmax_viewers = 2\n",
    );
    let out = Command::new(BIN)
        .args(["serve", "--check", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let back: toml::Table = toml::from_str(&String::from_utf8_lossy(&out.stdout)).unwrap();
    let video = back["gateway"]["video"].as_table().unwrap();
    assert_eq!(video["max_bitrate_kbps"].as_integer(), Some(800));
    assert_eq!(video["max_viewers"].as_integer(), Some(2));
    // Defaults filled in for what the file leaves out.
    assert_eq!(video["min_bitrate_kbps"].as_integer(), Some(60));
    assert_eq!(video["enabled"].as_bool(), Some(true));
    let bad = config_with(
        dir.path(),
        "bad-video.toml",
        "\n[gateway]\nprint_qr = false\n\n[gateway.video]\nmin_bitrate_kbps = 900\nmax_bitrate_kbps = 800\n",
    );
    let (code, err) = check_config(&bad, &[]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("gateway.video.min_bitrate_kbps (900) must not exceed max_bitrate_kbps (800)"),
        "{err}"
    );
    let (code, err) = check_config(&path, &[("PHONE2ACT_GATEWAY__VIDEO__MAX_FPS", "0")]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("(with PHONE2ACT_GATEWAY__VIDEO__MAX_FPS)")
            && err.contains("gateway.video.max_fps must be in 1..=60, got 0"),
        "{err}"
    );
}

#[test]
fn secrets_that_look_like_numbers_are_taken_and_never_printed() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_config(dir.path());
    for secret in ["123456789012345", "0x7f3a9c", "1e9", "true"] {
        let out = Command::new(BIN)
            .args(["serve", "--check", "--config"])
            .arg(&path)
            .env("PHONE2ACT_SERVER__TOKEN", secret)
            .env("PHONE2ACT_GATEWAY__TOKEN", secret)
            .output()
            .unwrap();
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert!(out.status.success(), "{secret}: {stderr}");
        let back: toml::Table = toml::from_str(&stdout).unwrap();
        assert_eq!(back["server"]["token"].as_str(), Some("<redacted>"), "{secret}");
        assert_eq!(back["gateway"]["token"].as_str(), Some("<redacted>"), "{secret}");
        assert!(!stderr.contains(secret), "{secret}: {stderr}");
        if secret.len() > 4 {
            assert!(!stdout.contains(secret), "{secret}");
        }
    }
    // A secret the file types as a number is refused, without the number.
    let path = config_with(dir.path(), "num.toml", "\n[gateway]\ntoken = 987654321987\n");
    let (code, err) = check_config(&path, &[]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("token") || err.contains("string"), "{err}");
    assert!(!err.contains("987654321987"), "{err}");
}

/// `serve` with the gateway on ephemeral ports (rosbridge only) and `env`; stderr up to the gRPC address line.
fn serve_gateway_log(dir: &std::path::Path, env: &[(&str, &str)]) -> Vec<String> {
    let mut child = Command::new(BIN)
        .args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(write_config(dir))
        .env("PHONE2ACT_SERVER__TOKEN", SECRET_TOKEN)
        .env("PHONE2ACT_GATEWAY__HTTPS", "false")
        .env("PHONE2ACT_GATEWAY__PRINT_QR", "false")
        .env("PHONE2ACT_GATEWAY__ROSBRIDGE_LISTEN", "127.0.0.1:0")
        .env("PHONE2ACT_GATEWAY__CERT_DIR", dir.join("gw"))
        .envs(env.iter().copied())
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let mut lines = Vec::new();
    for line in BufReader::new(stderr).lines().map_while(Result::ok) {
        let done = line.starts_with("phone2act: gRPC on ");
        lines.push(line);
        if done {
            break;
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    lines
}

#[test]
fn a_token_with_trusted_loopback_is_said_at_start_and_an_empty_list_trusts_none() {
    let dir = tempfile::tempdir().unwrap();
    let lines = serve_gateway_log(dir.path(), &[]);
    let warning: Vec<_> = lines
        .iter()
        .filter(|l| l.contains("WARN") && l.contains("admits every loopback"))
        .collect();
    assert_eq!(warning.len(), 1, "{lines:#?}");
    assert!(
        warning[0].contains("every loopback address")
            && warning[0].contains("local_addresses = []")
            && !warning[0].contains(SECRET_TOKEN),
        "{}",
        warning[0]
    );
    let lines = serve_gateway_log(dir.path(), &[("PHONE2ACT_GATEWAY__LOCAL_ADDRESSES", "[]")]);
    assert!(
        lines.iter().any(|l| l.starts_with("phone2act: gRPC on ")),
        "{lines:#?}"
    );
    assert!(
        !lines.iter().any(|l| l.contains("local_addresses = []")),
        "{lines:#?}"
    );
}

const FLIGHT_FIXTURES: [&str; 2] = [
    concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/flight/phone-session.flight"
    ),
    concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/flight/policy-session.flight"
    ),
];

#[test]
fn replay_log_finds_the_committed_sessions_identical() {
    let out = Command::new(BIN)
        .arg("replay-log")
        .args(FLIGHT_FIXTURES)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 2, "{stdout}");
    for (line, file) in lines.iter().zip(FLIGHT_FIXTURES) {
        assert!(line.starts_with(file), "{line}");
        assert!(
            line.contains(": identical; the log ends: the arm was shut down"),
            "{line}"
        );
    }
}

#[test]
fn replay_log_under_a_changed_gate_rule_names_the_first_differing_decision() {
    let dir = tempfile::tempdir().unwrap();
    // The shipped default with one rule changed: the phone session's wrist turn (up to 0.3 rad at 50 Hz,
    // about 0.03 rad a round) passes the default 0.5 rad jump threshold and not one of 0.01 rad.
    let config = dir.path().join("stricter.toml");
    let mut table: toml::Table =
        toml::from_str(&std::fs::read_to_string(write_config(dir.path())).unwrap()).unwrap();
    let arm = &mut table["arms"].as_array_mut().unwrap()[0];
    let teleop = arm
        .as_table_mut()
        .unwrap()
        .entry("teleop")
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    let gate = teleop
        .as_table_mut()
        .unwrap()
        .entry("gate")
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    gate.as_table_mut()
        .unwrap()
        .insert("jump_rotation_rad".into(), toml::Value::Float(0.01));
    std::fs::write(&config, toml::to_string(&table).unwrap()).unwrap();
    let out = Command::new(BIN)
        .arg("replay-log")
        .arg(FLIGHT_FIXTURES[0])
        .arg("--config")
        .arg(&config)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stdout}{stderr}");
    assert!(
        stdout.contains(": first difference at input ") && stdout.contains("(Teleop {"),
        "{stdout}"
    );
    assert!(stdout.contains("decision differs"), "{stdout}");
    assert!(
        stdout.contains("replayed: Some(GateDecision { verdict: RejectedJump"),
        "{stdout}"
    );
    assert!(
        stderr.contains("1 of 1 flight log(s) replayed differently"),
        "{stderr}"
    );
}

#[test]
fn replay_log_refuses_a_file_that_is_not_a_log() {
    let dir = tempfile::tempdir().unwrap();
    let bogus = dir.path().join("x.flight");
    std::fs::write(&bogus, "hello").unwrap();
    let out = Command::new(BIN).arg("replay-log").arg(&bogus).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("not a phone2act flight log"), "{stderr}");
}

//! `phone2act`: the command-line entry point. `phone2act serve` runs the server (the embedded default when
//! no `--config` is given).

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use phone2act_gateway::GatewayConfig;
use phone2act_sdk::proto as v1;
use phone2act_server::config::ConfigSource;
use phone2act_server::{bind, run_with_local};
use std::net::SocketAddr;
use std::path::PathBuf;

mod fleet;
mod plot;
mod replay_log;

#[derive(Parser, Debug)]
#[command(
    name = "phone2act",
    version,
    about = "Phone-to-robot teleoperation and LeRobot recording server"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the server.
    Serve {
        /// TOML configuration file; without it the embedded default runs (simulated arm `main`, synthetic
        /// camera, datasets under ./datasets/).
        #[arg(long, env = "PHONE2ACT_CONFIG")]
        config: Option<PathBuf>,
        /// gRPC listen address (overrides `server.listen`).
        #[arg(long)]
        listen: Option<SocketAddr>,
        /// Print the effective configuration and exit.
        #[arg(long)]
        check: bool,
    },
    /// Manage episodes on a running server.
    Episode {
        #[command(flatten)]
        conn: Conn,
        #[command(subcommand)]
        action: EpisodeAction,
    },
    /// Print the server's status: arms, cameras, recorder.
    Status {
        #[command(flatten)]
        conn: Conn,
        /// Keep printing every INTERVAL seconds.
        #[arg(long)]
        watch: Option<f64>,
    },
    /// Inspect a dataset on disk.
    Dataset {
        #[command(subcommand)]
        action: DatasetAction,
    },
    /// Re-run the control core on flight logs (written with `[flight_log]` on) and check that every command
    /// and gate decision comes out identical; exit 1 naming the first input where one does not.
    ReplayLog {
        /// Flight logs (`<arm>-<unix time>.flight`).
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Replay under this configuration's teleop and chunk settings for the log's arm, instead of the
        /// settings the log recorded.
        #[arg(long)]
        config: Option<PathBuf>,
    },
}

#[derive(clap::Args, Debug)]
struct Conn {
    /// Server URL.
    #[arg(
        long,
        env = "PHONE2ACT_URL",
        default_value = "http://127.0.0.1:50051",
        global = true
    )]
    url: String,
    /// Bearer token, if the server requires one.
    #[arg(long, env = "PHONE2ACT_TOKEN", global = true)]
    token: Option<String>,
}

#[derive(Subcommand, Debug)]
enum EpisodeAction {
    /// Start recording an episode.
    Start {
        /// Task text stored with every frame.
        #[arg(long)]
        task: String,
        /// Who records it (kept in the episode's provenance).
        #[arg(long, env = "PHONE2ACT_OPERATOR", default_value = "")]
        operator: String,
    },
    /// Stop and save the episode in progress, optionally with the operator's outcome (kept in the episode's
    /// provenance and, in a dataset that records `next.success`, as its last frame's value).
    Stop {
        /// The episode succeeded.
        #[arg(long, conflicts_with = "failure")]
        success: bool,
        /// The episode failed.
        #[arg(long)]
        failure: bool,
    },
    /// Stop and throw away the episode in progress.
    Discard,
    /// Save the last seconds the server kept while idle (`[recorder] highlight_s`, LeRobot's `highlight`) as
    /// an episode; refused while an episode is recorded.
    Highlight {
        /// Task text stored with every frame.
        #[arg(long)]
        task: String,
        /// Who recorded it (kept in the episode's provenance).
        #[arg(long, env = "PHONE2ACT_OPERATOR", default_value = "")]
        operator: String,
        /// The episode succeeded.
        #[arg(long, conflicts_with_all = ["failure", "keep_recording"])]
        success: bool,
        /// The episode failed.
        #[arg(long, conflicts_with = "keep_recording")]
        failure: bool,
        /// Do not save yet: the kept seconds begin the episode in progress, which records on until
        /// `episode stop`.
        #[arg(long)]
        keep_recording: bool,
    },
    /// Throw away the episode in progress and start again (same task unless --task).
    Rerecord {
        #[arg(long, default_value = "")]
        task: String,
    },
    /// List saved episodes.
    List,
}

#[derive(Subcommand, Debug)]
enum DatasetAction {
    /// Summarise a dataset: format, fps, episodes, frames, features.
    Info {
        /// Dataset root directory, or s3://bucket/prefix (downloaded to a scratch directory first).
        path: String,
        #[command(flatten)]
        remote: fleet::RemoteArgs,
    },
    /// Check a dataset against the LeRobot format rules and say what is wrong; exit 1 if anything is.
    Verify {
        /// Dataset root directory, or s3://bucket/prefix (downloaded to a scratch directory first).
        path: String,
        #[command(flatten)]
        remote: fleet::RemoteArgs,
    },
    /// Upload a dataset to S3-compatible storage (s3://bucket/prefix); an existing remote copy of the same
    /// dataset gets only the episodes it lacks, a different one is refused with nothing written.
    Push {
        /// Dataset root directory.
        path: PathBuf,
        /// s3://bucket/prefix
        url: String,
        #[command(flatten)]
        remote: fleet::RemoteArgs,
    },
    /// Download a dataset from S3-compatible storage into a directory.
    Pull {
        /// s3://bucket/prefix
        url: String,
        /// Destination directory.
        path: PathBuf,
        #[command(flatten)]
        remote: fleet::RemoteArgs,
    },
    /// Merge several LeRobot v3.0 datasets (local directories or s3:// URLs, e.g. one per station) into one:
    /// episodes renumbered, tasks unified, statistics recomputed, videos copied without re-encoding, each
    /// episode's station and operator kept. Inputs that differ (fps, robot type, features, cameras) are
    /// refused with nothing written.
    Merge {
        /// Datasets to merge, in order (directories or s3://bucket/prefix).
        #[arg(required = true)]
        sources: Vec<String>,
        /// New dataset (a directory that does not exist yet, or s3://bucket/prefix).
        #[arg(long)]
        out: String,
        #[command(flatten)]
        sizes: fleet::SizeArgs,
        #[command(flatten)]
        remote: fleet::RemoteArgs,
    },
    /// Repack a LeRobot v3.0 dataset's many small files into files of lerobot's sizes (100 MB data, 200 MB
    /// video by default), without re-encoding; the same as a merge of one dataset.
    Compact {
        /// Dataset to compact (a directory or s3://bucket/prefix).
        source: String,
        /// New dataset (a directory that does not exist yet, or s3://bucket/prefix).
        #[arg(long)]
        out: String,
        #[command(flatten)]
        sizes: fleet::SizeArgs,
        #[command(flatten)]
        remote: fleet::RemoteArgs,
    },
    /// Plot an episode into one HTML page: camera frames, state and action per dimension over time, clutch
    /// and gate events marked.
    Plot {
        /// Dataset root directory.
        path: PathBuf,
        /// Episode index.
        #[arg(long)]
        episode: u64,
        /// Output file [default: episode_NNNNNN.html in the current directory].
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// Writes one line to stdout. A reader that went away (`phone2act dataset info X | head`) ends the process
/// quietly with success, as other Unix tools do, instead of the panic `println!` gives.
macro_rules! outln {
    ($($arg:tt)*) => {
        write_stdout_line(format_args!($($arg)*))
    };
}

fn write_stdout_line(args: std::fmt::Arguments<'_>) {
    use std::io::Write as _;
    let mut out = std::io::stdout().lock();
    if let Err(e) = out.write_fmt(args).and_then(|()| out.write_all(b"\n")) {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("phone2act: error: cannot write to stdout: {e}");
        std::process::exit(1);
    }
}

/// The log filter: `PHONE2ACT_LOG` first, then the usual `RUST_LOG`, else `info`. Both take
/// `tracing_subscriber` filter directives (`warn`, `phone2act_server=debug,info`). `var` reads the
/// environment (a parameter so that the choice is testable without touching the process environment).
fn log_filter(var: impl Fn(&str) -> Option<String>) -> tracing_subscriber::EnvFilter {
    ["PHONE2ACT_LOG", "RUST_LOG"]
        .into_iter()
        .find_map(|name| {
            let value = var(name).filter(|v| !v.trim().is_empty())?;
            match tracing_subscriber::EnvFilter::try_new(&value) {
                Ok(filter) => Some(filter),
                Err(e) => {
                    eprintln!("phone2act: ignoring {name}={value:?}: {e}");
                    None
                }
            }
        })
        .unwrap_or_else(|| tracing_subscriber::EnvFilter::new("info"))
}

fn main() -> std::process::ExitCode {
    // Before any thread exists: it sets an environment variable.
    phone2act_recorder::av::quiet_encoder_library_logs();
    phone2act_recorder::memory::limit_malloc_arenas();
    tracing_subscriber::fmt()
        .with_env_filter(log_filter(|name| std::env::var(name).ok()))
        .with_writer(std::io::stderr)
        .init();
    match real_main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("phone2act: error: {}", one_line(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The error and its causes on one line, each said once: transport layers wrap an error in another with the
/// same text ("tcp connect error: tcp connect error: ..."), which reads as noise.
fn one_line(e: &anyhow::Error) -> String {
    let mut parts: Vec<String> = Vec::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if parts.last().is_none_or(|last| !last.ends_with(&text)) {
            parts.push(text);
        }
    }
    parts.join(": ")
}

fn client_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")
}

async fn connect(conn: &Conn) -> anyhow::Result<phone2act_sdk::Client> {
    phone2act_sdk::Client::connect(&conn.url, conn.token.as_deref())
        .await
        .with_context(|| format!("is `phone2act serve` running at {}?", conn.url))
}

fn print_status(status: &phone2act_sdk::proto::SystemStatus) {
    for line in status_lines(status, None) {
        outln!("{line}");
    }
}

/// One status snapshot as lines. With the previous snapshot of a watch, each arm also shows its command rate
/// over the interval between the two.
fn status_lines(
    status: &phone2act_sdk::proto::SystemStatus,
    previous: Option<&phone2act_sdk::proto::SystemStatus>,
) -> Vec<String> {
    let mut lines = vec![format!(
        "phone2act {}  uptime {:.1} s",
        status.version, status.uptime_s
    )];
    for arm in &status.arms {
        let pose = arm.robot_from_ee.as_ref().and_then(|p| p.position_m.as_ref());
        let at = pose.map_or_else(
            || "no feedback".to_owned(),
            |p| format!("ee ({:.3}, {:.3}, {:.3}) m", p.x, p.y, p.z),
        );
        let decision = arm.last_decision.as_ref().map_or("", |d| d.reason.as_str());
        lines.push(format!(
            "  arm {:<8} {:<6} {:?} owner {:?} {}  {at}  gripper {:.2}  {decision}",
            arm.arm,
            arm.bridge_kind,
            arm.health(),
            arm.owner(),
            if arm.engaged { "engaged" } else { "" },
            arm.gripper_position,
        ));
        if !arm.health_message.is_empty() {
            lines.push(format!("      {}", arm.health_message));
        }
        let rate = previous
            .and_then(|p| Some((p, p.arms.iter().find(|a| a.arm == arm.arm)?)))
            .and_then(|(p, before)| {
                let dt_s = status.uptime_s - p.uptime_s;
                (dt_s > 0.0).then(|| arm.commands_sent.saturating_sub(before.commands_sent) as f64 / dt_s)
            })
            .map_or_else(String::new, |hz| format!("{hz:.1} cmd/s  "));
        lines.push(format!(
            "      {rate}gate: sent {}  clamped {}  rejected {}",
            arm.commands_sent, arm.commands_clamped, arm.commands_rejected
        ));
    }
    for cam in &status.cameras {
        lines.push(format!(
            "  camera {:<8} {:<12} {}x{} @ {} fps  {} frames  {}",
            cam.camera,
            cam.kind,
            cam.width,
            cam.height,
            cam.fps,
            cam.frames_captured,
            if cam.live { "live" } else { "STALE" }
        ));
    }
    if let Some(rec) = &status.recording {
        lines.push(format!(
            "  recorder {} ({}) {}  episode {}  {} frames  {:.1} s  held {} paused {} late {} dropped {}  saved {}  {}",
            rec.dataset_root,
            rec.dataset_format,
            phone2act_sdk::phase_name(rec.phase),
            rec.episode_index,
            rec.frames_recorded,
            rec.duration_s,
            rec.held_ticks,
            rec.paused_ticks,
            rec.late_ticks,
            rec.dropped_frames,
            rec.episodes_saved,
            rec.warning
        ));
    }
    lines
}

/// `status --watch`: on a terminal each snapshot replaces the previous one (cursor home, clear screen), so the
/// view stays in place; into a pipe or a file snapshots follow each other, separated by a blank line, so logs
/// keep every one.
async fn watch_status(system: &mut phone2act_sdk::SystemApi, interval_s: f64) -> anyhow::Result<()> {
    use std::io::IsTerminal as _;
    let redraw = std::io::stdout().is_terminal();
    let mut stream = system.watch_status(interval_s).await?;
    let mut previous = None;
    while let Some(status) = stream.message().await? {
        let mut frame = status_lines(&status, previous.as_ref()).join("\n");
        if redraw {
            frame.insert_str(0, "\x1b[H\x1b[2J");
        } else if previous.is_some() {
            frame.insert(0, '\n');
        }
        outln!("{frame}");
        previous = Some(status);
    }
    Ok(())
}

/// Prints a summary of the dataset at `path`, named `name` (the directory or the URL it was given as).
fn dataset_info(path: &std::path::Path, name: &str) -> anyhow::Result<()> {
    let info_path = path.join("meta/info.json");
    let text = std::fs::read_to_string(&info_path)
        .with_context(|| format!("{name} is not a LeRobot dataset (no meta/info.json)"))?;
    let info: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{} is not valid JSON", info_path.display()))?;
    let get = |k: &str| info.get(k).map_or_else(|| "?".to_owned(), ToString::to_string);
    outln!("dataset   {name}");
    outln!("format    LeRobot {}", get("codebase_version").trim_matches('"'));
    outln!("robot     {}", get("robot_type").trim_matches('"'));
    outln!("fps       {}", get("fps"));
    outln!("episodes  {}", get("total_episodes"));
    outln!("frames    {}", get("total_frames"));
    outln!("tasks     {}", get("total_tasks"));
    if let Some(features) = info.get("features").and_then(|f| f.as_object()) {
        outln!("features");
        for (key, f) in features {
            let dtype = f.get("dtype").and_then(|d| d.as_str()).unwrap_or("?");
            let shape = f.get("shape").map(ToString::to_string).unwrap_or_default();
            outln!("  {key:<32} {dtype:<8} {shape}");
        }
    }
    // Per episode, from the data rows themselves (so a dataset lerobot wrote reads the same).
    let report = phone2act_dataset::verify::verify(path);
    let fps = info.get("fps").and_then(serde_json::Value::as_f64).unwrap_or(0.0);
    if !report.per_episode.is_empty() {
        outln!("episode  frames  duration_s  success  task");
    }
    for (index, facts) in &report.per_episode {
        let success = match facts.success_at_end {
            Some(true) => "yes",
            Some(false) => "no",
            None => "-",
        };
        let task = facts
            .task_indices
            .iter()
            .map(|&t| {
                usize::try_from(t)
                    .ok()
                    .and_then(|t| report.tasks.get(t))
                    .map_or_else(|| format!("<task {t}>"), Clone::clone)
            })
            .collect::<Vec<_>>()
            .join(" | ");
        let duration_s = if fps > 0.0 {
            facts.frames as f64 / fps
        } else {
            f64::NAN
        };
        outln!(
            "{index:>7}  {:>6}  {duration_s:>10.2}  {success:>7}  {task}",
            facts.frames
        );
    }
    if !report.ok() {
        outln!(
            "verify    {} problem(s): run `phone2act dataset verify {}`",
            report.problems.len(),
            name
        );
    }
    Ok(())
}

/// How an episode line shows the operator's outcome.
fn outcome_suffix(outcome: v1::EpisodeOutcome) -> &'static str {
    match outcome {
        v1::EpisodeOutcome::Success => " [success]",
        v1::EpisodeOutcome::Failure => " [failure]",
        v1::EpisodeOutcome::Unspecified => "",
    }
}

/// The operator's outcome from `--success` / `--failure`.
fn outcome_of(success: bool, failure: bool) -> v1::EpisodeOutcome {
    match (success, failure) {
        (true, _) => v1::EpisodeOutcome::Success,
        (_, true) => v1::EpisodeOutcome::Failure,
        _ => v1::EpisodeOutcome::Unspecified,
    }
}

fn real_main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Episode { conn, action } => client_runtime()?.block_on(async {
            let client = connect(&conn).await?;
            let mut episodes = client.episodes();
            match action {
                EpisodeAction::Start { task, operator } => {
                    let s = episodes.start_by(&task, &operator).await?;
                    outln!("recording episode {} ({:?})", s.episode_index, s.task);
                }
                EpisodeAction::Stop { success, failure } => {
                    let outcome = outcome_of(success, failure);
                    let r = episodes.stop_with(outcome).await?;
                    let ep = r.episode.unwrap_or_default();
                    outln!(
                        "saved episode {}: {} frames, {:.2} s, task {:?}{} (save took {:.0} ms)",
                        ep.episode_index,
                        ep.length_frames,
                        ep.duration_s,
                        ep.task,
                        outcome_suffix(ep.outcome()),
                        r.save_latency_s * 1000.0
                    );
                }
                EpisodeAction::Discard => outln!("discarded {} frames", episodes.discard().await?),
                EpisodeAction::Highlight {
                    task,
                    operator,
                    success,
                    failure,
                    keep_recording,
                } => {
                    let r = episodes
                        .save_highlight_with(v1::SaveHighlightRequest {
                            task,
                            operator,
                            keep_recording,
                            outcome: outcome_of(success, failure).into(),
                        })
                        .await?;
                    match (r.episode, r.status) {
                        (Some(ep), _) => outln!(
                            "saved the last {:.2} s as episode {}: {} frames, task {:?}{} (save took {:.0} ms)",
                            ep.duration_s,
                            ep.episode_index,
                            ep.length_frames,
                            ep.task,
                            outcome_suffix(ep.outcome()),
                            r.save_latency_s * 1000.0
                        ),
                        (None, Some(s)) => outln!(
                            "recording episode {} ({:?}) from the last {:.2} s; `episode stop` saves it",
                            s.episode_index,
                            s.task,
                            s.duration_s
                        ),
                        (None, None) => anyhow::bail!("SaveHighlight answered with neither episode nor status"),
                    }
                }
                EpisodeAction::Rerecord { task } => {
                    let s = episodes.rerecord(&task).await?;
                    outln!("re-recording episode {} ({:?})", s.episode_index, s.task);
                }
                EpisodeAction::List => {
                    let list = episodes.list().await?;
                    outln!("{} episodes in {}", list.episodes.len(), list.dataset_root);
                    if let Some(s) = &list.storage {
                        outln!("{}", fleet::storage_line(s));
                    }
                    for ep in list.episodes {
                        outln!(
                            "  {:>4}  {:>6} frames  {:>7.2} s  held {:>3} paused {:>3} late {:>3} dropped {:>3}  {}{}{}",
                            ep.episode_index,
                            ep.length_frames,
                            ep.duration_s,
                            ep.held_ticks,
                            ep.paused_ticks,
                            ep.late_ticks,
                            ep.dropped_frames,
                            ep.task,
                            outcome_suffix(ep.outcome()),
                            fleet::upload_suffix(&ep)
                        );
                    }
                }
            }
            anyhow::Ok(())
        }),
        Command::Status { conn, watch } => client_runtime()?.block_on(async {
            let client = connect(&conn).await?;
            let mut system = client.system();
            match watch {
                None => {
                    print_status(&system.status().await?);
                    if let Ok(list) = client.episodes().list().await
                        && let Some(s) = &list.storage
                    {
                        outln!("{}", fleet::storage_line(s));
                    }
                }
                Some(interval_s) => watch_status(&mut system, interval_s).await?,
            }
            anyhow::Ok(())
        }),
        Command::Dataset {
            action: DatasetAction::Info { path, remote },
        } => {
            let local = fleet::local_copy(&path, &remote)?;
            dataset_info(local.path(), &path)
        }
        Command::ReplayLog { files, config } => replay_log::run(&files, config.as_deref()),
        Command::Dataset {
            action: DatasetAction::Push { path, url, remote },
        } => {
            outln!("{}", fleet::push(&path, &url, &remote)?);
            Ok(())
        }
        Command::Dataset {
            action: DatasetAction::Pull { url, path, remote },
        } => {
            outln!("{}", fleet::pull(&url, &path, &remote)?);
            Ok(())
        }
        Command::Dataset {
            action:
                DatasetAction::Merge {
                    sources,
                    out,
                    sizes,
                    remote,
                },
        } => {
            outln!("{}", fleet::merge(&sources, &out, &sizes, &remote)?);
            Ok(())
        }
        Command::Dataset {
            action:
                DatasetAction::Compact {
                    source,
                    out,
                    sizes,
                    remote,
                },
        } => {
            outln!("{}", fleet::merge(&[source], &out, &sizes, &remote)?);
            Ok(())
        }
        Command::Dataset {
            action: DatasetAction::Plot { path, episode, out },
        } => {
            let written = plot::plot(&path, episode, out)?;
            outln!("{}", written.display());
            Ok(())
        }
        Command::Dataset {
            action: DatasetAction::Verify { path, remote },
        } => {
            let local = fleet::local_copy(&path, &remote)?;
            let report = phone2act_dataset::verify::verify(local.path());
            for warning in &report.warnings {
                outln!("warning: {warning}");
            }
            if report.ok() {
                outln!(
                    "{}: valid LeRobot {} dataset, {} episodes, {} frames",
                    path,
                    report.version,
                    report.episodes,
                    report.frames
                );
                Ok(())
            } else {
                for problem in &report.problems {
                    outln!("problem: {problem}");
                }
                let removed = phone2act_storage::removed_locally(local.path()).unwrap_or_default();
                if !removed.is_empty() {
                    outln!(
                        "note: {} data and video files were removed from this disk after their upload \
                         (storage.retain_local = false): verify the stored copy, `phone2act dataset verify \
                         s3://…`",
                        removed.len()
                    );
                }
                anyhow::bail!("{}: {} problem(s) found", path, report.problems.len())
            }
        }
        Command::Serve {
            config,
            listen,
            check,
        } => {
            let source = match &config {
                Some(path) => ConfigSource::file(path)?,
                None => ConfigSource::embedded(),
            };
            let origin = source.origin().to_owned();
            let mut config = source.config(std::env::vars())?;
            if let Some(listen) = listen {
                config.server.listen = listen;
            }
            let gateway_config: GatewayConfig =
                source.gateway(std::env::vars(), |g: &GatewayConfig| {
                    // The message names its `gateway.` key; the location is added by the caller.
                    g.validate().map_err(|e| match e {
                        phone2act_gateway::GatewayError::Config(message) => message,
                        other => other.to_string(),
                    })
                })?;
            // Defaults filled in, so that `--check` and the datasets' provenance show the whole table.
            config.gateway = toml::Table::try_from(&gateway_config)
                .context("cannot write the gateway configuration back as TOML")?;
            if check {
                let text = config
                    .to_redacted_toml()
                    .context("cannot print the configuration as TOML")?;
                outln!("# phone2act {} effective configuration of {origin}", env!("CARGO_PKG_VERSION"));
                outln!("# (defaults filled in, PHONE2ACT_* overrides applied, secrets shown as \"{}\")", phone2act_server::config::REDACTED);
                outln!("{text}");
                return Ok(());
            }
            warn_if_local_addresses_skip_the_token(&config, &gateway_config);
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .thread_name("phone2act-rt")
                .build()
                .context("cannot start the async runtime")?;
            runtime.block_on(async move {
                let listener = bind(config.server.listen).await?;
                let local = listener.local_addr()?;
                eprintln!("phone2act: gRPC on {local}");
                // One signal, two servers: the gRPC server and the embedded phone gateway.
                let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
                tokio::spawn(async move {
                    shutdown_signal().await;
                    stop_tx.send_replace(true);
                });
                let stopped = |mut rx: tokio::sync::watch::Receiver<bool>| async move {
                    let _ = rx.wait_for(|s| *s).await;
                };
                // The embedded gateway is an SDK client of this server, in-process: no socket, no loopback
                // hop, the same token check. Phones' addresses (pairing, take-over) are the gateway's.
                let (gateway, local) = if gateway_config.enabled {
                    let (client, local) = phone2act_sdk::Client::in_process(config.server.token.as_deref())
                        .context("the server token cannot be sent as a header")?;
                    let gateway = phone2act_gateway::Gateway::bind_client(gateway_config, client)
                        .await
                        .context(
                            "cannot start the phone gateway (set [gateway] enabled = false to run without it)",
                        )?;
                    let local: phone2act_server::LocalConnections =
                        Box::new(move |routes, stopped| local.serve(routes, stopped));
                    (Some(tokio::spawn(gateway.run(stopped(stop_rx.clone())))), Some(local))
                } else {
                    (None, None)
                };
                run_with_local(config, listener, local, stopped(stop_rx))
                    .await
                    .with_context(|| format!("serving with the configuration {origin}"))?;
                if let Some(gateway) = gateway {
                    match tokio::time::timeout(std::time::Duration::from_millis(300), gateway).await {
                        Ok(Ok(Err(e))) => tracing::warn!("phone gateway: {e}"),
                        Ok(_) => {}
                        Err(_) => tracing::warn!("phone gateway still closing connections; exiting anyway"),
                    }
                }
                anyhow::Ok(())
            })
        }
    }
}

/// Said once at start: with a server token, the addresses the gateway trusts as this machine skip it.
fn warn_if_local_addresses_skip_the_token(config: &phone2act_server::Config, gateway: &GatewayConfig) {
    if config.server.token.is_some()
        && let Some(warning) = gateway.local_trust_warning()
    {
        tracing::warn!("{warning}");
    }
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {}
        () = term => {}
    }
    tracing::info!("shutdown requested");
}

#[cfg(test)]
mod tests {
    use super::log_filter;

    fn filter(env: &[(&str, &str)]) -> String {
        log_filter(|name| env.iter().find(|(k, _)| *k == name).map(|(_, v)| (*v).to_owned())).to_string()
    }

    #[test]
    fn phone2act_log_then_rust_log_then_info() {
        assert_eq!(filter(&[]), "info");
        assert_eq!(filter(&[("RUST_LOG", "debug")]), "debug");
        assert_eq!(
            filter(&[("PHONE2ACT_LOG", "warn"), ("RUST_LOG", "debug")]),
            "warn"
        );
        // An unusable value is reported and skipped, not silently turned into "log nothing".
        assert_eq!(filter(&[("PHONE2ACT_LOG", "=="), ("RUST_LOG", "error")]), "error");
        assert_eq!(filter(&[("PHONE2ACT_LOG", " ")]), "info");
    }
}

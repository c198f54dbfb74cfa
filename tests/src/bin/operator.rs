//! The scripted operator: records pick-and-place demonstrations on a simulated arm through the real phone
//! path (`Teleop.Stream`, as a phone does), saving only the episodes that succeed. See
//! `phone2act_tests::operator` for what it does and docs/simulation.md for how to use it.
//!
//! `cargo run --release -p phone2act-tests --bin operator -- --server http://127.0.0.1:50051 --episodes 50 --seed 0`
//!
//! Prints a progress line per episode on stderr and, at the end, one JSON line on stdout:
//! `{"attempted":..,"succeeded":..,"saved":..,"success_rate":..,"seeds":[..],"refused":..,"skipped":[..]}`.
//! Episode `k` uses scene seed `seed + k`, so a run with `--seed S --episodes N` trains on seeds `S..S+N`;
//! evaluate on a disjoint range. A try the server cuts short by refusing a phone sample (the arm not ready) is
//! discarded and its seed tried again, up to `MAX_REFUSED_TRIES` tries, then skipped (listed in `skipped`).

use anyhow::Context as _;
use clap::Parser;
use phone2act_sdk::Client;
use phone2act_tests::operator::{self, DEFAULT_TASK, OperatorOptions};

/// Flag names follow lerobot-record's (`--episodes` for `num_episodes`, `--episode-time-s`, `--reset-time-s`).
#[derive(Parser, Debug)]
#[command(
    name = "operator",
    about = "Record pick-and-place demonstrations through the phone path"
)]
struct Args {
    /// gRPC URL of the phone2act server.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    server: String,
    /// Bearer token, if the server has one.
    #[arg(long, env = "PHONE2ACT_TOKEN")]
    token: Option<String>,
    /// Simulated arm to drive.
    #[arg(long, default_value = "main")]
    arm: String,
    /// Episodes to attempt.
    #[arg(long, default_value_t = 10)]
    episodes: u64,
    /// Scene seed of the first episode; episode k uses seed + k.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Task text recorded with every episode.
    #[arg(long, default_value = DEFAULT_TASK)]
    task: String,
    /// Longest an episode may take before it counts as failed (s).
    #[arg(long, default_value_t = 30.0)]
    episode_time_s: f64,
    /// Pause after each scene reset before recording (s).
    #[arg(long, default_value_t = 1.0)]
    reset_time_s: f64,
    /// Release and re-grip the clutch half way through each carry.
    #[arg(long)]
    clutch_cycles: bool,
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let client = Client::connect(&args.server, args.token.as_deref())
        .await
        .with_context(|| format!("connecting to {}", args.server))?;
    let options = OperatorOptions {
        arm: args.arm,
        episodes: args.episodes,
        seed: args.seed,
        task: args.task,
        episode_time_s: args.episode_time_s,
        reset_time_s: args.reset_time_s,
        clutch_cycles: args.clutch_cycles,
    };
    let total = options.episodes;
    let summary = operator::run(
        &client,
        &options,
        |r| {
            let outcome = match (r.success, r.episode_index) {
                (true, Some(index)) => format!("saved as episode {index} ({} frames)", r.frames),
                _ => format!("failed, discarded: {}", r.note),
            };
            eprintln!(
                "episode {}/{total} seed {}: {outcome} in {:.1} s",
                r.attempt + 1,
                r.seed,
                r.duration_s
            );
        },
        |seed, tries, reason| {
            let next = if tries < operator::MAX_REFUSED_TRIES {
                "trying it again"
            } else {
                "skipping it"
            };
            eprintln!(
                "refused: seed {seed}, try {tries}/{}: {reason}; discarded, {next}",
                operator::MAX_REFUSED_TRIES
            );
        },
    )
    .await?;
    println!("{}", summary.to_json());
    Ok(())
}

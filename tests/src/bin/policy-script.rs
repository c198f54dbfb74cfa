//! A scripted policy session for tests in other languages (the phone page's browser tests): it opens a
//! `Policy.Session` that drives one arm and pushes the chunks its standard input asks for, one JSON object a
//! line, answering each on standard output, one JSON object a line.
//!
//! `policy-script --server http://127.0.0.1:50051 --arm main --name scripted`
//!
//! In: `{"cmd":"chunk","steps":40,"period_s":0.1,"dx_m":0.06,"gripper_end":0.8}` pushes relative steps walking
//! `dx_m` along +x (rotation held, the gripper ramping from 0 to `gripper_end`) answering a fresh observation
//! (one that arrived after the command), or with `"observation":"marked"` the one `{"cmd":"mark"}` kept;
//! `{"cmd":"loading"}` says the policy is loading (answered `{"event":"loading","arms":[..],"remaining_s":..,
//! "error":".."}`).
//! Out: `{"event":"ready"}`, then per chunk `{"event":"accepted"|"rejected","observation_id":..,
//! "targets_m":[[x,y,z],..],"grippers":[..],"reason":".."}` (the targets the steps command: the observation's
//! position plus each step's offset).

use anyhow::Context as _;
use clap::Parser;
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, PolicySession};
use serde_json::{Value, json};
use std::io::{BufRead as _, Write as _};
use tokio::sync::{mpsc, watch};

#[derive(Parser, Debug)]
#[command(name = "policy-script", about = "A policy session driven from standard input")]
struct Args {
    /// gRPC URL of the phone2act server.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    server: String,
    /// Bearer token, if the server has one.
    #[arg(long, env = "PHONE2ACT_TOKEN")]
    token: Option<String>,
    #[arg(long, default_value = "main")]
    arm: String,
    /// The policy's name on status displays.
    #[arg(long, default_value = "scripted")]
    name: String,
}

fn say(v: &Value) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{v}");
    let _ = out.flush();
}

/// Reads the session's events, keeping the newest observation in `latest`, until the stream ends; sends the
/// loading messages `loading` asks for (the session's sender lives here, beside its events).
async fn observe(
    mut session: PolicySession,
    latest: watch::Sender<Option<v1::Observation>>,
    mut loading: mpsc::Receiver<()>,
) {
    loop {
        let event = tokio::select! {
            event = session.next_event() => event,
            Some(()) = loading.recv() => {
                if let Err(e) = session.loading().await {
                    say(&json!({"event": "error", "reason": e.to_string()}));
                }
                continue;
            }
        };
        let Ok(Some(event)) = event else { break };
        match event {
            v1::policy_event::Event::Observation(obs) => {
                let _ = latest.send(Some(obs));
            }
            v1::policy_event::Event::Revoked(r) => say(&json!({"event": "revoked", "reason": r.reason})),
            v1::policy_event::Event::Loading(l) => say(&json!({
                "event": "loading", "arms": l.arms, "remaining_s": l.remaining_s, "error": l.error,
            })),
            _ => {}
        }
    }
    say(&json!({"event": "closed"}));
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let client = Client::connect(&args.server, args.token.as_deref())
        .await
        .with_context(|| format!("connecting to {}", args.server))?;
    let hello = v1::PolicyHello {
        arms: vec![args.arm.clone()],
        observation_rate_hz: 20.0,
        image_encoding: v1::ImageEncoding::None as i32,
        request_control: true,
        policy_name: args.name.clone(),
        // Long: the scripts pause between chunks while a person (a browser test) acts.
        silence_timeout_s: 600.0,
        ..v1::PolicyHello::default()
    };
    let session = client.policy(hello).await.context("opening the policy session")?;
    let session_id = session.ready().session_id.clone();
    let (latest_tx, mut latest) = watch::channel(None);
    let (loading_tx, loading_rx) = mpsc::channel::<()>(1);
    tokio::spawn(observe(session, latest_tx, loading_rx));
    say(&json!({"event": "ready"}));

    let mut marked: Option<v1::Observation> = None;
    // A thread reads standard input (tokio's is a feature the workspace does not build), one line at a time.
    let (line_tx, mut lines) = mpsc::channel::<String>(4);
    std::thread::spawn(move || {
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            if line_tx.blocking_send(line).is_err() {
                break;
            }
        }
    });
    while let Some(line) = lines.recv().await {
        let cmd: Value = serde_json::from_str(&line).with_context(|| format!("command {line:?}"))?;
        // Two observations that arrived after the command: the first may have been on its way already.
        let fresh = async {
            for _ in 0..2 {
                latest.changed().await.context("the session ended")?;
            }
            latest.borrow_and_update().clone().context("no observation")
        };
        match cmd["cmd"].as_str() {
            Some("loading") => {
                // Answered by the session's `LoadingAccepted` event, from the reading task.
                loading_tx.send(()).await.context("the session ended")?;
            }
            Some("mark") => {
                marked = Some(fresh.await?);
                say(&json!({"event": "marked"}));
            }
            Some("chunk") => {
                let obs = if cmd["observation"] == "marked" {
                    marked.clone().context("no observation was marked")?
                } else {
                    fresh.await?
                };
                let here = obs
                    .arms
                    .first()
                    .and_then(|a| a.robot_from_ee.as_ref())
                    .and_then(|p| p.position_m)
                    .context("the observation has no pose")?;
                let n = cmd["steps"].as_u64().unwrap_or(20).max(1) as usize;
                let dx_m = cmd["dx_m"].as_f64().unwrap_or(0.02);
                let gripper_end = cmd["gripper_end"].as_f64().unwrap_or(0.0);
                let steps: Vec<[f64; 7]> = (1..=n)
                    .map(|k| {
                        let f = k as f64 / n as f64;
                        [dx_m * f, 0.0, 0.0, 0.0, 0.0, 0.0, gripper_end * f]
                    })
                    .collect();
                let chunk = v1::ActionChunk {
                    arm: args.arm.clone(),
                    steps: steps
                        .iter()
                        .map(|s| v1::ActionStep { values: s.to_vec() })
                        .collect(),
                    step_period_s: cmd["period_s"].as_f64().unwrap_or(0.1),
                    observation_id: obs.observation_id,
                    mode: v1::ActionMode::DeltaEe as i32,
                    blend_steps: 0,
                    keep_steps: 0,
                };
                let request = v1::PushChunkRequest {
                    session_id: session_id.clone(),
                    chunk: Some(chunk),
                };
                let targets: Vec<[f64; 3]> = steps
                    .iter()
                    .map(|s| [here.x + s[0], here.y + s[1], here.z + s[2]])
                    .collect();
                let grippers: Vec<f64> = steps.iter().map(|s| s[6]).collect();
                let (event, reason) = match client.policy_raw().push_chunk(request).await {
                    Ok(_) => ("accepted", String::new()),
                    Err(status) => ("rejected", status.message().to_owned()),
                };
                say(&json!({
                    "event": event, "reason": reason, "observation_id": obs.observation_id,
                    "targets_m": targets, "grippers": grippers,
                }));
            }
            other => say(&json!({"event": "error", "reason": format!("unknown command {other:?}")})),
        }
    }
    Ok(())
}

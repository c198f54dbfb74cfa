//! Inputs for real-time chunking (issue 27): observations carry the driving plan's pending steps and the
//! session's measured inference delay, and a chunk may keep the replaced plan's leading steps. A policy with a
//! 300 ms inference delay whose consecutive chunks disagree by 8 mm (as a real policy's chunks do) joins them
//! without a jump when it uses those inputs, and with the full disagreement as a jump when it does not. The
//! commanded targets are read back from the recorded dataset's actions.

use phone2act_dataset::parquet_io::{Row, read_rows};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, PolicySession};
use phone2act_tests::{TestServer, default_config};
use std::time::Duration;

/// The injected inference delay.
const DELAY: Duration = Duration::from_millis(300);
const STEP_S: f64 = 0.1;
const HORIZON: usize = 20;
/// How far consecutive chunks disagree (z, alternating sign): 8 mm between neighbours.
const OFFSET_M: f64 = 0.004;
/// Steps over which a policy using the inputs eases from the pending plan into its own.
const BLEND: usize = 5;

/// The path every chunk tracks along x, on the server's clock: a 1.5 cm, 3 s sine (at most 3.1 mm per step);
/// z stays at the start height plus the chunk's offset.
fn path_x(x0: f64, t_s: f64) -> f64 {
    x0 + 0.015 * (2.0 * std::f64::consts::PI * t_s / 3.0).sin()
}

/// Runs `chunks` chunks, each computed from a fresh observation and pushed `DELAY` later; with `rtc`, each
/// keeps the pending steps the inference delay covers and blends from them into its own over `BLEND` steps.
/// Returns the inference delays (s, steps) the observations reported.
async fn run_policy(
    client: &Client,
    policy: &mut PolicySession,
    (x0, z0): (f64, f64),
    first_chunk: usize,
    chunks: usize,
    rtc: bool,
) -> Vec<(f64, u32)> {
    let mut delays = Vec::new();
    for i in first_chunk..first_chunk + chunks {
        policy.request_observation().await.unwrap();
        let obs = policy.next_observation().await.unwrap();
        delays.push((obs.inference_delay_s, obs.inference_delay_steps));
        let arm = &obs.arms[0];
        let [ox, _, oz] = phone2act_tests::pos(arm.robot_from_ee.as_ref().unwrap());
        let t0_s = obs.timestamp_ns as f64 * 1e-9;
        let offset_m = if i % 2 == 0 { OFFSET_M } else { -OFFSET_M };
        // Relative steps (the arm's mode) against this observation: what the "network" predicts.
        let own = |k: usize| -> Vec<f64> {
            let x = path_x(x0, t0_s + k as f64 * STEP_S);
            vec![x - ox, 0.0, z0 + offset_m - oz, 0.0, 0.0, 0.0, 0.0]
        };
        let received = std::time::Instant::now();
        tokio::time::sleep(DELAY).await;
        let pending: Vec<&[f64]> = arm.pending_steps.iter().map(|s| s.values.as_slice()).collect();
        // The steps that will be past when the chunk lands: the server's measured delay (the largest of the
        // last chunks), or, when this inference stalled longer (a loaded machine), what the policy measured
        // itself plus a step for the way to the server, as LeRobot's RTC does with its own latency tracker.
        let own_delay_steps = (received.elapsed().as_secs_f64() / STEP_S).ceil() as usize + 1;
        let keep = if rtc {
            (obs.inference_delay_steps as usize)
                .max(own_delay_steps)
                .min(pending.len())
                .min(HORIZON - 1)
        } else {
            0
        };
        let steps = (0..HORIZON)
            .map(|k| {
                let mine = own(k);
                let values = match pending.get(k) {
                    Some(old) if rtc && k < keep => old.to_vec(),
                    Some(old) if rtc && k < keep + BLEND => {
                        let w = (k - keep + 1) as f64 / (BLEND + 1) as f64;
                        old.iter().zip(&mine).map(|(a, b)| a + (b - a) * w).collect()
                    }
                    _ => mine,
                };
                v1::ActionStep { values }
            })
            .collect();
        let chunk = v1::ActionChunk {
            arm: "main".into(),
            steps,
            step_period_s: STEP_S,
            observation_id: obs.observation_id,
            mode: v1::ActionMode::DeltaEe as i32,
            blend_steps: 0,
            keep_steps: keep as u32,
        };
        policy.push_chunk_checked(client, chunk).await.unwrap();
    }
    delays
}

/// The largest step-to-step change of the commanded position over an episode's frames (m): over all three
/// axes, and along z alone (the axis where chunks disagree; the path itself moves along x only).
fn largest_jumps_m(rows: &[&Row]) -> (f64, f64) {
    let diff = |w: &[&Row], i: usize| f64::from(w[1].action[i]) - f64::from(w[0].action[i]);
    rows.windows(2)
        .map(|w| {
            let full = (0..3).map(|i| diff(w, i).powi(2)).sum::<f64>().sqrt();
            (full, diff(w, 2).abs())
        })
        .fold((0.0, 0.0), |(a, b), (full, z)| {
            (f64::max(a, full), f64::max(b, z))
        })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pending_steps_and_the_measured_delay_join_chunks_without_a_jump() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = default_config(dir.path());
    // One frame per half step: every step the arm is sent shows in the actions.
    config.recorder.fps = 2.0 / STEP_S;
    let server = TestServer::start(config).await.unwrap();
    let client = server.client().await.unwrap();
    let mut hello = phone2act_tests::policy_hello(&["main"], "rtc-test", 2.0);
    hello.observation_rate_hz = 0.0;
    let mut policy = client.policy(hello).await.unwrap();
    // The path starts where the arm is, at the height it has.
    let start = phone2act_tests::sim_pose_of(&client, "main").await;
    let origin = (start[0], start[2]);
    let mut episodes = client.episodes();
    let mut measured = Vec::new();
    for (phase, rtc) in [(0, false), (1, true)] {
        // Two chunks to settle onto the path, then an episode of 12 chunk boundaries.
        run_policy(&client, &mut policy, origin, phase * 100, 2, rtc).await;
        episodes
            .start(if rtc { "with rtc inputs" } else { "without" })
            .await
            .unwrap();
        let delays = run_policy(&client, &mut policy, origin, phase * 100 + 2, 12, rtc).await;
        episodes.stop().await.unwrap();
        measured.push(delays);
    }
    server.shutdown().await.unwrap();

    // The delay the observations reported: at least the injected 300 ms (3 steps of 0.1 s), in steps rounded up.
    for (delay_s, steps) in measured.iter().flatten() {
        assert!(*delay_s >= DELAY.as_secs_f64(), "{delay_s}");
        assert_eq!(*steps, (delay_s / STEP_S - 1e-9).ceil() as u32);
    }
    let mut rows = Vec::new();
    for entry in std::fs::read_dir(dir.path().join("data/chunk-000")).unwrap() {
        rows.extend(read_rows(&entry.unwrap().path()).unwrap());
    }
    let jumps = |episode: i64| {
        let mut of: Vec<&Row> = rows.iter().filter(|r| r.episode_index == episode).collect();
        of.sort_by_key(|r| r.frame_index);
        assert!(of.len() > 40, "episode {episode} has {} frames", of.len());
        largest_jumps_m(&of)
    };
    let ((without_m, without_z_m), (with_m, with_z_m)) = (jumps(0), jumps(1));
    eprintln!(
        "largest step-to-step jump of the commanded position under a {} ms inference delay: {:.1} mm ({:.1} mm \
         along z) without the RTC inputs, {:.1} mm ({:.1} mm along z) with them (chunks disagree by {:.0} mm \
         along z; the path moves at most 3.1 mm per step along x)",
        DELAY.as_millis(),
        without_m * 1e3,
        without_z_m * 1e3,
        with_m * 1e3,
        with_z_m * 1e3,
        2.0 * OFFSET_M * 1e3
    );
    // Judged along z, where only the chunks' disagreement moves the target: a tick or recorder stall on a
    // loaded machine can fold two of the path's steps along x into one frame, but not create a z jump.
    // Without: every boundary jumps by the disagreement (8 mm).
    assert!(without_z_m > 0.007, "{without_z_m}");
    // With: one blend step of the disagreement (8 mm / 6 = 1.3 mm), two if a stall folds two into a frame.
    assert!(with_z_m < 0.003, "{with_z_m}");
}

//! Micro-benchmark: planner + safety gate per phone sample (`TeleopArm::on_pose`), and the gate alone.
//!
//! Run with `cargo bench -p phone2act-core --bench planner`. Prints nanoseconds per sample as the median of
//! several timed batches, so one scheduler hiccup does not move the figure.

// A benchmark times itself; the rule against clock reads is for the library.
#![allow(clippy::disallowed_methods)]

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use phone2act_core::{
    ActionMode, ClutchKind, GateConfig, Mapping, Planner, SafetyGate, TeleopArm, TeleopConfig,
};
use std::hint::black_box;
use std::time::Instant;

const SAMPLES: usize = 1024;
const BATCHES: usize = 41;
const ROUNDS_PER_BATCH: usize = 50;

/// A phone path with combined rotations, sampled at 50 Hz.
fn phone_path() -> Vec<Isometry3<f64>> {
    (0..SAMPLES)
        .map(|i| {
            let t = i as f64 * 0.02;
            Isometry3::from_parts(
                Translation3::new(
                    0.05 * (0.7 * t).sin(),
                    1.2 + 0.03 * (1.1 * t).sin(),
                    -0.05 * (0.5 * t).cos(),
                ),
                UnitQuaternion::from_scaled_axis(Vector3::new(
                    0.4 * (0.3 * t).sin(),
                    0.6 * (0.2 * t).sin(),
                    0.3 * (0.4 * t).cos(),
                )),
            )
        })
        .collect()
}

fn median_ns_per_sample(mut run_batch: impl FnMut() -> usize) -> (f64, usize) {
    let mut per_sample = Vec::with_capacity(BATCHES);
    let mut checksum = 0;
    for _ in 0..BATCHES {
        let start = Instant::now();
        for _ in 0..ROUNDS_PER_BATCH {
            checksum += run_batch();
        }
        per_sample.push(start.elapsed().as_nanos() as f64 / (ROUNDS_PER_BATCH * SAMPLES) as f64);
    }
    per_sample.sort_by(f64::total_cmp);
    (per_sample[BATCHES / 2], checksum)
}

fn main() {
    let path = phone_path();
    let start_pose = Isometry3::from_parts(
        Translation3::new(0.25, 0.0, 0.18),
        UnitQuaternion::from_euler_angles(0.0, 0.9, 0.0),
    );
    let config = TeleopConfig {
        gate: GateConfig {
            max_linear_speed_m_s: Some(1.0),
            max_angular_speed_rad_s: Some(6.0),
            ..GateConfig::default()
        },
        ..TeleopConfig::default()
    };

    let (teleop_ns, passed) = median_ns_per_sample(|| {
        let mut arm = TeleopArm::new(&config, start_pose).expect("valid config");
        arm.clutch(ClutchKind::Engage, Some(path[0]), start_pose, 0.0);
        let mut passed = 0;
        for (i, phone) in path.iter().enumerate() {
            let step = arm.on_pose(black_box(*phone), true, start_pose, i as f64 * 0.02);
            passed += usize::from(step.command.is_some());
        }
        black_box(passed)
    });

    let mut planner = Planner::new(Mapping::from_config(&config.mapping).expect("valid mapping"));
    planner.reindex(path[0], start_pose);
    let targets: Vec<Isometry3<f64>> = path.iter().map(|p| planner.target(p).expect("indexed")).collect();
    let (gate_ns, gate_passed) = median_ns_per_sample(|| {
        let mut gate = SafetyGate::new(&config.gate, targets[0]).expect("valid config");
        let mut passed = 0;
        for (i, t) in targets.iter().enumerate() {
            passed += usize::from(gate.check(black_box(*t), i as f64 * 0.02).0.is_some());
        }
        black_box(passed)
    });

    let (layout_ns, _) = median_ns_per_sample(|| {
        let mut acc = 0.0;
        for pair in targets.windows(2) {
            let action = phone2act_core::step_from_target(&pair[0], &pair[1], 0.5, ActionMode::Relative);
            let (t, g) = phone2act_core::target_from_step(&pair[0], black_box(&action), ActionMode::Relative)
                .expect("width 7");
            acc += t.translation.x + g;
        }
        usize::from(black_box(acc) > 0.0)
    });

    println!(
        "planner + gate (TeleopArm::on_pose): {teleop_ns:.0} ns/sample (median of {BATCHES} batches of {} samples)",
        ROUNDS_PER_BATCH * SAMPLES
    );
    println!("safety gate alone (SafetyGate::check): {gate_ns:.0} ns/sample");
    println!("action round trip (step_from_target + target_from_step, relative): {layout_ns:.0} ns/sample");
    println!("(samples passed: {passed} / {gate_passed})");
}

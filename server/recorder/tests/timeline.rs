//! The recorder's timeline on a loaded machine: an arm moving on a known trajectory of time, a camera whose
//! frames carry their number, the recorder at 20 fps, and a group of busy threads (twice the cores) competing
//! for the CPU the whole time. Every recorded frame must hold the arm's state and the camera frame of its
//! own instant (captured at or before it, within the tolerance), or be counted as late (and listed in the
//! episode's events).
//!
//! Why nothing here is a timing bound that load can break: the arm's state carries its own capture time, so
//! the check is of the recorder's choice of sample, whatever the scheduler did. A frame's sample is either
//! captured within the tolerance before the frame's instant (the bound on the state follows from the
//! trajectory's speed), or the frame is counted late; a loaded machine changes how many frames are late,
//! not whether the rule holds. The two stalls injected into the robot's reads are 150 ms each, longer than
//! the 50 ms tolerance by construction, so they produce late frames on any machine.

mod common;

use common::spec;
use parking_lot::Mutex;
use phone2act_capture::camera::{FrameSlot, spawn_generated};
use phone2act_clock::monotonic_ns;
use phone2act_dataset::Format;
use phone2act_dataset::events::{EventKind, read_events};
use phone2act_dataset::parquet_io::read_rows;
use phone2act_recorder::synthetic::SyntheticRobot;
use phone2act_recorder::{Recorder, RobotSample, RobotSource, SyncConfig};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

const FPS: u32 = 20;
/// One period of the recorder: longer than the camera's (33 ms), so its frames are late only when the
/// machine held them back.
const TOLERANCE_S: f64 = 0.05;
/// The trajectory: joint 0 follows `AMPLITUDE * sin(2π f t)`; its speed is at most `AMPLITUDE * 2π f`.
const AMPLITUDE: f64 = 1.0;
const FREQUENCY_HZ: f64 = 0.5;
const SIZE: (u32, u32) = (96, 64);
/// The camera draws its frame number as 16 blocks of 6 px, black or white.
const BLOCK_PX: usize = 6;

fn trajectory(t_s: f64) -> f64 {
    AMPLITUDE * (std::f64::consts::TAU * FREQUENCY_HZ * t_s).sin()
}

/// The arm: a thread that measures the trajectory every 5 ms into a feedback cell (the newest sample wins,
/// as a bridge's feedback does). State 0 is the trajectory at the capture time, state 1 the capture time.
struct Arm {
    feedback: Mutex<Option<RobotSample>>,
    /// When reads stall for `STALL`, as a bridge call blocked on a busy machine would: the first read at or
    /// after each of these instants (monotonic ns, latest first).
    stalls_at_ns: Mutex<Vec<i64>>,
}

const STALL: Duration = Duration::from_millis(150);

impl RobotSource for Arm {
    fn sample(&self) -> Option<RobotSample> {
        let due = {
            let mut stalls = self.stalls_at_ns.lock();
            let due = stalls.last().is_some_and(|&at| monotonic_ns() >= at);
            if due {
                stalls.pop();
            }
            due
        };
        if due {
            std::thread::sleep(STALL);
        }
        self.feedback.lock().clone()
    }
}

fn measure(arm: &Arm) {
    let now = monotonic_ns();
    let t_s = now as f64 * 1e-9;
    let mut state = vec![0.0; SyntheticRobot::state_names().len()];
    state[0] = trajectory(t_s);
    state[1] = t_s;
    *arm.feedback.lock() = Some(RobotSample {
        state,
        action: vec![0.0; SyntheticRobot::action_names().len()],
        success: false,
        capture_time_ns: now,
        arms: Vec::new(),
    });
}

fn draw(seq: u64, buf: &mut Vec<u8>) {
    let (w, h) = (SIZE.0 as usize, SIZE.1 as usize);
    buf.clear();
    buf.resize(w * h * 3, 128);
    for bit in 0..16 {
        let v = if (seq >> bit) & 1 == 1 { 255 } else { 0 };
        for y in 0..h {
            for x in bit * BLOCK_PX..(bit + 1) * BLOCK_PX {
                buf[(y * w + x) * 3..(y * w + x) * 3 + 3].fill(v);
            }
        }
    }
}

fn read_seq(rgb: &[u8], width: usize) -> u64 {
    let row = 32 * width * 3;
    (0..16)
        .map(|bit| {
            let x = bit * BLOCK_PX + BLOCK_PX / 2;
            u64::from(rgb[row + x * 3] > 128) << bit
        })
        .sum()
}

/// Busy threads, twice the cores, spinning until dropped.
struct Stress {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Stress {
    fn start() -> Stress {
        let stop = Arc::new(AtomicBool::new(false));
        let n = std::thread::available_parallelism().map_or(2, std::num::NonZero::get) * 2;
        let threads = (0..n)
            .map(|_| {
                let stop = Arc::clone(&stop);
                std::thread::spawn(move || {
                    let mut x = 0u64;
                    while !stop.load(Ordering::Relaxed) {
                        x = std::hint::black_box(x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1));
                    }
                })
            })
            .collect();
        Stress { stop, threads }
    }
}

impl Drop for Stress {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

#[test]
fn under_cpu_stress_every_frame_holds_its_own_instant_or_is_counted_late() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let arm = Arc::new(Arm {
        feedback: Mutex::new(None),
        stalls_at_ns: Mutex::new(Vec::new()),
    });
    let running = Arc::new(AtomicBool::new(true));
    let measuring = {
        let (arm, running) = (Arc::clone(&arm), Arc::clone(&running));
        std::thread::spawn(move || {
            while running.load(Ordering::Relaxed) {
                measure(&arm);
                std::thread::sleep(Duration::from_millis(5));
            }
        })
    };
    // When each camera frame was drawn, by its number (the capture time is stamped just after drawing).
    let drawn_ns: Arc<Mutex<BTreeMap<u64, i64>>> = Arc::default();
    let slot = Arc::new(FrameSlot::default());
    let camera = {
        let drawn_ns = Arc::clone(&drawn_ns);
        spawn_generated(
            "front",
            SIZE.0,
            SIZE.1,
            30.0,
            move |seq, buf| {
                draw(seq, buf);
                drawn_ns.lock().insert(seq, monotonic_ns());
            },
            Arc::clone(&slot),
        )
        .unwrap()
    };
    measure(&arm);
    let mut dataset = spec(&root, Format::V30, &["front"], SIZE);
    dataset.fps = FPS;
    // H.264: decoded below by this crate's reader.
    dataset.video_codec = Some("h264".into());
    let sync = SyncConfig {
        sample_tolerance_s: TOLERANCE_S,
        ..SyncConfig::for_fps(FPS)
    };
    let rec = Recorder::open_with(
        dataset,
        Arc::clone(&arm) as Arc<dyn RobotSource>,
        vec![("front".into(), slot)],
        sync,
    )
    .unwrap();

    let stress = Stress::start();
    rec.start_episode("follow the sine").unwrap();
    let started_ns = monotonic_ns();
    *arm.stalls_at_ns.lock() = vec![started_ns + 2_500_000_000, started_ns + 1_000_000_000];
    std::thread::sleep(Duration::from_secs(5));
    let summary = rec.stop_episode().unwrap();
    drop(stress);
    rec.close().unwrap();
    running.store(false, Ordering::Relaxed);
    measuring.join().unwrap();
    camera.stop();

    let events = read_events(&root, 0).unwrap().unwrap_or_default();
    let late: BTreeMap<u64, String> = events
        .iter()
        .filter(|e| e.kind == EventKind::LateTick)
        .map(|e| (e.frame_index, e.detail.clone()))
        .collect();
    let paused: BTreeMap<u64, u64> = events
        .iter()
        .filter(|e| e.kind == EventKind::Paused)
        .map(|e| (e.frame_index, e.count))
        .collect();
    assert_eq!(late.len() as u64, summary.late_ticks, "one event per late frame");
    assert_eq!(paused.values().sum::<u64>(), summary.paused_ticks);
    // Each 150 ms stall of the robot's reads leaves a gap of at least 145 ms between two samples (the arm
    // measures every 5 ms), and the ticks more than 50 ms into it, at least one per stall, have no sample
    // within the tolerance.
    assert!(arm.stalls_at_ns.lock().is_empty(), "both stalls happened");
    assert!(summary.late_ticks >= 2, "{summary:?}");

    let rows = read_rows(&root.join("data/chunk-000/file-000.parquet")).unwrap();
    assert_eq!(rows.len() as u64, summary.length_frames);
    let video = root.join("videos/observation.images.front/chunk-000/file-000.mp4");
    let times_s: Vec<f64> = (0..rows.len()).map(|i| i as f64 / f64::from(FPS)).collect();
    let frames = phone2act_dataset::av::decode::frames_at(&video, &times_s, SIZE.0).unwrap();
    let drawn_ns = drawn_ns.lock();
    let speed_bound = AMPLITUDE * std::f64::consts::TAU * FREQUENCY_HZ;
    let mut skipped_ticks = 0;
    let mut on_time = 0;
    let mut last_seq = 0;
    for (i, row) in rows.iter().enumerate() {
        let i = i as u64;
        skipped_ticks += paused.get(&i).copied().unwrap_or(0);
        let tick_ns =
            summary.first_frame_time_ns + ((i + skipped_ticks) * 1_000_000_000 / u64::from(FPS)) as i64;
        let tick_s = tick_ns as f64 * 1e-9;
        // The capture time went through float32: a few µs of rounding at these magnitudes.
        let captured_s = f64::from(row.state[1]);
        let rounding_s = 4.0 * f64::from(f32::EPSILON) * captured_s.abs().max(1.0);
        let seq = read_seq(&frames[i as usize].rgb, SIZE.0 as usize);
        assert!(seq >= last_seq, "frame {i}: camera frame {seq} after {last_seq}");
        last_seq = seq;
        // A late frame may hold the oldest sample left when its own instant's was evicted (a tick written
        // more than a ring's span late): only frames not counted late are bound to their instant.
        if late.contains_key(&i) {
            continue;
        }
        on_time += 1;
        assert!(
            captured_s <= tick_s + rounding_s,
            "frame {i}: the state was captured {:.1} ms after the frame's instant",
            (captured_s - tick_s) * 1e3
        );
        let drawn = drawn_ns[&seq];
        assert!(
            drawn <= tick_ns,
            "frame {i}: camera frame {seq} was drawn {:.1} ms after the frame's instant",
            (drawn - tick_ns) as f64 / 1e6
        );
        assert!(
            tick_s - captured_s <= TOLERANCE_S + rounding_s,
            "frame {i} is not counted late, but its state was captured {:.1} ms before its instant",
            (tick_s - captured_s) * 1e3
        );
        // The path: the recorded joint is the trajectory at the frame's instant, within the distance the arm
        // can move in the tolerance.
        let error = (f64::from(row.state[0]) - trajectory(tick_s)).abs();
        assert!(
            error <= speed_bound * TOLERANCE_S + 1e-6,
            "frame {i}: joint {} vs the trajectory's {} at the frame's instant",
            row.state[0],
            trajectory(tick_s)
        );
    }
    // Only a machine that starved the 5 ms measuring thread for the whole episode leaves no frame on time.
    assert!(on_time > 0, "{summary:?}");
    eprintln!(
        "{} frames: {on_time} on time, {} late, {} paused, {} held",
        rows.len(),
        summary.late_ticks,
        summary.paused_ticks,
        summary.held_ticks
    );
}

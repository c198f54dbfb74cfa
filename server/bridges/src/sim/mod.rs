//! The simulated SO-101 arm: the default bridge. A [`SimWorld`] (pure state, stepped with an explicit `dt`)
//! driven by one thread at `step_hz`, commands through a latest-only slot, feedback in a shared cell, and a
//! software renderer for `sim_render` cameras.
//!
//! The thread waits on the command slot between physics ticks, so a command is solved (IK) as soon as it
//! arrives rather than at the next tick; the joints then move toward the solution with the configured
//! first-order lag.

mod config;
mod render;
mod world;

pub use config::{SimCameraConfig, SimConfig};
pub use render::Renderer;
pub use world::{BallState, CommandOutcome, IkRequest, SceneSnapshot, SimWorld};

use crate::{Bridge, BridgeError, Command, Control, Feedback, FeedbackCell, Health, LatestSlot};
use phone2act_core::kinematics::SO101_ARM_JOINT_NAMES;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// A monotonic clock in nanoseconds; the server passes its process-wide clock so feedback times compare
/// with every other `*_time_ns`.
pub type ClockFn = fn() -> i64;

/// Nanoseconds since the first call; used when no clock is supplied.
fn local_monotonic_ns() -> i64 {
    static EPOCH: OnceLock<Instant> = OnceLock::new();
    let epoch = *EPOCH.get_or_init(Instant::now);
    i64::try_from(epoch.elapsed().as_nanos()).unwrap_or(i64::MAX)
}

/// Behind by more than this many ticks (a suspended process), the thread skips ahead instead of running
/// the backlog in a burst.
const MAX_TICK_BACKLOG: u32 = 5;

struct Shared {
    world: Mutex<SimWorld>,
    commands: LatestSlot<Command>,
    feedback: FeedbackCell,
    stop: AtomicBool,
    clock: ClockFn,
}

/// The simulated arm bridge.
pub struct SimBridge {
    shared: Arc<Shared>,
    joint_names: Vec<String>,
    renderer: Mutex<Renderer>,
    thread: Mutex<Option<JoinHandle<()>>>,
}

impl std::fmt::Debug for SimBridge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimBridge")
            .field("joint_names", &self.joint_names)
            .finish_non_exhaustive()
    }
}

impl SimBridge {
    /// Starts the simulation thread with a process-local clock.
    pub fn start(config: SimConfig) -> Result<Arc<Self>, BridgeError> {
        Self::start_with_clock(config, local_monotonic_ns)
    }

    /// Starts the simulation thread; feedback is stamped with `clock`.
    pub fn start_with_clock(config: SimConfig, clock: ClockFn) -> Result<Arc<Self>, BridgeError> {
        let world = SimWorld::new(config)?;
        let step_period = Duration::from_secs_f64(1.0 / world.config().step_hz);
        let renderer = Renderer::new(&world.config().camera);
        let initial_feedback = world.feedback(clock());
        let shared = Arc::new(Shared {
            world: Mutex::new(world),
            commands: LatestSlot::default(),
            feedback: Arc::new(Mutex::new(Some(initial_feedback))),
            stop: AtomicBool::new(false),
            clock,
        });
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("sim-arm".into())
            .spawn(move || run(&thread_shared, step_period))?;
        tracing::info!(
            step_hz = 1.0 / step_period.as_secs_f64(),
            "simulated SO-101 started"
        );
        Ok(Arc::new(Self {
            shared,
            joint_names: SO101_ARM_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect(),
            renderer: Mutex::new(renderer),
            thread: Mutex::new(Some(thread)),
        }))
    }

    /// Renders the scene from the configured camera into `out` as packed RGB8 (`width × height × 3` bytes).
    /// Safe to call from any thread; the world lock is held only to copy the state.
    pub fn render_rgb(&self, width: u32, height: u32, out: &mut Vec<u8>) {
        let snapshot = self
            .shared
            .world
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .snapshot();
        self.renderer
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .render(&snapshot, width, height, out);
    }

    /// Puts the ball back at its start position (between episodes).
    pub fn reset_scene(&self) {
        self.shared
            .world
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .reset_scene();
    }

    /// The scene state (ball, gripper, links) right now.
    pub fn snapshot(&self) -> SceneSnapshot {
        self.shared
            .world
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .snapshot()
    }
}

fn run(shared: &Shared, period: Duration) {
    let mut last_step = Instant::now();
    let mut next_tick = last_step + period;
    while !shared.stop.load(Ordering::Acquire) {
        let now = Instant::now();
        if now >= next_tick {
            let dt_s = (now - last_step).as_secs_f64();
            last_step = now;
            let feedback = {
                let mut world = shared.world.lock().unwrap_or_else(PoisonError::into_inner);
                world.step(dt_s);
                world.feedback((shared.clock)())
            };
            *shared.feedback.lock().unwrap_or_else(PoisonError::into_inner) = Some(feedback);
            next_tick += period;
            if now > next_tick + period * MAX_TICK_BACKLOG {
                next_tick = now + period;
            }
            continue;
        }
        if let Some(command) = shared.commands.take_wait(next_tick - now) {
            // IK runs outside the world lock: unoptimised builds take milliseconds per solve, and the
            // renderer and feedback readers should not wait for it.
            let request = shared
                .world
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .ik_request();
            let outcome = match request {
                Some(request) => {
                    let solution = request.solve(&command);
                    shared
                        .world
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .apply_solution(&command, solution)
                }
                None => CommandOutcome::Disabled,
            };
            match outcome {
                CommandOutcome::Applied(solution) if !solution.position_reached => {
                    tracing::debug!(
                        seq = command.seq,
                        position_error_m = solution.position_error_m,
                        "sim target out of reach; moving to the closest reachable pose"
                    );
                }
                CommandOutcome::Rejected => {
                    tracing::warn!(seq = command.seq, "sim rejected a non-finite command");
                }
                _ => {}
            }
        }
    }
}

impl Bridge for SimBridge {
    fn kind(&self) -> &'static str {
        "sim"
    }

    fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    fn send(&self, command: Command) {
        self.shared.commands.put(command);
    }

    fn feedback(&self) -> Option<Feedback> {
        self.shared
            .feedback
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    fn health(&self) -> Health {
        if self.shared.stop.load(Ordering::Acquire) {
            Health::Disconnected("simulation stopped".into())
        } else {
            Health::Ready
        }
    }

    fn control(&self, request: Control) -> Result<(), BridgeError> {
        let mut world = self.shared.world.lock().unwrap_or_else(PoisonError::into_inner);
        match request {
            Control::Enable => world.set_enabled(true),
            Control::Disable => world.set_enabled(false),
            // The simulation has no error state and no link to re-establish.
            Control::ClearError | Control::Reconnect => {}
        }
        Ok(())
    }

    fn shutdown(&self) {
        self.shared.stop.store(true, Ordering::Release);
        let handle = self.thread.lock().unwrap_or_else(PoisonError::into_inner).take();
        if let Some(handle) = handle
            && handle.join().is_err()
        {
            tracing::error!("simulation thread panicked");
        }
    }
}

impl Drop for SimBridge {
    fn drop(&mut self) {
        self.shutdown();
    }
}

#[cfg(test)]
mod tests;

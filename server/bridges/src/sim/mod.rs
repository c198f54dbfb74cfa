//! The simulated SO-101 arm: the default bridge. A [`SimWorld`] (pure state, advanced to explicit times)
//! driven by one thread at `step_hz`, commands through a bounded queue, feedback in a shared cell, and a
//! software renderer for `sim_render` cameras.
//!
//! Each command is put in force at its `issue_time_ns`, in issue order: the world is advanced to that time,
//! the command solved (IK, seeded with the previous solution) and made the joint target, and the joints move
//! toward it with the configured first-order lag. A stall of the sim thread therefore delays the feedback
//! but does not change the path the arm takes. The thread wakes when a command arrives, so it is solved
//! without waiting for the next tick. The queue is bounded: when full it drops the oldest command (counted
//! in [`SimBridge::commands_dropped`]), so the newest command always wins.

mod config;
mod queue;
mod render;
mod world;

pub use config::{SimCameraConfig, SimConfig, TableArea, grasp_pose_at};
pub use render::Renderer;
pub use world::{BallState, CommandOutcome, IkRequest, SceneSnapshot, SceneState, SimWorld};

use crate::{Bridge, BridgeError, Command, Control, Feedback, FeedbackCell, Health};
use parking_lot::Mutex;
use phone2act_core::kinematics::SO101_ARM_JOINT_NAMES;
use queue::BoundedQueue;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub use phone2act_clock::ClockFn;
use phone2act_clock::monotonic_ns as local_monotonic_ns;

/// Behind by more than this many ticks (a suspended process), the thread skips ahead instead of running
/// the backlog in a burst.
const MAX_TICK_BACKLOG: u32 = 5;

struct Shared {
    world: Mutex<SimWorld>,
    commands: BoundedQueue<Command>,
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
        let world = SimWorld::new(config)?.starting_at_ns(clock());
        let step_period = Duration::from_secs_f64(1.0 / world.config().step_hz);
        let renderer = Renderer::new(&world.config().camera);
        let initial_feedback = world.feedback(world.time_ns());
        let shared = Arc::new(Shared {
            world: Mutex::new(world),
            commands: BoundedQueue::new(queue::CAPACITY),
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
        let snapshot = self.shared.world.lock().snapshot();
        self.renderer.lock().render(&snapshot, width, height, out);
    }

    /// The scene state (ball, gripper, links) right now.
    pub fn snapshot(&self) -> SceneSnapshot {
        self.shared.world.lock().snapshot()
    }

    /// Commands dropped because the queue was full (the sim thread stalled for a long time), since start.
    pub fn commands_dropped(&self) -> u64 {
        self.shared.commands.dropped()
    }
}

fn run(shared: &Shared, period: Duration) {
    let mut next_tick = Instant::now() + period;
    let mut batch = Vec::with_capacity(queue::CAPACITY);
    while !shared.stop.load(Ordering::Acquire) {
        let now = Instant::now();
        if now >= next_tick {
            catch_up(shared, &mut batch, true);
            next_tick += period;
            if now > next_tick + period * MAX_TICK_BACKLOG {
                next_tick = now + period;
            }
            continue;
        }
        if shared.commands.wait_nonempty(next_tick - now) {
            catch_up(shared, &mut batch, false);
        }
    }
}

/// Puts every queued command in force at its issue time and, on a tick, advances the world to the present
/// and publishes its feedback.
///
/// The queue is drained and the present read with the world locked, so a command is either in this batch
/// or was stamped after the present this batch advances to: the world never runs past a command it has not
/// seen, unless its sender is preempted between stamping it and handing it over.
fn catch_up(shared: &Shared, batch: &mut Vec<Command>, tick: bool) {
    let present_ns = {
        let _world = shared.world.lock();
        shared.commands.drain_into(batch);
        (shared.clock)()
    };
    for command in batch.drain(..) {
        // IK runs outside the world lock: unoptimised builds take milliseconds per solve, and the renderer
        // should not wait for it. Only this thread advances the world or sets its joint targets, so the
        // seed taken here is still the one in force when the solution is applied.
        let request = {
            let mut world = shared.world.lock();
            world.advance_to_issue(&command, present_ns);
            world.ik_request()
        };
        let outcome = match request {
            Some(request) => {
                let solution = request.solve(&command);
                shared.world.lock().apply_solution(&command, solution)
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
    if tick {
        // Published under the world lock, as a scene reset publishes its own: stored after the lock was
        // released, a tick's feedback could overwrite a reset that came in between with the world before it.
        let mut world = shared.world.lock();
        world.advance_to_ns(present_ns);
        *shared.feedback.lock() = Some(world.feedback(present_ns));
    }
}

impl Bridge for SimBridge {
    fn kind(&self) -> &'static str {
        "sim"
    }

    fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    /// Queues the command to take effect at its `issue_time_ns`; never blocks. A full queue drops its oldest.
    fn send(&self, command: Command) {
        if self.shared.commands.push(command) {
            let dropped = self.shared.commands.dropped();
            // Logged at the first drop and then every 100th, so a suspended sim does not flood the log.
            if dropped % 100 == 1 {
                tracing::warn!(
                    dropped,
                    "sim command queue full: the oldest commands were dropped"
                );
            }
        }
    }

    fn feedback(&self) -> Option<Feedback> {
        self.shared.feedback.lock().clone()
    }

    fn health(&self) -> Health {
        if self.shared.stop.load(Ordering::Acquire) {
            Health::Disconnected("simulation stopped".into())
        } else {
            Health::Ready
        }
    }

    fn control(&self, request: Control) -> Result<(), BridgeError> {
        let mut world = self.shared.world.lock();
        match request {
            Control::Enable => world.set_enabled(true),
            Control::Disable => world.set_enabled(false),
            // The simulation has no error state and no link to re-establish.
            Control::ClearError | Control::Reconnect => {}
        }
        Ok(())
    }

    fn scene(&self) -> Result<SceneState, BridgeError> {
        Ok(self.shared.world.lock().scene_state())
    }

    /// Draws a new scene (see [`SimWorld::reset_scene`]) and publishes the new state at once, so the next
    /// feedback anyone reads (the arm controller re-indexing a source, `ArmState.task_success`) is the reset
    /// world, not the one before it.
    fn reset_scene(&self, seed: Option<u64>, home_arm: bool) -> Result<SceneState, BridgeError> {
        let mut world = self.shared.world.lock();
        let now_ns = (self.shared.clock)();
        world.advance_to_ns(now_ns);
        if home_arm {
            // Commands still queued were issued before the teleport: played after it they would drag the arm
            // back toward where it was.
            let mut stale = Vec::new();
            self.shared.commands.drain_into(&mut stale);
        }
        world.reset_scene(seed, home_arm);
        *self.shared.feedback.lock() = Some(world.feedback(now_ns));
        Ok(world.scene_state())
    }

    fn shutdown(&self) {
        self.shared.stop.store(true, Ordering::Release);
        let handle = self.thread.lock().take();
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

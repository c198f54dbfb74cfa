//! The one runtime of the hardware bridges: threads, the latest-only command slot, the hold-on-fault gate,
//! published feedback and shutdown. A bridge supplies only its protocol, as a [`RobotLink`]; the rules of
//! `BRIDGE_TEMPLATE.md` are held here, once, for every link:
//!
//! - `send` never blocks: the newest target replaces one not yet written ([`LatestSlot`]).
//! - Hold on fault: while [`RobotLink::accepts_targets`] is false, a target is dropped (and counted), so
//!   the robot keeps its last one; a target with a non-finite number is never handed to the link.
//! - `applied_seq` is whatever the link confirmed with [`LinkContext::applied`]; feedback is stamped with
//!   the bridge's clock when it is published, so a link cannot publish a state without its time.
//! - `shutdown` stops and joins every thread, closes the link so blocked reads return, and is idempotent;
//!   dropping the bridge shuts it down; `control` after shutdown is an error.

use crate::sim::ClockFn;
use crate::{Bridge, BridgeError, Command, Control, Feedback, Health, LatestSlot};
use nalgebra::Isometry3;
use parking_lot::Mutex;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use tracing::warn;

/// How the runtime drives a link.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Schedule {
    /// One thread, one fixed-rate period: write (the newest target, if one came and the link accepts it,
    /// else `None`), then read. For buses where writing and reading share one line (the Feetech bus).
    Cycle { period: Duration },
    /// Two threads: one waits (up to `command_wait`) for a target and writes it; the other reads feedback
    /// as it streams. For robots with a separate feedback stream (the Dobot controller).
    Split { command_wait: Duration },
}

/// A measured robot state as a link reads it. The runtime adds the time and `applied_seq`.
#[derive(Clone, Debug, PartialEq)]
pub struct Measured {
    /// Radians, in the order of [`RobotLink::joint_names`].
    pub joint_positions_rad: Vec<f64>,
    /// Tool pose in the robot base frame.
    pub robot_from_ee: Isometry3<f64>,
    /// 0 = open, 1 = closed.
    pub gripper_position: f64,
}

/// A robot's protocol, as the runtime drives it. Every method returns within the link's own timeouts.
pub trait RobotLink: Send + Sync + 'static {
    /// "dobot", "so101".
    fn kind(&self) -> &'static str;
    fn joint_names(&self) -> &[String];
    fn supports_orientation(&self) -> bool {
        true
    }
    fn schedule(&self) -> Schedule;
    fn health(&self, ctx: &LinkContext) -> Health;
    fn warning(&self) -> Option<String> {
        None
    }
    /// True when a new target may be written. By default: health is `Ready`.
    fn accepts_targets(&self, ctx: &LinkContext) -> bool {
        self.health(ctx) == Health::Ready
    }
    /// Writes `command` (accepted and finite). With [`Schedule::Cycle`], called every period, with `None`
    /// when no new target was accepted (a link ramping toward its last target goes on). Returns false when
    /// the write failed and this period's read should be skipped.
    fn write_command(&self, ctx: &LinkContext, command: Option<&Command>) -> bool;
    /// Reads the robot's state: with [`Schedule::Split`], blocks at most the link's read timeout and returns
    /// the newest state read, if any.
    fn read_feedback(&self, ctx: &LinkContext) -> Option<Measured>;
    /// Between two waits for a target ([`Schedule::Split`]): work the command thread owns (asking a faulted
    /// robot why, for example).
    fn between_commands(&self, _ctx: &LinkContext) {}
    fn control(&self, ctx: &LinkContext, request: Control) -> Result<(), BridgeError>;
    /// Closes the link's I/O so that blocked reads return; the robot holds its last target.
    fn close(&self);
}

/// The runtime's state that a link may read: the newest feedback and the counters.
pub struct LinkContext {
    slot: LatestSlot<Command>,
    feedback: Mutex<Option<Feedback>>,
    applied_seq: AtomicU64,
    targets_held: AtomicU64,
    stop: AtomicBool,
    clock: ClockFn,
}

impl std::fmt::Debug for LinkContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkContext")
            .field("applied_seq", &self.applied_seq)
            .field("targets_held", &self.targets_held)
            .field("stop", &self.stop)
            .finish_non_exhaustive()
    }
}

impl LinkContext {
    fn new(clock: ClockFn) -> Self {
        Self {
            slot: LatestSlot::default(),
            feedback: Mutex::new(None),
            applied_seq: AtomicU64::new(0),
            targets_held: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            clock,
        }
    }

    /// The robot accepted the command with this `seq`.
    pub fn applied(&self, seq: u64) {
        self.applied_seq.store(seq, Ordering::SeqCst);
    }

    pub fn applied_seq(&self) -> u64 {
        self.applied_seq.load(Ordering::SeqCst)
    }

    /// True once any feedback has been published.
    pub fn has_feedback(&self) -> bool {
        self.feedback.lock().is_some()
    }

    /// Targets dropped because the link did not accept them or they were not finite (the arm held).
    pub fn targets_held(&self) -> u64 {
        self.targets_held.load(Ordering::Relaxed)
    }

    /// Targets replaced by a newer one before they were written.
    pub fn targets_superseded(&self) -> u64 {
        self.slot.superseded()
    }

    /// The bridge's clock, nanoseconds.
    pub fn now_ns(&self) -> i64 {
        (self.clock)()
    }

    pub fn stopping(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    fn publish(&self, measured: Measured) {
        *self.feedback.lock() = Some(Feedback {
            capture_time_ns: self.now_ns(),
            joint_positions_rad: measured.joint_positions_rad,
            robot_from_ee: measured.robot_from_ee,
            gripper_position: measured.gripper_position,
            applied_seq: self.applied_seq(),
            task_success: false,
        });
    }

    fn hold(&self, command: &Command, why: &str) {
        self.targets_held.fetch_add(1, Ordering::Relaxed);
        tracing::debug!(seq = command.seq, why, "bridge: target held");
    }
}

/// True if every number of `command` is finite: the pose, the gripper target and any joint targets.
pub fn command_is_finite(command: &Command) -> bool {
    let t = command.robot_from_target.translation.vector;
    let q = command.robot_from_target.rotation.quaternion().coords;
    t.iter().chain(q.iter()).all(|v| v.is_finite())
        && command.gripper_target.is_finite()
        && command
            .joint_targets_rad
            .as_deref()
            .is_none_or(|joints| joints.iter().all(|v| v.is_finite()))
}

/// A hardware bridge: a [`RobotLink`] driven by the runtime's threads.
pub struct ThreadedBridge<L: RobotLink> {
    link: Arc<L>,
    ctx: Arc<LinkContext>,
    threads: Mutex<Vec<JoinHandle<()>>>,
}

impl<L: RobotLink + std::fmt::Debug> std::fmt::Debug for ThreadedBridge<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ThreadedBridge")
            .field("link", &self.link)
            .field("ctx", &self.ctx)
            .finish_non_exhaustive()
    }
}

impl<L: RobotLink> ThreadedBridge<L> {
    /// Starts the threads of `link`'s schedule.
    pub fn spawn(link: L, clock: ClockFn) -> Result<Self, BridgeError> {
        let link = Arc::new(link);
        let ctx = Arc::new(LinkContext::new(clock));
        let bridge = Self {
            link,
            ctx,
            threads: Mutex::new(Vec::new()),
        };
        let kind = bridge.link.kind();
        let spawn = |name: String, body: fn(&L, &LinkContext)| -> Result<JoinHandle<()>, BridgeError> {
            let (link, ctx) = (Arc::clone(&bridge.link), Arc::clone(&bridge.ctx));
            std::thread::Builder::new()
                .name(name)
                .spawn(move || body(&link, &ctx))
                .map_err(BridgeError::Io)
        };
        let spawned = match bridge.link.schedule() {
            Schedule::Cycle { .. } => vec![spawn(format!("{kind}-cycle"), run_cycle::<L>)],
            Schedule::Split { .. } => vec![
                spawn(format!("{kind}-command"), run_commands::<L>),
                spawn(format!("{kind}-feedback"), run_feedback::<L>),
            ],
        };
        for handle in spawned {
            match handle {
                Ok(h) => bridge.threads.lock().push(h),
                Err(e) => {
                    bridge.stop();
                    return Err(e);
                }
            }
        }
        Ok(bridge)
    }

    /// The protocol side, for a bridge's own methods (stats, diagnostics).
    pub fn link(&self) -> &L {
        &self.link
    }

    pub fn context(&self) -> &LinkContext {
        &self.ctx
    }

    fn stop(&self) {
        if self.ctx.stop.swap(true, Ordering::SeqCst) {
            return;
        }
        // Close first, so a thread blocked on the robot returns now rather than at its timeout.
        self.link.close();
        let threads = std::mem::take(&mut *self.threads.lock());
        for handle in threads {
            // A link may shut its bridge down from its own thread; that one cannot join itself.
            if handle.thread().id() != std::thread::current().id() {
                let _ = handle.join();
            }
        }
    }
}

impl<L: RobotLink> Drop for ThreadedBridge<L> {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Takes the newest target if there is one and the link accepts it; a refused or non-finite one is held.
fn gated(link: &impl RobotLink, ctx: &LinkContext, command: Option<Command>) -> Option<Command> {
    let command = command?;
    if !link.accepts_targets(ctx) {
        ctx.hold(&command, "not ready");
        return None;
    }
    if !command_is_finite(&command) {
        warn!(
            seq = command.seq,
            kind = link.kind(),
            "bridge: non-finite target dropped; arm holds"
        );
        ctx.hold(&command, "not finite");
        return None;
    }
    Some(command)
}

fn run_cycle<L: RobotLink>(link: &L, ctx: &LinkContext) {
    let Schedule::Cycle { period } = link.schedule() else {
        return;
    };
    let mut next = Instant::now();
    while !ctx.stopping() {
        let command = gated(link, ctx, ctx.slot.take());
        if link.write_command(ctx, command.as_ref())
            && let Some(measured) = link.read_feedback(ctx)
        {
            ctx.publish(measured);
        }
        next += period;
        let now = Instant::now();
        match next.checked_duration_since(now) {
            Some(rest) => std::thread::sleep(rest),
            // A late wake-up is made up by the next periods; a stall longer than a period is not, so the
            // robot never sees a burst.
            None if now.duration_since(next) > period => next = now,
            None => {}
        }
    }
}

fn run_commands<L: RobotLink>(link: &L, ctx: &LinkContext) {
    let Schedule::Split { command_wait } = link.schedule() else {
        return;
    };
    while !ctx.stopping() {
        link.between_commands(ctx);
        if let Some(command) = gated(link, ctx, ctx.slot.take_wait(command_wait)) {
            link.write_command(ctx, Some(&command));
        }
    }
}

fn run_feedback<L: RobotLink>(link: &L, ctx: &LinkContext) {
    while !ctx.stopping() {
        if let Some(measured) = link.read_feedback(ctx) {
            ctx.publish(measured);
        }
    }
}

impl<L: RobotLink> Bridge for ThreadedBridge<L> {
    fn kind(&self) -> &'static str {
        self.link.kind()
    }

    fn joint_names(&self) -> &[String] {
        self.link.joint_names()
    }

    fn supports_orientation(&self) -> bool {
        self.link.supports_orientation()
    }

    fn send(&self, command: Command) {
        self.ctx.slot.put(command);
    }

    fn feedback(&self) -> Option<Feedback> {
        self.ctx.feedback.lock().clone()
    }

    fn health(&self) -> Health {
        self.link.health(&self.ctx)
    }

    fn warning(&self) -> Option<String> {
        self.link.warning()
    }

    fn control(&self, request: Control) -> Result<(), BridgeError> {
        if self.ctx.stopping() {
            return Err(BridgeError::Protocol("bridge is shut down".into()));
        }
        self.link.control(&self.ctx, request)
    }

    fn shutdown(&self) {
        self.stop();
    }
}

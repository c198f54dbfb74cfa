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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A link that records what the runtime asks of it.
    #[derive(Debug)]
    struct Toy {
        schedule: Schedule,
        accepting: AtomicBool,
        write_ok: AtomicBool,
        written: Mutex<Vec<Option<u64>>>,
        reads: AtomicU64,
        between: AtomicU64,
        closes: AtomicU64,
        names: Vec<String>,
        /// While set, the command thread waits in `between_commands`.
        gate: AtomicBool,
        /// A write sleeps this long once (a stalled bus), then the field is zero again.
        stall_once_ms: AtomicU64,
        /// When each write began.
        write_times: Mutex<Vec<Instant>>,
    }

    impl Toy {
        fn new(schedule: Schedule) -> Self {
            Self {
                schedule,
                accepting: AtomicBool::new(true),
                write_ok: AtomicBool::new(true),
                written: Mutex::new(Vec::new()),
                reads: AtomicU64::new(0),
                between: AtomicU64::new(0),
                closes: AtomicU64::new(0),
                names: vec!["a".into(), "b".into()],
                gate: AtomicBool::new(false),
                stall_once_ms: AtomicU64::new(0),
                write_times: Mutex::new(Vec::new()),
            }
        }

        fn written_seqs(&self) -> Vec<u64> {
            self.written.lock().iter().flatten().copied().collect()
        }
    }

    impl RobotLink for Toy {
        fn kind(&self) -> &'static str {
            "toy"
        }
        fn joint_names(&self) -> &[String] {
            &self.names
        }
        fn supports_orientation(&self) -> bool {
            false
        }
        fn schedule(&self) -> Schedule {
            self.schedule
        }
        fn health(&self, _ctx: &LinkContext) -> Health {
            if self.accepting.load(Ordering::SeqCst) {
                Health::Ready
            } else {
                Health::Error("toy fault".into())
            }
        }
        fn warning(&self) -> Option<String> {
            Some("toy warning".into())
        }
        fn write_command(&self, ctx: &LinkContext, command: Option<&Command>) -> bool {
            self.write_times.lock().push(Instant::now());
            let stall_ms = self.stall_once_ms.swap(0, Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(stall_ms));
            self.written.lock().push(command.map(|c| c.seq));
            if let Some(c) = command {
                ctx.applied(c.seq);
            }
            self.write_ok.load(Ordering::SeqCst)
        }
        fn read_feedback(&self, _ctx: &LinkContext) -> Option<Measured> {
            if matches!(self.schedule, Schedule::Split { .. }) {
                // The pace of a streaming robot; counted after it, so a thread left running past
                // shutdown shows in `reads`.
                std::thread::sleep(Duration::from_millis(1));
            }
            let n = self.reads.fetch_add(1, Ordering::SeqCst);
            Some(Measured {
                joint_positions_rad: vec![n as f64, 0.0],
                robot_from_ee: Isometry3::identity(),
                gripper_position: 0.5,
            })
        }
        fn between_commands(&self, _ctx: &LinkContext) {
            self.between.fetch_add(1, Ordering::SeqCst);
            while self.gate.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        fn control(&self, _ctx: &LinkContext, request: Control) -> Result<(), BridgeError> {
            match request {
                Control::ClearError => Ok(()),
                other => Err(BridgeError::Unsupported(format!("{other:?}"))),
            }
        }
        fn close(&self) {
            self.closes.fetch_add(1, Ordering::SeqCst);
        }
    }

    fn clock() -> i64 {
        42
    }

    fn command(seq: u64) -> Command {
        Command {
            seq,
            robot_from_target: Isometry3::from_parts(
                Translation3::new(0.1, 0.2, 0.3),
                UnitQuaternion::identity(),
            ),
            gripper_target: 0.0,
            issue_time_ns: 0,
            joint_targets_rad: None,
        }
    }

    /// Waits on the condition; every bound here is a deadline for something that happens within
    /// milliseconds, generous for a loaded machine.
    fn wait_for(what: &str, mut f: impl FnMut() -> bool) {
        let deadline = Instant::now() + Duration::from_secs(5);
        while !f() {
            assert!(Instant::now() < deadline, "timed out waiting for {what}");
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    const SPLIT: Schedule = Schedule::Split {
        command_wait: Duration::from_millis(5),
    };
    const CYCLE: Schedule = Schedule::Cycle {
        period: Duration::from_millis(2),
    };

    #[test]
    fn non_finite_numbers_anywhere_in_a_command_are_caught() {
        assert!(command_is_finite(&command(1)));
        let mut c = command(1);
        c.robot_from_target.translation.vector.x = f64::NAN;
        assert!(!command_is_finite(&c));
        let mut c = command(1);
        c.robot_from_target.rotation =
            UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(f64::INFINITY, 0.0, 0.0, 0.0));
        assert!(!command_is_finite(&c));
        let mut c = command(1);
        c.gripper_target = f64::NAN;
        assert!(!command_is_finite(&c));
        let mut c = command(1);
        c.joint_targets_rad = Some(vec![0.0, f64::NEG_INFINITY]);
        assert!(!command_is_finite(&c));
        c.joint_targets_rad = Some(vec![0.0, 1.0]);
        assert!(command_is_finite(&c));
    }

    #[test]
    fn targets_are_written_only_while_the_link_accepts_them_and_only_when_finite() {
        for schedule in [SPLIT, CYCLE] {
            let bridge = ThreadedBridge::spawn(Toy::new(schedule), clock).unwrap();
            let toy = bridge.link();
            toy.accepting.store(false, Ordering::SeqCst);
            bridge.send(command(1));
            wait_for("the refused target held", || bridge.context().targets_held() == 1);
            let mut bad = command(2);
            bad.gripper_target = f64::NAN;
            toy.accepting.store(true, Ordering::SeqCst);
            bridge.send(bad);
            wait_for("the non-finite target held", || {
                bridge.context().targets_held() == 2
            });
            bridge.send(command(3));
            wait_for("the good target written", || toy.written_seqs() == vec![3]);
            wait_for("feedback naming it", || {
                bridge.feedback().is_some_and(|f| f.applied_seq == 3)
            });
            let f = bridge.feedback().unwrap();
            assert_eq!(f.capture_time_ns, 42, "stamped with the bridge's clock");
            assert!((f.gripper_position - 0.5).abs() < 1e-12, "the link's gripper");
            assert!(!f.task_success);
            assert_eq!(bridge.context().applied_seq(), 3);
            assert!(bridge.context().has_feedback());
        }
    }

    #[test]
    fn only_the_newest_of_several_unsent_targets_is_written() {
        let toy = Toy::new(SPLIT);
        // The command thread starts held in `between_commands`, so all three targets wait in the slot.
        toy.gate.store(true, Ordering::SeqCst);
        let bridge = ThreadedBridge::spawn(toy, clock).unwrap();
        wait_for("the command thread held", || {
            bridge.link().between.load(Ordering::SeqCst) == 1
        });
        bridge.send(command(1));
        bridge.send(command(2));
        bridge.send(command(3));
        bridge.link().gate.store(false, Ordering::SeqCst);
        wait_for("a target written", || !bridge.link().written_seqs().is_empty());
        assert_eq!(bridge.link().written_seqs(), vec![3]);
        assert_eq!(bridge.context().targets_superseded(), 2);
        assert_eq!(bridge.context().targets_held(), 0);
    }

    #[test]
    fn a_failed_cycle_write_skips_the_read_and_a_cycle_runs_without_a_target() {
        let toy = Toy::new(CYCLE);
        toy.write_ok.store(false, Ordering::SeqCst);
        let bridge = ThreadedBridge::spawn(toy, clock).unwrap();
        wait_for("cycles", || bridge.link().written.lock().len() >= 5);
        assert_eq!(bridge.link().reads.load(Ordering::SeqCst), 0);
        assert!(bridge.feedback().is_none());
        assert!(!bridge.context().has_feedback());
        assert!(bridge.link().written.lock().iter().all(Option::is_none));
        bridge.link().write_ok.store(true, Ordering::SeqCst);
        wait_for("reads", || bridge.link().reads.load(Ordering::SeqCst) >= 2);
        assert_eq!(
            bridge.link().between.load(Ordering::SeqCst),
            0,
            "no command thread in a cycle"
        );
    }

    /// A cycle never runs early: after a stall of 20 periods the cycles resume on the period, not in a
    /// burst that makes up for the stall. Sleeping never ends early, so the upper bound holds however
    /// loaded the machine is.
    #[test]
    fn cycles_keep_their_period_and_a_stall_is_not_made_up_in_a_burst() {
        let period = Duration::from_millis(2);
        let bridge = ThreadedBridge::spawn(Toy::new(Schedule::Cycle { period }), clock).unwrap();
        let toy = bridge.link();
        wait_for("cycles", || toy.write_times.lock().len() >= 3);
        toy.stall_once_ms.store(40, Ordering::SeqCst);
        let stalled_from = toy.write_times.lock().len();
        wait_for("the stall and 20 ms after it", || {
            let times = toy.write_times.lock();
            times.len() > stalled_from + 1
                && times[stalled_from + 1..]
                    .last()
                    .is_some_and(|t| t.duration_since(times[stalled_from + 1]) >= Duration::from_millis(20))
        });
        let times = toy.write_times.lock().clone();
        let after = &times[stalled_from + 1..];
        let window = Duration::from_millis(20);
        let in_window = after
            .iter()
            .filter(|t| t.duration_since(after[0]) <= window)
            .count();
        // 20 ms at 2 ms is 10 periods; one late wake-up may be made up (+1), plus the first write.
        assert!(in_window <= 12, "{in_window} cycles in 20 ms at a 2 ms period");
    }

    #[test]
    fn the_split_schedule_reads_while_the_command_thread_waits() {
        let bridge = ThreadedBridge::spawn(Toy::new(SPLIT), clock).unwrap();
        wait_for("reads", || bridge.link().reads.load(Ordering::SeqCst) >= 3);
        wait_for("waits between commands", || {
            bridge.link().between.load(Ordering::SeqCst) >= 2
        });
        assert!(
            bridge.link().written.lock().is_empty(),
            "nothing written without a target"
        );
    }

    #[test]
    fn the_bridge_speaks_for_its_link() {
        let bridge = ThreadedBridge::spawn(Toy::new(SPLIT), clock).unwrap();
        assert_eq!(bridge.kind(), "toy");
        let debug = format!("{bridge:?}");
        assert!(
            debug.contains("ThreadedBridge") && debug.contains("applied_seq"),
            "{debug}"
        );
        assert_eq!(bridge.joint_names(), ["a", "b"]);
        assert!(!bridge.supports_orientation());
        assert_eq!(bridge.warning().as_deref(), Some("toy warning"));
        assert_eq!(bridge.health(), Health::Ready);
        bridge.link().accepting.store(false, Ordering::SeqCst);
        assert_eq!(bridge.health(), Health::Error("toy fault".into()));
        bridge.control(Control::ClearError).unwrap();
        assert!(matches!(
            bridge.control(Control::Enable),
            Err(BridgeError::Unsupported(_))
        ));
    }

    #[test]
    fn shutdown_closes_once_stops_every_thread_and_refuses_control() {
        let bridge = ThreadedBridge::spawn(Toy::new(SPLIT), clock).unwrap();
        wait_for("running", || bridge.link().reads.load(Ordering::SeqCst) > 0);
        bridge.shutdown();
        bridge.shutdown();
        assert_eq!(bridge.link().closes.load(Ordering::SeqCst), 1);
        assert!(bridge.threads.lock().is_empty(), "threads joined");
        let reads = bridge.link().reads.load(Ordering::SeqCst);
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(
            bridge.link().reads.load(Ordering::SeqCst),
            reads,
            "a thread still runs"
        );
        assert!(matches!(
            bridge.control(Control::ClearError),
            Err(BridgeError::Protocol(m)) if m.contains("shut down")
        ));
        bridge.send(command(9));
        std::thread::sleep(Duration::from_millis(20));
        assert!(bridge.link().written.lock().is_empty(), "written after shutdown");
    }

    #[test]
    fn dropping_the_bridge_shuts_it_down() {
        let bridge = ThreadedBridge::spawn(Toy::new(CYCLE), clock).unwrap();
        let link = Arc::clone(&bridge.link);
        drop(bridge);
        assert_eq!(link.closes.load(Ordering::SeqCst), 1);
        let reads = link.reads.load(Ordering::SeqCst);
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(link.reads.load(Ordering::SeqCst), reads);
    }
}

//! Robot bridges behind one [`Bridge`] trait: the simulated SO-101 arm, the Dobot CR5 over TCP, the SO-101 over
//! a Feetech servo bus, and remote bridges attached over gRPC; plus, behind the `emulators` feature, the
//! protocol emulators (Dobot controller, Feetech bus) that the tests and bridge-bench run against.
//!
//! Bridges run on their own threads and never block the caller: [`Bridge::send`] hands the command over without
//! waiting (hardware bridges keep a latest-only slot, where a newer command replaces an unsent older one; the sim
//! keeps a small bounded queue so that it can put each command in force at its issue time), and
//! [`Bridge::feedback`] returns the newest measured state.

pub mod dobot;
pub mod feetech;
pub mod remote;
pub mod runtime;
pub mod scene;
pub mod sim;
pub mod so101;

use nalgebra::Isometry3;
use parking_lot::{Condvar, Mutex};
use std::sync::Arc;
use std::time::Duration;

/// A target for the robot, already through the safety gate.
#[derive(Clone, Debug, PartialEq)]
pub struct Command {
    /// Increasing sequence number assigned by the arm controller.
    pub seq: u64,
    /// Target end-effector pose in the robot base frame (metres, unit quaternion).
    pub robot_from_target: Isometry3<f64>,
    /// Gripper target: 0 = open, 1 = closed.
    pub gripper_target: f64,
    /// Server monotonic time the command was issued.
    pub issue_time_ns: i64,
    /// The joints to drive to (radians, in the order of [`Bridge::joint_names`]), when the server solved the
    /// target for an arm whose kinematics it knows: already through the joint rate limits, so the robot, the
    /// recorded action and the next solve's seed are the same joints. `None`: the bridge solves the pose
    /// itself (remote bridges, and callers other than the server).
    pub joint_targets_rad: Option<Vec<f64>>,
}

/// Measured robot state.
#[derive(Clone, Debug, PartialEq)]
pub struct Feedback {
    /// Server monotonic time the state was measured (or received from the robot).
    pub capture_time_ns: i64,
    /// Joint positions in radians, in the order of [`Bridge::joint_names`].
    pub joint_positions_rad: Vec<f64>,
    /// Measured end-effector pose in the robot base frame.
    pub robot_from_ee: Isometry3<f64>,
    /// 0 = open, 1 = closed.
    pub gripper_position: f64,
    /// `seq` of the newest command the robot has applied (0 before any).
    pub applied_seq: u64,
    /// Task success flag (the simulated scene's ball-in-basket); false for real robots.
    pub task_success: bool,
}

/// Connection state of a bridge.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Health {
    Connecting,
    Ready,
    /// Connected, but the robot reports an error (robot mode, servo alarm, ...).
    Error(String),
    /// Not connected; the string says why (refused, timed out, dropped).
    Disconnected(String),
}

impl Feedback {
    /// This feedback as the pure core reads it (the arm's snapshot, its recorded sample).
    pub fn reading(&self) -> phone2act_core::Reading<'_> {
        phone2act_core::Reading {
            joint_positions_rad: &self.joint_positions_rad,
            robot_from_ee: &self.robot_from_ee,
            gripper_position: self.gripper_position,
            capture_time_ns: self.capture_time_ns,
            task_success: self.task_success,
        }
    }
}

impl From<Health> for phone2act_core::BridgeHealth {
    fn from(health: Health) -> Self {
        match health {
            Health::Ready => Self::Ready,
            Health::Connecting => Self::Connecting,
            Health::Error(m) => Self::Error(m),
            Health::Disconnected(m) => Self::Disconnected(m),
        }
    }
}

/// Out-of-band requests.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Control {
    Enable,
    Disable,
    ClearError,
    Reconnect,
}

/// Errors a bridge reports when it is created or controlled.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("cannot connect to {target}: {message}")]
    Connect { target: String, message: String },
    #[error("protocol error: {0}")]
    Protocol(String),
    #[error("invalid bridge configuration: {0}")]
    Config(String),
    /// The bridge has no such feature (a hardware arm asked for a scene reset); the text says which.
    #[error("{0}")]
    Unsupported(String),
    #[error("I/O: {0}")]
    Io(#[from] std::io::Error),
}

/// A robot bridge. Implementations own their I/O threads; every method returns promptly.
pub trait Bridge: Send + Sync {
    /// "sim", "dobot", "so101", "remote".
    fn kind(&self) -> &'static str;
    /// Joint names in feedback order.
    fn joint_names(&self) -> &[String];
    /// True if the robot follows orientation; false for position-only arms.
    fn supports_orientation(&self) -> bool {
        true
    }
    /// Hands a command to the bridge. Never blocks; the newest command is the one the robot ends on.
    fn send(&self, command: Command);
    /// The newest measured state, if any has arrived.
    fn feedback(&self) -> Option<Feedback>;
    /// Current connection state.
    fn health(&self) -> Health;
    /// Something the operator should know while the robot keeps working (a servo alarm that does not stop
    /// the arm), naming the part and the reason. Shown beside a `Ready` health.
    fn warning(&self) -> Option<String> {
        None
    }
    /// Enable, disable, clear an error, or reconnect.
    fn control(&self, request: Control) -> Result<(), BridgeError>;
    /// The task scene around the arm (the simulator's ball and basket). Real arms have none.
    fn scene(&self) -> Result<scene::SceneState, BridgeError> {
        Err(BridgeError::Unsupported(format!(
            "scene state is not supported by the {} bridge",
            self.kind()
        )))
    }
    /// Re-draws the scene from `seed` (or the next seed of the arm's sequence); `home_arm` also teleports
    /// the arm to its initial joints. Only a simulator can do either: real arms answer `Unsupported`.
    fn reset_scene(&self, seed: Option<u64>, home_arm: bool) -> Result<scene::SceneState, BridgeError> {
        let _ = (seed, home_arm);
        Err(BridgeError::Unsupported(format!(
            "scene reset is not supported by the {} bridge",
            self.kind()
        )))
    }
    /// Stops the bridge's threads; the robot holds. Idempotent.
    fn shutdown(&self);
}

/// A latest-only slot: `put` replaces the value, `take_wait` blocks a bridge thread until a value is there.
/// This is the paper's BEST_EFFORT depth-1 queue: a slow robot link only ever sees the newest command.
#[derive(Debug)]
pub struct LatestSlot<T> {
    value: Mutex<(Option<T>, u64)>,
    ready: Condvar,
}

impl<T> Default for LatestSlot<T> {
    fn default() -> Self {
        Self {
            value: Mutex::new((None, 0)),
            ready: Condvar::new(),
        }
    }
}

impl<T> LatestSlot<T> {
    /// Stores `value`, replacing any value not yet taken. Returns true if an older value was superseded.
    pub fn put(&self, value: T) -> bool {
        let mut guard = self.value.lock();
        let superseded = guard.0.replace(value).is_some();
        if superseded {
            guard.1 += 1;
        }
        drop(guard);
        self.ready.notify_one();
        superseded
    }

    /// Takes the value if there is one.
    pub fn take(&self) -> Option<T> {
        self.value.lock().0.take()
    }

    /// Takes the value, waiting up to `timeout` for one.
    pub fn take_wait(&self, timeout: Duration) -> Option<T> {
        let mut guard = self.value.lock();
        self.ready.wait_while_for(&mut guard, |v| v.0.is_none(), timeout);
        guard.0.take()
    }

    /// Values replaced before anyone took them, since creation.
    pub fn superseded(&self) -> u64 {
        self.value.lock().1
    }
}

/// A shared latest-feedback cell used by bridge threads to publish and by [`Bridge::feedback`] to read.
pub type FeedbackCell = Arc<Mutex<Option<Feedback>>>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latest_slot_keeps_only_the_newest() {
        let slot = LatestSlot::default();
        assert!(!slot.put(1));
        assert!(slot.put(2));
        assert!(slot.put(3));
        assert_eq!(slot.take(), Some(3));
        assert_eq!(slot.take(), None);
        assert_eq!(slot.superseded(), 2);
    }

    #[test]
    fn latest_slot_wakes_a_waiting_taker() {
        let slot = Arc::new(LatestSlot::default());
        let producer = Arc::clone(&slot);
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            producer.put(7u32);
        });
        assert_eq!(slot.take_wait(Duration::from_secs(2)), Some(7));
        t.join().unwrap();
        assert_eq!(slot.take_wait(Duration::from_millis(10)), None);
    }
}

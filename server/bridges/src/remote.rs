//! The remote bridge: an arm whose robot link lives in another process, attached over the server's
//! `Bridge.Attach` stream. This crate knows nothing of gRPC; the server's handler drives an
//! [`AttachHandle`] with plain blocking calls (from `spawn_blocking` or a dedicated thread):
//!
//! ```text
//! let handle = Arc::new(remote.attach(hello.joint_names, hello.supports_orientation)?);
//! // downstream thread: loop { match handle.next(timeout) { Ok(Some(msg)) => send msg, Ok(None) => continue,
//! //                                                       Err(_) => end the stream } }
//! // upstream task:     feedback => handle.publish_feedback(fb)?, status => handle.report_health(h)?
//! // stream end:        handle.detach()   (also done when the last handle is dropped)
//! ```
//!
//! Commands are latest-only (a slow remote only ever sees the newest target). Commands sent while no
//! remote is attached are dropped, not queued: a target from before a reconnect must not move the arm
//! after it. A new attach replaces the old one; the old handle's waits end with [`RemoteError::Superseded`].

use crate::scene::SceneState;
use crate::{Bridge, BridgeError, Command, Control, Feedback, Health};
use parking_lot::{Condvar, Mutex};
use std::collections::VecDeque;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

/// Control requests waiting for the remote beyond this are dropped oldest first; they are rare and a
/// backlog of stale enable/disable toggles is worse than losing the oldest.
const MAX_PENDING_CONTROLS: usize = 16;

/// How long a forwarded scene reset waits for the bridge's answer. A simulator re-draws its scene in well
/// under a second; 10 s leaves room for a bridge starved on a loaded machine, and a bridge that never
/// answers costs the caller only this wait (the arm holds meanwhile).
pub const SCENE_RESET_TIMEOUT: Duration = Duration::from_secs(10);

/// Why a remote-bridge call failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RemoteError {
    #[error("a bridge must name at least one joint")]
    NoJoints,
    #[error("joint names {got:?} differ from the arm's {expected:?}")]
    JointNamesMismatch { expected: Vec<String>, got: Vec<String> },
    #[error("invalid feedback: {0}")]
    InvalidFeedback(String),
    #[error("another bridge attached to this arm and replaced this one")]
    Superseded,
    #[error("this bridge detached")]
    Detached,
    #[error("the arm is shut down")]
    ShutDown,
    #[error("a scene report from a bridge whose hello did not set has_scene")]
    UndeclaredScene,
}

/// A message for the remote bridge.
#[derive(Clone, Debug, PartialEq)]
pub enum Downstream {
    Command(Command),
    Control(Control),
    /// `Scene.Reset` for a bridge that owns its scene; answered through [`AttachHandle::publish_scene`].
    SceneReset(SceneReset),
}

/// A scene reset forwarded to the remote bridge.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SceneReset {
    pub request_id: u64,
    pub seed: Option<u64>,
    pub home_arm: bool,
}

/// The remote side of the arm's scene (bridges that simulate one, see [`AttachHandle::declare_scene`]).
#[derive(Debug, Default)]
struct RemoteScene {
    /// The attached bridge declared a scene; kept after it detaches, so the scene reads as unavailable rather
    /// than absent until a bridge without one attaches.
    declared: bool,
    /// The newest scene the bridge reported.
    state: Option<SceneState>,
    /// Resets waiting to go down, and the id of the last one handed out.
    pending: VecDeque<SceneReset>,
    last_request_id: u64,
    /// The newest answer: the request it answers and the scene, or the bridge's reason for failing.
    answer: Option<(u64, Result<SceneState, String>)>,
    /// A reset that homes the arm, asked for and not answered yet: the bridge places the arm at home in one
    /// step, which its joints' speeds must not be judged by.
    homing: Option<u64>,
}

#[derive(Debug)]
struct State {
    /// Incremented by every attach; a handle is current while its generation matches and `attached` holds.
    generation: u64,
    attached: bool,
    command: Option<Command>,
    controls: VecDeque<Control>,
    feedback: Option<Feedback>,
    /// Why the last feedback was refused; cleared by the next valid one.
    feedback_problem: Option<String>,
    health: Health,
    supports_orientation: bool,
    shut_down: bool,
    /// The arm's joint speed limits, checked against the measured joints (the remote robot solves and moves
    /// its own joints, so the server cannot enforce them: docs/joint-limits.md).
    speed_watch: Option<phone2act_core::joint_limit::JointSpeedWatch>,
    /// The last joint measured over its limit, for [`Bridge::warning`].
    overspeed: Option<String>,
    scene: RemoteScene,
}

#[derive(Debug)]
struct Shared {
    state: Mutex<State>,
    changed: Condvar,
    /// Fixed by the first attach (or the constructor): `Bridge::joint_names` returns a borrowed slice.
    joint_names: OnceLock<Vec<String>>,
}

impl Shared {
    /// Ok if `generation` is the live attachment.
    fn check(state: &State, generation: u64) -> Result<(), RemoteError> {
        if state.shut_down {
            Err(RemoteError::ShutDown)
        } else if state.generation != generation {
            Err(RemoteError::Superseded)
        } else if !state.attached {
            Err(RemoteError::Detached)
        } else {
            Ok(())
        }
    }
}

/// An arm driven by an out-of-process bridge.
#[derive(Debug)]
pub struct RemoteBridge {
    arm: String,
    shared: Arc<Shared>,
}

impl RemoteBridge {
    /// A remote arm whose joint names are taken from the first bridge that attaches.
    pub fn new(arm: impl Into<String>) -> Arc<Self> {
        Self::build(arm.into(), OnceLock::new())
    }

    /// A remote arm with known joint names; a bridge naming others is refused.
    pub fn with_joint_names(arm: impl Into<String>, joint_names: Vec<String>) -> Arc<Self> {
        Self::build(arm.into(), OnceLock::from(joint_names))
    }

    fn build(arm: String, joint_names: OnceLock<Vec<String>>) -> Arc<Self> {
        Arc::new(Self {
            arm,
            shared: Arc::new(Shared {
                state: Mutex::new(State {
                    generation: 0,
                    attached: false,
                    command: None,
                    controls: VecDeque::new(),
                    feedback: None,
                    feedback_problem: None,
                    health: Health::Disconnected("no remote bridge attached".into()),
                    supports_orientation: true,
                    shut_down: false,
                    speed_watch: None,
                    overspeed: None,
                    scene: RemoteScene::default(),
                }),
                changed: Condvar::new(),
                joint_names,
            }),
        })
    }

    /// Checks every measured joint against these speed limits (rad/s, one per joint): a joint measured faster
    /// is counted and shown as the bridge's warning. Checked, not enforced: the remote robot moves its own
    /// joints.
    pub fn watch_joint_speeds(&self, max_velocity_rad_s: Vec<f64>) -> Result<(), BridgeError> {
        let watch = phone2act_core::joint_limit::JointSpeedWatch::new(max_velocity_rad_s)
            .map_err(|e| BridgeError::Config(e.to_string()))?;
        self.shared.state.lock().speed_watch = Some(watch);
        Ok(())
    }

    /// Feedback samples whose joints were measured over their speed limits, since start.
    pub fn joint_overspeeds(&self) -> u64 {
        self.shared
            .state
            .lock()
            .speed_watch
            .as_ref()
            .map_or(0, |w| w.overspeeds)
    }

    /// The arm name this bridge serves.
    pub fn arm(&self) -> &str {
        &self.arm
    }

    /// Attaches a remote bridge, replacing any attached one. The joint names must match the arm's (the first
    /// attach defines them unless the constructor did).
    pub fn attach(
        &self,
        joint_names: Vec<String>,
        supports_orientation: bool,
    ) -> Result<AttachHandle, RemoteError> {
        if joint_names.is_empty() {
            return Err(RemoteError::NoJoints);
        }
        let mut state = self.shared.state.lock();
        if state.shut_down {
            return Err(RemoteError::ShutDown);
        }
        // Checked and set under the state lock so two racing first attaches cannot both define the names.
        let expected = self.shared.joint_names.get_or_init(|| joint_names.clone());
        if *expected != joint_names {
            return Err(RemoteError::JointNamesMismatch {
                expected: expected.clone(),
                got: joint_names,
            });
        }
        let replaced = state.attached;
        state.generation += 1;
        state.attached = true;
        state.command = None;
        state.controls.clear();
        state.feedback = None;
        state.feedback_problem = None;
        state.health = Health::Ready;
        state.supports_orientation = supports_orientation;
        // A scene is declared by each attachment anew (after the attach, see `AttachHandle::declare_scene`).
        state.scene = RemoteScene {
            last_request_id: state.scene.last_request_id,
            ..RemoteScene::default()
        };
        let generation = state.generation;
        drop(state);
        // Wakes the replaced handle's waiter so its stream ends now rather than at its next timeout.
        self.shared.changed.notify_all();
        tracing::info!(arm = %self.arm, generation, replaced, "remote bridge attached");
        Ok(AttachHandle {
            shared: Arc::clone(&self.shared),
            generation,
            arm: self.arm.clone(),
        })
    }

    fn not_attached(&self) -> BridgeError {
        BridgeError::Connect {
            target: format!("remote bridge for arm {}", self.arm),
            message: "no remote bridge attached".into(),
        }
    }

    /// True while a remote bridge is attached.
    pub fn is_attached(&self) -> bool {
        let state = self.shared.state.lock();
        state.attached && !state.shut_down
    }
}

impl Bridge for RemoteBridge {
    fn kind(&self) -> &'static str {
        "remote"
    }

    /// Empty until the first bridge attaches (unless given at construction).
    fn joint_names(&self) -> &[String] {
        self.shared.joint_names.get().map_or(&[], Vec::as_slice)
    }

    fn supports_orientation(&self) -> bool {
        self.shared.state.lock().supports_orientation
    }

    fn send(&self, command: Command) {
        let mut state = self.shared.state.lock();
        if !state.attached || state.shut_down {
            return;
        }
        state.command = Some(command);
        drop(state);
        self.shared.changed.notify_all();
    }

    fn feedback(&self) -> Option<Feedback> {
        self.shared.state.lock().feedback.clone()
    }

    fn warning(&self) -> Option<String> {
        self.shared.state.lock().overspeed.clone()
    }

    /// Ready only once the attached bridge has sent valid feedback: joint names alone measure nothing.
    fn health(&self) -> Health {
        let state = self.shared.state.lock();
        match (&state.health, &state.feedback_problem, &state.feedback) {
            (Health::Ready, Some(problem), _) => Health::Error(format!("invalid feedback: {problem}")),
            (Health::Ready, None, None) => Health::Connecting,
            (health, _, _) => health.clone(),
        }
    }

    /// Forwards the request to the attached bridge.
    fn control(&self, request: Control) -> Result<(), BridgeError> {
        let mut state = self.shared.state.lock();
        if !state.attached || state.shut_down {
            return Err(BridgeError::Connect {
                target: format!("remote bridge for arm {}", self.arm),
                message: "no remote bridge attached".into(),
            });
        }
        if state.controls.len() >= MAX_PENDING_CONTROLS {
            state.controls.pop_front();
        }
        state.controls.push_back(request);
        drop(state);
        self.shared.changed.notify_all();
        Ok(())
    }

    /// The scene the attached bridge reported last; `Unsupported` unless the bridge declared one.
    fn scene(&self) -> Result<SceneState, BridgeError> {
        let state = self.shared.state.lock();
        if !state.scene.declared {
            return Err(BridgeError::Unsupported(format!(
                "arm {}: the remote bridge has no scene (its hello did not set has_scene)",
                self.arm
            )));
        }
        if !state.attached || state.shut_down {
            return Err(self.not_attached());
        }
        state.scene.state.clone().ok_or_else(|| {
            BridgeError::Protocol(format!(
                "arm {}: the remote bridge has not reported its scene yet",
                self.arm
            ))
        })
    }

    /// Forwards the reset to the attached bridge and waits (at most [`SCENE_RESET_TIMEOUT`]) for its answer.
    fn reset_scene(&self, seed: Option<u64>, home_arm: bool) -> Result<SceneState, BridgeError> {
        // Answers `Unsupported`, or why there is no scene to reset.
        self.scene()?;
        let mut state = self.shared.state.lock();
        let generation = state.generation;
        state.scene.last_request_id += 1;
        let request_id = state.scene.last_request_id;
        state.scene.pending.push_back(SceneReset {
            request_id,
            seed,
            home_arm,
        });
        if home_arm {
            state.scene.homing = Some(request_id);
        }
        self.shared.changed.notify_all();
        let deadline = Instant::now() + SCENE_RESET_TIMEOUT;
        loop {
            if state.generation != generation || !state.attached || state.shut_down {
                return Err(self.not_attached());
            }
            if let Some((id, _)) = &state.scene.answer
                && *id == request_id
            {
                let (_, answer) = state.scene.answer.take().expect("checked above");
                return answer.map_err(|e| {
                    BridgeError::Protocol(format!(
                        "arm {}: the bridge failed the scene reset: {e}",
                        self.arm
                    ))
                });
            }
            if self.shared.changed.wait_until(&mut state, deadline).timed_out() {
                state.scene.pending.retain(|r| r.request_id != request_id);
                if state.scene.homing == Some(request_id) {
                    state.scene.homing = None;
                }
                return Err(BridgeError::Protocol(format!(
                    "arm {}: the remote bridge did not answer the scene reset within {} s",
                    self.arm,
                    SCENE_RESET_TIMEOUT.as_secs()
                )));
            }
        }
    }

    fn shutdown(&self) {
        let mut state = self.shared.state.lock();
        if state.shut_down {
            return;
        }
        state.shut_down = true;
        state.attached = false;
        state.command = None;
        state.feedback = None;
        state.health = Health::Disconnected("shut down".into());
        drop(state);
        self.shared.changed.notify_all();
    }
}

/// One attachment of a remote bridge. `Send + Sync`: share it in an `Arc` between the thread that waits for
/// commands and the task that reads feedback. Dropping the last reference detaches (if still current).
#[derive(Debug)]
pub struct AttachHandle {
    shared: Arc<Shared>,
    generation: u64,
    arm: String,
}

impl AttachHandle {
    /// Waits up to `timeout` for the next message: pending control requests first, then the newest command.
    /// `Ok(None)` on timeout; an error once this attachment is over (detached, replaced, shut down).
    pub fn next(&self, timeout: Duration) -> Result<Option<Downstream>, RemoteError> {
        self.take_within(timeout, |state| {
            state
                .controls
                .pop_front()
                .map(Downstream::Control)
                .or_else(|| state.scene.pending.pop_front().map(Downstream::SceneReset))
                .or_else(|| state.command.take().map(Downstream::Command))
        })
    }

    /// Like [`Self::next`] but only commands (control requests stay queued for `next`).
    pub fn next_command(&self, timeout: Duration) -> Result<Option<Command>, RemoteError> {
        self.take_within(timeout, |state| state.command.take())
    }

    /// Waits until `take` finds something, this attachment ends (an error) or `timeout` passes (`Ok(None)`).
    /// The state is looked at once more after the deadline, so a message that arrived with it is not left
    /// for the next call.
    fn take_within<T>(
        &self,
        timeout: Duration,
        mut take: impl FnMut(&mut State) -> Option<T>,
    ) -> Result<Option<T>, RemoteError> {
        let deadline = Instant::now() + timeout;
        let mut state = self.shared.state.lock();
        let mut timed_out = false;
        loop {
            Shared::check(&state, self.generation)?;
            if let Some(found) = take(&mut state) {
                return Ok(Some(found));
            }
            if timed_out {
                return Ok(None);
            }
            // Any wake-up (a notify or a spurious one) looks again; only the deadline ends the wait.
            timed_out = self.shared.changed.wait_until(&mut state, deadline).timed_out();
        }
    }

    /// Publishes measured state from the remote. Rejects feedback whose joint count differs from the arm's or
    /// that holds non-finite values (nothing is stored then).
    /// The arm's health is an error until the next valid feedback.
    pub fn publish_feedback(&self, feedback: Feedback) -> Result<(), RemoteError> {
        let expected = self.shared.joint_names.get().map_or(0, Vec::len);
        let pose = &feedback.robot_from_ee;
        let problem = if feedback.joint_positions_rad.len() == expected {
            let finite = feedback.joint_positions_rad.iter().all(|v| v.is_finite())
                && pose.translation.vector.iter().all(|v| v.is_finite())
                && pose.rotation.coords.iter().all(|v| v.is_finite())
                && feedback.gripper_position.is_finite();
            (!finite).then(|| "non-finite value".to_owned())
        } else {
            Some(format!(
                "{} joint positions, expected {expected}",
                feedback.joint_positions_rad.len()
            ))
        };
        let mut state = self.shared.state.lock();
        Shared::check(&state, self.generation)?;
        if let Some(problem) = problem {
            state.feedback_problem = Some(problem.clone());
            return Err(RemoteError::InvalidFeedback(problem));
        }
        state.feedback_problem = None;
        // A remote scene's success rides on the arm's feedback, as the simulator's does.
        let mut feedback = feedback;
        if let Some(scene) = &state.scene.state {
            feedback.task_success = scene.task_success;
        }
        let time_s = feedback.capture_time_ns as f64 * 1e-9;
        let homing = state.scene.homing.is_some();
        let over = state.speed_watch.as_mut().and_then(|w| {
            if homing {
                // The arm may be placed at home before the answer comes: its jump is not a speed.
                w.restart();
                return None;
            }
            Some((w.observe(&feedback.joint_positions_rad, time_s)?, w.overspeeds))
        });
        if let Some((o, count)) = over {
            let name = self
                .shared
                .joint_names
                .get()
                .and_then(|n| n.get(o.joint))
                .map_or("?", String::as_str);
            let message = format!(
                "joint {name} measured at {:.2} rad/s, over its {:.2} rad/s limit ({count} samples so far)",
                o.speed_rad_s, o.limit_rad_s
            );
            // The first and then every hundredth: a robot that keeps overspeeding must not flood the log.
            if count == 1 || count % 100 == 0 {
                tracing::warn!(arm = %self.arm, "{message}");
            }
            state.overspeed = Some(message);
        }
        state.feedback = Some(feedback);
        Ok(())
    }

    /// This bridge simulates the arm's scene: `Scene.Get` reads what it reports through
    /// [`Self::publish_scene`] and `Scene.Reset` reaches it as [`Downstream::SceneReset`].
    pub fn declare_scene(&self) -> Result<(), RemoteError> {
        let mut state = self.shared.state.lock();
        Shared::check(&state, self.generation)?;
        state.scene.declared = true;
        Ok(())
    }

    /// The bridge's scene now; `answers` is the id of the reset it answers (0: none) and `error` the bridge's
    /// reason for failing that reset. Refused from a bridge that declared no scene.
    pub fn publish_scene(
        &self,
        scene: SceneState,
        answers: u64,
        error: Option<String>,
    ) -> Result<(), RemoteError> {
        let mut state = self.shared.state.lock();
        Shared::check(&state, self.generation)?;
        if !state.scene.declared {
            return Err(RemoteError::UndeclaredScene);
        }
        if let Some(feedback) = state.feedback.as_mut() {
            feedback.task_success = scene.task_success;
        }
        if answers != 0 {
            state.scene.answer = Some((answers, error.map_or_else(|| Ok(scene.clone()), Err)));
            if state.scene.homing == Some(answers) {
                state.scene.homing = None;
                // Judged again from the next sample, at home.
                if let Some(w) = state.speed_watch.as_mut() {
                    w.restart();
                }
            }
        }
        state.scene.state = Some(scene);
        drop(state);
        self.shared.changed.notify_all();
        Ok(())
    }

    /// Reports the remote robot's health (errors, reconnects to its own robot).
    pub fn report_health(&self, health: Health) -> Result<(), RemoteError> {
        let mut state = self.shared.state.lock();
        Shared::check(&state, self.generation)?;
        state.health = health;
        Ok(())
    }

    /// Ends this attachment: health becomes Disconnected, feedback is cleared, the arm holds (no further
    /// commands reach anyone). Does nothing if a newer attach already replaced this one. Idempotent.
    pub fn detach(&self) {
        let mut state = self.shared.state.lock();
        if state.generation != self.generation || !state.attached || state.shut_down {
            return;
        }
        state.attached = false;
        state.command = None;
        state.controls.clear();
        state.scene.pending.clear();
        state.scene.homing = None;
        state.feedback = None;
        state.health = Health::Disconnected("remote bridge detached".into());
        drop(state);
        self.shared.changed.notify_all();
        tracing::info!(arm = %self.arm, generation = self.generation, "remote bridge detached");
    }

    /// True while this is the live attachment.
    pub fn is_current(&self) -> bool {
        Shared::check(&self.shared.state.lock(), self.generation).is_ok()
    }
}

impl Drop for AttachHandle {
    fn drop(&mut self) {
        self.detach();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Isometry3;

    fn names() -> Vec<String> {
        ["j1", "j2", "j3"].iter().map(|s| (*s).to_owned()).collect()
    }

    fn command(seq: u64) -> Command {
        Command {
            seq,
            robot_from_target: Isometry3::translation(0.2, 0.0, 0.1),
            gripper_target: 0.0,
            issue_time_ns: 0,
            joint_targets_rad: None,
        }
    }

    fn feedback(joints: Vec<f64>) -> Feedback {
        Feedback {
            capture_time_ns: 1,
            joint_positions_rad: joints,
            robot_from_ee: Isometry3::translation(0.2, 0.0, 0.1),
            gripper_position: 0.5,
            applied_seq: 3,
            task_success: false,
        }
    }

    const SHORT: Duration = Duration::from_millis(10);

    #[test]
    fn before_attach_the_arm_is_disconnected_and_commands_go_nowhere() {
        let remote = RemoteBridge::new("main");
        assert!(matches!(remote.health(), Health::Disconnected(_)));
        assert!(remote.joint_names().is_empty());
        remote.send(command(1));
        assert!(remote.control(Control::Enable).is_err());
        assert_eq!(remote.feedback(), None);
        // A command from before the attach must not reach the new bridge.
        let handle = remote.attach(names(), false).unwrap();
        assert_eq!(handle.next(SHORT), Ok(None));
        // Attached is not ready: nothing has been measured yet.
        assert_eq!(remote.health(), Health::Connecting);
        handle.publish_feedback(feedback(vec![0.0; 3])).unwrap();
        assert_eq!(remote.health(), Health::Ready);
        assert_eq!(remote.joint_names(), names().as_slice());
        assert!(!remote.supports_orientation());
        assert_eq!(remote.kind(), "remote");
    }

    #[test]
    fn latest_command_only_and_controls_first() {
        let remote = RemoteBridge::new("main");
        let handle = remote.attach(names(), true).unwrap();
        for seq in 1..=3 {
            remote.send(command(seq));
        }
        remote.control(Control::Disable).unwrap();
        assert_eq!(handle.next_command(SHORT), Ok(Some(command(3))));
        assert_eq!(handle.next_command(SHORT), Ok(None));
        remote.send(command(4));
        assert_eq!(
            handle.next(SHORT),
            Ok(Some(Downstream::Control(Control::Disable)))
        );
        assert_eq!(handle.next(SHORT), Ok(Some(Downstream::Command(command(4)))));
        assert_eq!(handle.next(SHORT), Ok(None));
    }

    #[test]
    fn a_waiting_handle_wakes_on_a_command() {
        let remote = RemoteBridge::new("main");
        let handle = Arc::new(remote.attach(names(), true).unwrap());
        let waiter = Arc::clone(&handle);
        let t = std::thread::spawn(move || waiter.next_command(Duration::from_secs(5)));
        std::thread::sleep(Duration::from_millis(30));
        let start = Instant::now();
        remote.send(command(9));
        assert_eq!(t.join().unwrap(), Ok(Some(command(9))));
        assert!(start.elapsed() < Duration::from_secs(1));
    }

    #[test]
    fn a_wake_for_something_else_does_not_end_the_wait_early() {
        let remote = RemoteBridge::new("main");
        let handle = Arc::new(remote.attach(names(), true).unwrap());
        let waiter = Arc::clone(&handle);
        let timeout = Duration::from_millis(300);
        let start = Instant::now();
        let t = std::thread::spawn(move || waiter.next_command(timeout));
        std::thread::sleep(Duration::from_millis(30));
        // Notifies the waiter, which takes only commands: it must go back to waiting.
        remote.control(Control::Enable).unwrap();
        assert_eq!(t.join().unwrap(), Ok(None));
        // A lower bound only: a loaded machine makes the wait end later, never earlier than its deadline.
        assert!(start.elapsed() >= timeout, "{:?}", start.elapsed());
        // The control request stayed queued for `next`.
        assert_eq!(handle.next(SHORT), Ok(Some(Downstream::Control(Control::Enable))));
    }

    #[test]
    fn feedback_and_health_flow_up_and_bad_feedback_is_refused() {
        let remote = RemoteBridge::new("main");
        let handle = remote.attach(names(), true).unwrap();
        handle.publish_feedback(feedback(vec![0.1, 0.2, 0.3])).unwrap();
        assert_eq!(remote.feedback(), Some(feedback(vec![0.1, 0.2, 0.3])));
        assert!(matches!(
            handle.publish_feedback(feedback(vec![0.1, 0.2])),
            Err(RemoteError::InvalidFeedback(_))
        ));
        assert!(matches!(
            handle.publish_feedback(feedback(vec![0.1, f64::NAN, 0.3])),
            Err(RemoteError::InvalidFeedback(_))
        ));
        assert_eq!(
            remote.feedback(),
            Some(feedback(vec![0.1, 0.2, 0.3])),
            "bad feedback changed no stored value"
        );
        // But it is not silent: the arm is in error until valid feedback comes again.
        assert_eq!(
            remote.health(),
            Health::Error("invalid feedback: non-finite value".into())
        );
        handle.publish_feedback(feedback(vec![0.1, 0.2, 0.3])).unwrap();
        assert_eq!(remote.health(), Health::Ready);
        handle.report_health(Health::Error("servo alarm".into())).unwrap();
        assert_eq!(remote.health(), Health::Error("servo alarm".into()));
    }

    #[test]
    fn detach_disconnects_and_holds() {
        let remote = RemoteBridge::new("main");
        let handle = Arc::new(remote.attach(names(), true).unwrap());
        handle.publish_feedback(feedback(vec![0.0; 3])).unwrap();
        let waiter = Arc::clone(&handle);
        let t = std::thread::spawn(move || waiter.next(Duration::from_secs(5)));
        std::thread::sleep(Duration::from_millis(30));
        handle.detach();
        assert_eq!(t.join().unwrap(), Err(RemoteError::Detached));
        assert!(matches!(remote.health(), Health::Disconnected(_)));
        assert_eq!(remote.feedback(), None);
        assert!(!remote.is_attached() && !handle.is_current());
        assert_eq!(
            handle.publish_feedback(feedback(vec![0.0; 3])),
            Err(RemoteError::Detached)
        );
        remote.send(command(5));
        handle.detach();
        // Re-attach works and does not see the command sent while detached.
        let again = remote.attach(names(), true).unwrap();
        assert_eq!(again.next(SHORT), Ok(None));
    }

    #[test]
    fn a_new_attach_replaces_the_old_one() {
        let remote = RemoteBridge::new("main");
        let old = Arc::new(remote.attach(names(), true).unwrap());
        let waiter = Arc::clone(&old);
        let t = std::thread::spawn(move || waiter.next(Duration::from_secs(5)));
        std::thread::sleep(Duration::from_millis(30));
        let new = remote.attach(names(), false).unwrap();
        assert_eq!(t.join().unwrap(), Err(RemoteError::Superseded));
        assert_eq!(old.report_health(Health::Ready), Err(RemoteError::Superseded));
        // The replaced handle going away must not disconnect its successor.
        drop(old);
        assert!(remote.is_attached() && new.is_current());
        remote.send(command(7));
        assert_eq!(new.next_command(SHORT), Ok(Some(command(7))));
        // Joint names are fixed by the first attach.
        assert!(matches!(
            remote.attach(vec!["other".into()], true),
            Err(RemoteError::JointNamesMismatch { .. })
        ));
        assert!(new.is_current(), "a refused attach replaces nothing");
        assert_eq!(remote.attach(Vec::new(), true).err(), Some(RemoteError::NoJoints));
    }

    #[test]
    fn dropping_the_handle_detaches_and_shutdown_ends_everything() {
        let remote = RemoteBridge::with_joint_names("main", names());
        assert_eq!(remote.joint_names().len(), 3);
        drop(remote.attach(names(), true).unwrap());
        assert!(matches!(remote.health(), Health::Disconnected(_)));
        let handle = Arc::new(remote.attach(names(), true).unwrap());
        let waiter = Arc::clone(&handle);
        let t = std::thread::spawn(move || waiter.next_command(Duration::from_secs(5)));
        std::thread::sleep(Duration::from_millis(30));
        remote.shutdown();
        remote.shutdown();
        assert_eq!(t.join().unwrap(), Err(RemoteError::ShutDown));
        assert_eq!(remote.attach(names(), true).err(), Some(RemoteError::ShutDown));
        assert!(matches!(remote.health(), Health::Disconnected(m) if m == "shut down"));
    }
    fn scene(seed: u64, task_success: bool) -> SceneState {
        SceneState {
            seed,
            resets: seed,
            ball_center_m: nalgebra::Vector3::new(0.2, 0.0, 0.01),
            ball_state: crate::scene::BallState::Resting,
            ball_radius_m: 0.01,
            basket_xy_m: [0.25, 0.1],
            basket_radius_m: 0.04,
            basket_height_m: 0.03,
            task_success,
            ball_area_m: crate::scene::TableArea {
                x_min_m: 0.1,
                x_max_m: 0.3,
                y_min_m: -0.1,
                y_max_m: 0.1,
            },
            basket_area_m: None,
        }
    }

    #[test]
    fn a_bridge_without_a_scene_has_none_and_cannot_report_one() {
        let remote = RemoteBridge::new("main");
        let handle = remote.attach(names(), true).unwrap();
        assert!(matches!(remote.scene(), Err(BridgeError::Unsupported(_))));
        assert!(matches!(
            remote.reset_scene(Some(1), true),
            Err(BridgeError::Unsupported(_))
        ));
        assert_eq!(
            handle.publish_scene(scene(1, false), 0, None),
            Err(RemoteError::UndeclaredScene)
        );
        assert_eq!(handle.next(SHORT), Ok(None), "nothing was forwarded");
    }

    #[test]
    fn a_scene_reset_is_forwarded_and_answered_and_success_rides_on_feedback() {
        let remote = RemoteBridge::new("main");
        let handle = Arc::new(remote.attach(names(), true).unwrap());
        handle.declare_scene().unwrap();
        // Declared but not reported yet: the scene exists, its state is not known.
        assert!(matches!(remote.scene(), Err(BridgeError::Protocol(_))));
        handle.publish_scene(scene(0, false), 0, None).unwrap();
        assert_eq!(remote.scene().unwrap(), scene(0, false));
        // The remote side: answers the first reset with the scene of its seed, and fails the second.
        let bridge_side = Arc::clone(&handle);
        let t = std::thread::spawn(move || {
            let mut seen = Vec::new();
            for answer_error in [None, Some("no such seed".to_owned())] {
                let Ok(Some(Downstream::SceneReset(r))) = bridge_side.next(Duration::from_secs(10)) else {
                    panic!("expected a scene reset");
                };
                seen.push(r);
                bridge_side
                    .publish_scene(scene(r.seed.unwrap_or(0), true), r.request_id, answer_error)
                    .unwrap();
            }
            seen
        });
        assert_eq!(remote.reset_scene(Some(7), true).unwrap(), scene(7, true));
        assert!(matches!(
            remote.reset_scene(None, false),
            Err(BridgeError::Protocol(m)) if m.contains("no such seed")
        ));
        let seen = t.join().unwrap();
        assert_eq!(
            seen.iter().map(|r| (r.seed, r.home_arm)).collect::<Vec<_>>(),
            [(Some(7), true), (None, false)]
        );
        assert_ne!(seen[0].request_id, seen[1].request_id);
        // The scene's success reaches the arm's feedback, as the built-in simulator's does.
        handle.publish_feedback(feedback(vec![0.0; 3])).unwrap();
        assert!(remote.feedback().unwrap().task_success);
        // Detached: the scene is unavailable (not absent), and a reset fails at once rather than waiting.
        handle.detach();
        assert!(matches!(remote.scene(), Err(BridgeError::Connect { .. })));
        assert!(matches!(
            remote.reset_scene(Some(1), false),
            Err(BridgeError::Connect { .. })
        ));
    }

    #[test]
    fn joints_measured_faster_than_their_limits_are_counted_and_shown() {
        let remote = RemoteBridge::with_joint_names("arm", names());
        remote.watch_joint_speeds(vec![1.0, 1.0, 1.0]).unwrap();
        let handle = remote.attach(names(), true).unwrap();
        let at = |t_s: f64, q: [f64; 3]| Feedback {
            capture_time_ns: (t_s * 1e9) as i64,
            ..feedback(q.to_vec())
        };
        // 0.8 rad/s on j2: within its limit.
        for i in 0..30 {
            let t = f64::from(i) * 0.01;
            handle.publish_feedback(at(t, [0.0, 0.8 * t, 0.0])).unwrap();
        }
        assert_eq!((remote.joint_overspeeds(), remote.warning()), (0, None));
        // Then 3 rad/s on j3.
        for i in 30..60 {
            let t = f64::from(i) * 0.01;
            handle
                .publish_feedback(at(t, [0.0, 0.24, 3.0 * (t - 0.3)]))
                .unwrap();
        }
        assert!(remote.joint_overspeeds() > 10, "{}", remote.joint_overspeeds());
        let warning = remote.warning().expect("a warning");
        assert!(
            warning.starts_with("joint j3 measured at 3.00 rad/s"),
            "{warning}"
        );
        assert!(remote.watch_joint_speeds(vec![f64::NAN]).is_err());
    }

    /// A simulator's homing reset places the arm at home in one step: that jump is not a joint speed, whether
    /// the bridge reports the new pose before or after answering the reset. The same jump without a reset is
    /// counted.
    #[test]
    fn a_homing_reset_is_not_measured_as_a_joint_speed() {
        let remote = RemoteBridge::with_joint_names("arm", names());
        remote.watch_joint_speeds(vec![1.0, 1.0, 1.0]).unwrap();
        let handle = Arc::new(remote.attach(names(), true).unwrap());
        handle.declare_scene().unwrap();
        handle.publish_scene(scene(0, false), 0, None).unwrap();
        let at = |t_s: f64, q: [f64; 3]| Feedback {
            capture_time_ns: (t_s * 1e9) as i64,
            ..feedback(q.to_vec())
        };
        // Away from home, at rest; then homed (1.5 rad on j1 in one 10 ms step) by two resets: the first
        // bridge reports home before its answer, the second after.
        for i in 0..20 {
            handle
                .publish_feedback(at(f64::from(i) * 0.01, [1.5, 0.0, 0.0]))
                .unwrap();
        }
        let mut t_s = 0.2;
        for home_before_answer in [true, false] {
            let bridge_side = Arc::clone(&handle);
            let start_s = t_s;
            let side = std::thread::spawn(move || {
                let Ok(Some(Downstream::SceneReset(r))) = bridge_side.next(Duration::from_secs(10)) else {
                    panic!("expected a scene reset");
                };
                assert!(r.home_arm);
                let mut t = start_s;
                let mut report = |q: [f64; 3]| {
                    for _ in 0..10 {
                        t += 0.01;
                        bridge_side.publish_feedback(at(t, q)).unwrap();
                    }
                };
                if home_before_answer {
                    report([0.0; 3]);
                    bridge_side
                        .publish_scene(scene(1, false), r.request_id, None)
                        .unwrap();
                } else {
                    bridge_side
                        .publish_scene(scene(1, false), r.request_id, None)
                        .unwrap();
                    report([0.0; 3]);
                }
                report([0.0; 3]);
                t
            });
            remote.reset_scene(Some(1), true).unwrap();
            t_s = side.join().unwrap();
            // Away again for the second reset, as a policy would leave it (within the limit: 1 rad/s).
            for i in 1..=150 {
                t_s += 0.01;
                handle
                    .publish_feedback(at(t_s, [f64::from(i) * 0.01, 0.0, 0.0]))
                    .unwrap();
            }
        }
        assert_eq!((remote.joint_overspeeds(), remote.warning()), (0, None));
        // The same jump with no reset is a speed.
        for _ in 0..10 {
            t_s += 0.01;
            handle.publish_feedback(at(t_s, [0.0; 3])).unwrap();
        }
        assert!(remote.joint_overspeeds() > 0);
    }
}

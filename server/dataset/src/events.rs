//! The per-episode events sidecar: clutch cycles and safety-gate decisions, at the frame where the recorder
//! saw them, and the recorder's own timeline events (a late frame, a pause), in `meta/phone2act/events/episode_{index:06}.jsonl` (one JSON object per line). lerobot and
//! GR00T read only the files they know, so they ignore it; `phone2act dataset plot` marks them on the time
//! axis.
//!
//! The recorder samples each arm's clutch state and cumulative gate counters once per recorded frame and
//! turns their changes into events ([`transitions`], pure). The file streams into the episode's staging
//! directory (memory stays bounded however long the episode) and is renamed into place with the episode's
//! commit, before `info.json`: a discarded episode leaves none, a re-recorded take replaces it.

use crate::error::RecorderError;
use phone2act_core::Activity;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Write as _};
use std::path::{Path, PathBuf};

/// Where the events of episode `index` live, relative to the dataset root.
pub fn events_path(index: u64) -> PathBuf {
    PathBuf::from(format!("meta/phone2act/events/episode_{index:06}.jsonl"))
}

/// One arm's clutch and gate state at a sample: what events are derived from.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ArmActivity {
    pub arm: String,
    /// What the arbiter was doing and had counted (clutch, driving policy, gate and joint-limit counters,
    /// the gate's last reason), read with the frame's action.
    pub arbiter: Activity,
    /// What the robot reports while it keeps working (a servo alarm that does not stop the arm, naming
    /// the part and the reason); empty when nothing is reported.
    pub warning: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    ClutchEngage,
    ClutchRelease,
    GateRejected,
    GateClamped,
    /// The recorder's own: the frame holds a sample captured farther from its time than the tolerance (see
    /// the recorder's `timeline`); `detail` names the sources and how far. `arm` is empty.
    LateTick,
    /// The recorder's own: `count` ticks before this frame were not recorded because a source had sent
    /// nothing within the hold tolerance, so the episode's time jumps here by `count / fps`. `arm` is empty.
    Paused,
    /// The joint speed limits shortened commands: the arm followed at its limit, behind the target.
    JointLimited,
    /// The robot reports something while it keeps working (`detail`: which part and why, e.g. a gripper
    /// servo's overload alarm while it squeezes an object), or reports something else than before.
    RobotWarning,
    /// The robot's warning went away (`detail`: the warning that was shown).
    RobotWarningCleared,
    /// A policy started driving the arm (`detail`: its name).
    PolicyStart,
    /// The policy that drove the arm stopped (`detail`: its name): a person took over (the policy then
    /// waits for a hand-back), it released the arm, went silent or ended.
    PolicyStop,
    /// The operator handed the arm back to the policy that waited (`detail`: its name; `count`: hand-backs
    /// since the previous frame). The policy drives again from here (a `policy_start` at the same frame) but
    /// the arm holds until its first chunk answering a newer observation.
    PolicyResume,
}

/// One line of the sidecar.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeEvent {
    /// The first recorded frame at which the change was seen.
    pub frame_index: u64,
    /// `frame_index / fps`, s.
    pub timestamp: f64,
    pub arm: String,
    pub kind: EventKind,
    /// Gate events: how many decisions of this kind happened since the previous frame (the gate runs at
    /// the phone's rate, the recorder at the dataset's); 1 for clutch events.
    pub count: u64,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub detail: String,
}

/// The events between two consecutive recorded samples. `previous` is `None` at an episode's first frame:
/// counters are only a baseline there (decisions before the episode are not its events), and an arm already
/// engaged gets a `clutch_engage` at frame 0 so that every engaged span has a start. An arm absent from
/// `previous` (or whose counters went down: a restarted source) is treated the same way. Changes are seen at
/// the recorder's rate: a clutch released and engaged again between two frames leaves no event.
pub fn transitions(
    previous: Option<&[ArmActivity]>,
    current: &[ArmActivity],
    frame_index: u64,
    fps: u32,
) -> Vec<EpisodeEvent> {
    let timestamp = frame_index as f64 / f64::from(fps);
    let event = |arm: &ArmActivity, kind, count, detail: &str| EpisodeEvent {
        frame_index,
        timestamp,
        arm: arm.arm.clone(),
        kind,
        count,
        detail: detail.to_owned(),
    };
    let mut events = Vec::new();
    for now in current {
        let before = previous
            .and_then(|p| p.iter().find(|b| b.arm == now.arm))
            .filter(|b| {
                b.arbiter.rejected <= now.arbiter.rejected
                    && b.arbiter.clamped <= now.arbiter.clamped
                    && b.arbiter.joint_limited <= now.arbiter.joint_limited
                    && b.arbiter.handed_back <= now.arbiter.handed_back
            });
        let Some(before) = before else {
            if now.arbiter.engaged {
                events.push(event(
                    now,
                    EventKind::ClutchEngage,
                    1,
                    "engaged when the episode started",
                ));
            }
            if !now.arbiter.policy.is_empty() {
                events.push(event(now, EventKind::PolicyStart, 1, &now.arbiter.policy));
            }
            // Unlike the counters, a warning is a state: one present at the start belongs to the episode.
            if !now.warning.is_empty() {
                events.push(event(now, EventKind::RobotWarning, 1, &now.warning));
            }
            continue;
        };
        match (before.arbiter.engaged, now.arbiter.engaged) {
            (false, true) => events.push(event(now, EventKind::ClutchEngage, 1, "")),
            (true, false) => events.push(event(now, EventKind::ClutchRelease, 1, "")),
            _ => {}
        }
        if before.arbiter.policy != now.arbiter.policy {
            // A take-over between two frames stops the policy and engages the clutch at the same frame.
            if !before.arbiter.policy.is_empty() {
                events.push(event(now, EventKind::PolicyStop, 1, &before.arbiter.policy));
            }
            if !now.arbiter.policy.is_empty() {
                events.push(event(now, EventKind::PolicyStart, 1, &now.arbiter.policy));
            }
        }
        let handed_back = now.arbiter.handed_back - before.arbiter.handed_back;
        if handed_back > 0 {
            events.push(event(
                now,
                EventKind::PolicyResume,
                handed_back,
                &now.arbiter.policy,
            ));
        }
        let rejected = now.arbiter.rejected - before.arbiter.rejected;
        let clamped = now.arbiter.clamped - before.arbiter.clamped;
        // The last reason belongs to one kind of decision; when both kinds happened it is not known which.
        let reason = if rejected == 0 || clamped == 0 {
            now.arbiter.last_reason.as_str()
        } else {
            ""
        };
        if rejected > 0 {
            events.push(event(now, EventKind::GateRejected, rejected, reason));
        }
        if clamped > 0 {
            events.push(event(now, EventKind::GateClamped, clamped, reason));
        }
        let joint_limited = now.arbiter.joint_limited - before.arbiter.joint_limited;
        if joint_limited > 0 {
            events.push(event(
                now,
                EventKind::JointLimited,
                joint_limited,
                "joint speed limit",
            ));
        }
        if before.warning != now.warning {
            if now.warning.is_empty() {
                events.push(event(now, EventKind::RobotWarningCleared, 1, &before.warning));
            } else {
                events.push(event(now, EventKind::RobotWarning, 1, &now.warning));
            }
        }
    }
    events
}

/// Reads a sidecar back: `Ok(None)` when the dataset has none for the episode (written by lerobot, or by a
/// phone2act before events were recorded).
pub fn read_events(root: &Path, index: u64) -> Result<Option<Vec<EpisodeEvent>>, RecorderError> {
    let path = root.join(events_path(index));
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(RecorderError::io(&path, e)),
    };
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(n, l)| {
            serde_json::from_str(l).map_err(|e| RecorderError::CorruptDataset {
                root: root.to_owned(),
                detail: format!("{} line {}: {e}", events_path(index).display(), n + 1),
            })
        })
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

/// Streams an episode's events into its staging file.
pub(crate) struct EventWriter {
    file: BufWriter<File>,
    path: PathBuf,
    fps: u32,
    previous: Option<Vec<ArmActivity>>,
    /// Every policy that drove an arm in the episode, for its provenance.
    policies: std::collections::BTreeSet<String>,
}

impl EventWriter {
    pub(crate) fn create(path: PathBuf, fps: u32) -> Result<Self, RecorderError> {
        let file = File::create(&path).map_err(|e| RecorderError::io(&path, e))?;
        Ok(EventWriter {
            file: BufWriter::new(file),
            path,
            fps,
            previous: None,
            policies: std::collections::BTreeSet::new(),
        })
    }

    /// Writes the events between the previous recorded frame and `frame_index`.
    pub(crate) fn observe(&mut self, arms: &[ArmActivity], frame_index: u64) -> Result<(), RecorderError> {
        if self.previous.as_deref() == Some(arms) {
            return Ok(());
        }
        // Only when the arms changed: a policy name is cloned once per change, not once per frame.
        for a in arms.iter().filter(|a| !a.arbiter.policy.is_empty()) {
            if !self.policies.contains(&a.arbiter.policy) {
                self.policies.insert(a.arbiter.policy.clone());
            }
        }
        for e in transitions(self.previous.as_deref(), arms, frame_index, self.fps) {
            let mut line = serde_json::to_vec(&e).map_err(|e| RecorderError::io(&self.path, e.into()))?;
            line.push(b'\n');
            self.file
                .write_all(&line)
                .map_err(|e| RecorderError::io(&self.path, e))?;
        }
        self.previous = Some(arms.to_vec());
        Ok(())
    }

    /// Writes one of the recorder's own events ([`EventKind::LateTick`], [`EventKind::Paused`]) at
    /// `frame_index`.
    pub(crate) fn note(
        &mut self,
        kind: EventKind,
        frame_index: u64,
        count: u64,
        detail: String,
    ) -> Result<(), RecorderError> {
        let e = EpisodeEvent {
            frame_index,
            timestamp: frame_index as f64 / f64::from(self.fps),
            arm: String::new(),
            kind,
            count,
            detail,
        };
        let mut line = serde_json::to_vec(&e).map_err(|e| RecorderError::io(&self.path, e.into()))?;
        line.push(b'\n');
        self.file
            .write_all(&line)
            .map_err(|e| RecorderError::io(&self.path, e))
    }

    /// The policies that drove an arm so far, by name.
    pub(crate) fn policies(&self) -> Vec<String> {
        self.policies.iter().cloned().collect()
    }

    /// Flushes and fsyncs the file; returns its path, ready to be renamed into the dataset.
    pub(crate) fn finish(self) -> Result<PathBuf, RecorderError> {
        let file = self
            .file
            .into_inner()
            .map_err(|e| RecorderError::io(&self.path, e.into_error()))?;
        file.sync_all().map_err(|e| RecorderError::io(&self.path, e))?;
        Ok(self.path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arm(engaged: bool, rejected: u64, clamped: u64) -> ArmActivity {
        ArmActivity {
            arm: "main".into(),
            arbiter: Activity {
                engaged,
                rejected,
                clamped,
                joint_limited: 0,
                handed_back: 0,
                last_reason: "jump of 120 mm".into(),
                policy: String::new(),
            },
            warning: String::new(),
        }
    }

    #[test]
    fn robot_warnings_are_events_when_they_appear_change_and_clear() {
        let quiet = arm(true, 0, 0);
        let mut overload = quiet.clone();
        overload.warning = "gripper (id 6): overload".into();
        let mut hot = quiet.clone();
        hot.warning = "gripper (id 6): overheat".into();
        // Present when the episode starts: an event at frame 0, beside the clutch's.
        let e = transitions(None, std::slice::from_ref(&overload), 0, 20);
        assert_eq!(
            kinds(&e),
            [(EventKind::ClutchEngage, 1), (EventKind::RobotWarning, 1)]
        );
        assert_eq!(e[1].detail, "gripper (id 6): overload");
        let e = transitions(
            Some(std::slice::from_ref(&quiet)),
            std::slice::from_ref(&overload),
            5,
            20,
        );
        assert_eq!(kinds(&e), [(EventKind::RobotWarning, 1)]);
        assert!(
            transitions(
                Some(std::slice::from_ref(&overload)),
                std::slice::from_ref(&overload),
                6,
                20
            )
            .is_empty()
        );
        let e = transitions(
            Some(std::slice::from_ref(&overload)),
            std::slice::from_ref(&hot),
            7,
            20,
        );
        assert_eq!(kinds(&e), [(EventKind::RobotWarning, 1)]);
        assert_eq!(e[0].detail, "gripper (id 6): overheat");
        let e = transitions(Some(&[hot]), &[quiet], 8, 20);
        assert_eq!(kinds(&e), [(EventKind::RobotWarningCleared, 1)]);
        assert_eq!(e[0].detail, "gripper (id 6): overheat");
    }

    #[test]
    fn joint_limited_commands_are_events_too() {
        let before = arm(true, 0, 0);
        let mut now = arm(true, 0, 0);
        now.arbiter.joint_limited = 4;
        let e = transitions(Some(&[before]), &[now.clone()], 12, 20);
        assert_eq!(kinds(&e), [(EventKind::JointLimited, 4)]);
        assert_eq!(e[0].detail, "joint speed limit");
        assert!(transitions(Some(&[now.clone()]), &[now], 13, 20).is_empty());
    }

    #[test]
    fn a_hand_back_is_a_policy_resume_beside_the_policy_start() {
        let waiting = arm(false, 0, 0);
        let mut resumed = arm(false, 0, 0);
        resumed.arbiter.policy = "gr00t".into();
        resumed.arbiter.handed_back = 1;
        let e = transitions(Some(&[waiting]), std::slice::from_ref(&resumed), 30, 20);
        assert_eq!(
            kinds(&e),
            [(EventKind::PolicyStart, 1), (EventKind::PolicyResume, 1)]
        );
        assert_eq!(e[1].detail, "gr00t");
        assert!(transitions(Some(&[resumed.clone()]), &[resumed], 31, 20).is_empty());
    }

    #[test]
    fn a_policy_driving_is_a_span_that_a_take_over_ends_at_the_clutch_frame() {
        let mut driving = arm(false, 0, 0);
        driving.arbiter.policy = "gr00t".into();
        // Driving when the episode starts: a start at frame 0, named.
        let e = transitions(None, std::slice::from_ref(&driving), 0, 20);
        assert_eq!(kinds(&e), [(EventKind::PolicyStart, 1)]);
        assert_eq!(e[0].detail, "gr00t");
        // The operator takes over: the clutch engages and the policy stops at the same frame.
        let taken = arm(true, 0, 0);
        let e = transitions(
            Some(std::slice::from_ref(&driving)),
            std::slice::from_ref(&taken),
            9,
            20,
        );
        assert_eq!(
            kinds(&e),
            [(EventKind::ClutchEngage, 1), (EventKind::PolicyStop, 1)]
        );
        assert_eq!((e[1].frame_index, e[1].detail.as_str()), (9, "gr00t"));
        // Another policy between two frames: one stops, the other starts.
        let mut other = driving.clone();
        other.arbiter.policy = "replay".into();
        let e = transitions(Some(&[driving]), std::slice::from_ref(&other), 12, 20);
        assert_eq!(
            kinds(&e),
            [(EventKind::PolicyStop, 1), (EventKind::PolicyStart, 1)]
        );
        assert_eq!((e[0].detail.as_str(), e[1].detail.as_str()), ("gr00t", "replay"));
        let dir = tempfile::tempdir().unwrap();
        let mut w = EventWriter::create(dir.path().join("e.jsonl"), 20).unwrap();
        w.observe(std::slice::from_ref(&other), 0).unwrap();
        w.observe(&[taken], 1).unwrap();
        let mut back = other;
        back.arbiter.policy = "gr00t".into();
        w.observe(&[back], 2).unwrap();
        assert_eq!(
            w.policies(),
            ["gr00t", "replay"],
            "the episode's policies, by name"
        );
    }

    fn kinds(events: &[EpisodeEvent]) -> Vec<(EventKind, u64)> {
        events.iter().map(|e| (e.kind, e.count)).collect()
    }

    #[test]
    fn the_first_frame_is_a_baseline_except_an_engaged_clutch() {
        assert!(transitions(None, &[arm(false, 7, 3)], 0, 20).is_empty());
        let e = transitions(None, &[arm(true, 7, 3)], 0, 20);
        assert_eq!(kinds(&e), [(EventKind::ClutchEngage, 1)]);
        assert!(e[0].detail.contains("started"));
    }

    #[test]
    fn changes_become_events_at_their_frame() {
        let e = transitions(Some(&[arm(false, 1, 0)]), &[arm(true, 1, 0)], 30, 20);
        assert_eq!(kinds(&e), [(EventKind::ClutchEngage, 1)]);
        assert!((e[0].timestamp - 1.5).abs() < 1e-12);
        assert_eq!(e[0].frame_index, 30);
        let e = transitions(Some(&[arm(true, 1, 0)]), &[arm(false, 4, 0)], 31, 20);
        assert_eq!(
            kinds(&e),
            [(EventKind::ClutchRelease, 1), (EventKind::GateRejected, 3)]
        );
        assert_eq!(e[1].detail, "jump of 120 mm");
        // Both kinds of decision between two frames: counts for both, no reason attributed.
        let e = transitions(Some(&[arm(true, 1, 0)]), &[arm(true, 2, 5)], 32, 20);
        assert_eq!(
            kinds(&e),
            [(EventKind::GateRejected, 1), (EventKind::GateClamped, 5)]
        );
        assert!(e.iter().all(|e| e.detail.is_empty()));
        assert!(transitions(Some(&[arm(true, 2, 5)]), &[arm(true, 2, 5)], 33, 20).is_empty());
    }

    #[test]
    fn arms_are_matched_by_name_and_a_restarted_counter_is_a_new_baseline() {
        let mut left = arm(false, 0, 0);
        left.arm = "left".into();
        let mut left_on = left.clone();
        left_on.arbiter.engaged = true;
        let e = transitions(
            Some(&[left.clone(), arm(false, 0, 0)]),
            &[arm(false, 2, 0), left_on],
            5,
            10,
        );
        let got: Vec<(&str, EventKind)> = e.iter().map(|e| (e.arm.as_str(), e.kind)).collect();
        assert_eq!(
            got,
            [
                ("main", EventKind::GateRejected),
                ("left", EventKind::ClutchEngage)
            ]
        );
        assert!(transitions(Some(&[arm(false, 9, 0)]), &[arm(false, 2, 0)], 6, 10).is_empty());
    }

    #[test]
    fn the_writer_streams_lines_that_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let mut w = EventWriter::create(root.join("events.jsonl"), 10).unwrap();
        w.observe(&[arm(false, 0, 0)], 0).unwrap();
        w.observe(&[arm(true, 0, 0)], 1).unwrap();
        w.observe(&[arm(true, 0, 0)], 2).unwrap();
        w.observe(&[arm(true, 2, 0)], 3).unwrap();
        let path = w.finish().unwrap();
        std::fs::create_dir_all(root.join("meta/phone2act/events")).unwrap();
        std::fs::rename(path, root.join(events_path(4))).unwrap();
        let events = read_events(root, 4).unwrap().unwrap();
        assert_eq!(
            kinds(&events),
            [(EventKind::ClutchEngage, 1), (EventKind::GateRejected, 2)]
        );
        assert_eq!(events[1].frame_index, 3);
        assert_eq!(read_events(root, 5).unwrap(), None);
        std::fs::write(root.join(events_path(5)), "{not json\n").unwrap();
        assert!(read_events(root, 5).unwrap_err().to_string().contains("line 1"));
    }
}

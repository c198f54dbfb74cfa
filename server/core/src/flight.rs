//! The flight recorder's content and its replay: what an arm's arbiter was given (every input with its time
//! and the robot state it saw) and what it decided, and a replayer that runs a fresh arbiter over the same
//! inputs and names the first input whose outcome differs.
//!
//! The arbiter is a deterministic function of its configuration, its starting pose and its inputs (time is an
//! input), so a session's log replayed on the same core gives back every command and gate decision bit for
//! bit. A difference therefore means the rules changed (or the configuration given to the replay did): the
//! answer to "why did the arm do that?" after an incident, and a real session kept as a regression test.
//! Encoding and files are the caller's: this module holds no I/O.

use crate::arbiter::{Arbiter, ArbiterError, Effects, Input, Robot};
use crate::chunk::ChunkConfig;
use crate::config::{ConfigError, TeleopConfig};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// Version of the log's content; a replayer refuses another one rather than misreading it.
pub const FLIGHT_FORMAT_VERSION: u32 = 1;

/// The start of a log: everything [`Arbiter::new`] was given.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FlightHeader {
    /// [`FLIGHT_FORMAT_VERSION`] of the writer.
    pub format_version: u32,
    pub arm: String,
    pub teleop: TeleopConfig,
    pub chunk: ChunkConfig,
    /// The pose the arbiter started holding.
    pub measured: Isometry3<f64>,
    pub gripper: f64,
}

impl FlightHeader {
    /// The header of an arbiter made with these arguments.
    pub fn new(
        arm: &str,
        teleop: &TeleopConfig,
        chunk: &ChunkConfig,
        measured: Isometry3<f64>,
        gripper: f64,
    ) -> Self {
        Self {
            format_version: FLIGHT_FORMAT_VERSION,
            arm: arm.to_owned(),
            teleop: teleop.clone(),
            chunk: chunk.clone(),
            measured,
            gripper,
        }
    }
}

/// What the arbiter made of one input.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Outcome {
    Applied(Effects),
    /// Refused, with the refusal's message (a refused input changes nothing).
    Refused(String),
}

impl Outcome {
    /// The outcome of [`Arbiter::handle`]'s result (borrowed, so a caller that goes on with the effects keeps
    /// them).
    pub fn of(result: Result<&Effects, &ArbiterError>) -> Self {
        match result {
            Ok(effects) => Self::Applied(effects.clone()),
            Err(e) => Self::Refused(e.to_string()),
        }
    }
}

/// One input as the arbiter saw it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FlightEntry {
    pub now_s: f64,
    pub input: Input,
    pub robot: Robot,
    pub outcome: Outcome,
}

/// The first input whose replayed outcome differs from the recorded one.
#[derive(Debug, Clone, PartialEq)]
pub struct Divergence {
    /// Position of the input in the log, from 0.
    pub index: usize,
    pub now_s: f64,
    /// The input, as `Debug` prints it (chunks shortened to their size).
    pub input: String,
    /// What differs, e.g. `commands[0].robot_from_target` or `decision`.
    pub field: String,
    pub recorded: String,
    pub replayed: String,
}

impl std::fmt::Display for Divergence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "input {} at {:.6} s ({}): {} differs\n  recorded: {}\n  replayed: {}",
            self.index, self.now_s, self.input, self.field, self.recorded, self.replayed
        )
    }
}

/// Why a log cannot be replayed at all.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplayError {
    #[error("the log is format version {found}; this replayer reads version {FLIGHT_FORMAT_VERSION}")]
    Version { found: u32 },
    #[error("the log's configuration is refused: {0}")]
    Config(#[from] ConfigError),
}

/// What a replay went through.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplayCounts {
    pub inputs: usize,
    pub refused: usize,
    pub commands: usize,
    /// Inputs that put a gate decision on display.
    pub decisions: usize,
}

/// Replays a log entry by entry on a fresh arbiter.
#[derive(Debug, Clone)]
pub struct Replayer {
    arbiter: Arbiter,
    counts: ReplayCounts,
}

impl Replayer {
    /// An arbiter made as the header says.
    pub fn new(header: &FlightHeader) -> Result<Self, ReplayError> {
        if header.format_version != FLIGHT_FORMAT_VERSION {
            return Err(ReplayError::Version {
                found: header.format_version,
            });
        }
        let arbiter = Arbiter::new(
            &header.teleop,
            header.chunk.clone(),
            header.measured,
            header.gripper,
        )?;
        Ok(Self {
            arbiter,
            counts: ReplayCounts::default(),
        })
    }

    /// Hands the next entry's input to the arbiter and compares the outcome with the recorded one. After a
    /// divergence the replay may go on, but the arbiter's state need not match the session's any more.
    pub fn step(&mut self, entry: &FlightEntry) -> Result<(), Divergence> {
        let index = self.counts.inputs;
        self.counts.inputs += 1;
        let replayed = Outcome::of(
            self.arbiter
                .handle(entry.input.clone(), &entry.robot, entry.now_s)
                .as_ref(),
        );
        match &replayed {
            Outcome::Applied(fx) => {
                self.counts.commands += fx.commands.len();
                self.counts.decisions += usize::from(fx.decision.is_some());
            }
            Outcome::Refused(_) => self.counts.refused += 1,
        }
        match first_difference(&entry.outcome, &replayed) {
            None => Ok(()),
            Some((field, recorded, replayed)) => Err(Divergence {
                index,
                now_s: entry.now_s,
                input: describe(&entry.input),
                field,
                recorded,
                replayed,
            }),
        }
    }

    /// What was replayed so far.
    pub fn counts(&self) -> ReplayCounts {
        self.counts
    }
}

/// Replays a whole log; stops at the first divergence.
pub fn replay<'a>(
    header: &FlightHeader,
    entries: impl IntoIterator<Item = &'a FlightEntry>,
) -> Result<Result<ReplayCounts, Divergence>, ReplayError> {
    let mut replayer = Replayer::new(header)?;
    for entry in entries {
        if let Err(d) = replayer.step(entry) {
            return Ok(Err(d));
        }
    }
    Ok(Ok(replayer.counts()))
}

/// The input for a report: a chunk's steps would fill the screen, so it is named by its size.
fn describe(input: &Input) -> String {
    match input {
        Input::Chunk {
            session,
            chunk,
            observed_s,
        } => format!(
            "Chunk {{ session: {session}, steps: {}, anchor_time_s: {}, step_period_s: {}, observed_s: {observed_s} }}",
            chunk.steps.len(),
            chunk.anchor_time_s,
            chunk.step_period_s
        ),
        other => format!("{other:?}"),
    }
}

/// The first field (in the order a reader cares about: the gate decision, the commands, then the rest) where
/// the two outcomes differ, with both values. Values are compared as `Debug` prints them, which for floats is
/// the shortest text that reads back to the same bits: equal text is equal bits (and NaN equals NaN).
fn first_difference(recorded: &Outcome, replayed: &Outcome) -> Option<(String, String, String)> {
    let (a, b) = match (recorded, replayed) {
        (Outcome::Applied(a), Outcome::Applied(b)) => (a, b),
        (Outcome::Refused(a), Outcome::Refused(b)) => {
            return (a != b).then(|| ("refusal".to_owned(), a.clone(), b.clone()));
        }
        (a, b) => return Some(("outcome".to_owned(), brief(a), brief(b))),
    };
    let differs = |field: String, x: String, y: String| (x != y).then_some((field, x, y));
    differs(
        "decision".into(),
        format!("{:?}", a.decision),
        format!("{:?}", b.decision),
    )
    .or_else(|| {
        differs(
            "number of commands".into(),
            a.commands.len().to_string(),
            b.commands.len().to_string(),
        )
    })
    .or_else(|| {
        a.commands
            .iter()
            .zip(&b.commands)
            .enumerate()
            .find_map(|(i, (x, y))| differs(format!("commands[{i}]"), format!("{x:?}"), format!("{y:?}")))
    })
    .or_else(|| {
        differs(
            "revoked".into(),
            format!("{:?}", a.revoked),
            format!("{:?}", b.revoked),
        )
    })
    .or_else(|| {
        differs(
            "reindexed".into(),
            a.reindexed.to_string(),
            b.reindexed.to_string(),
        )
    })
    .or_else(|| {
        differs(
            "phone_error".into(),
            format!("{:?}", a.phone_error),
            format!("{:?}", b.phone_error),
        )
    })
    .or_else(|| differs("chunk".into(), format!("{:?}", a.chunk), format!("{:?}", b.chunk)))
}

fn brief(outcome: &Outcome) -> String {
    match outcome {
        Outcome::Applied(fx) => format!("applied ({} commands)", fx.commands.len()),
        Outcome::Refused(message) => format!("refused: {message}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::arbiter::{BridgeHealth, Measured, TeleopButton, TeleopRound};
    use crate::chunk::{ActionChunk, ChunkStep};
    use crate::gate::GateVerdict;
    use crate::teleop::ClutchKind;
    use nalgebra::{Translation3, UnitQuaternion};

    const PHONE: u64 = 41;
    const POLICY: u64 = 7;

    fn home() -> Isometry3<f64> {
        Isometry3::translation(0.25, 0.0, 0.2)
    }

    fn ready(now_s: f64) -> Robot {
        Robot {
            health: BridgeHealth::Ready,
            feedback: Some(Measured {
                robot_from_ee: home(),
                capture_time_s: now_s,
            }),
        }
    }

    fn phone(x_m: f64, yaw_rad: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(x_m, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_rad),
        )
    }

    fn round(pose: Option<Result<Isometry3<f64>, String>>, buttons: Vec<TeleopButton>) -> Input {
        Input::Teleop {
            session: PHONE,
            round: TeleopRound {
                pose,
                tracking_ok: true,
                buttons,
            },
        }
    }

    /// A session as the arm shell would log it: a phone binds, engages, moves (one step a jump the default
    /// gate drops), grips, disengages; a policy claims, sends a chunk, ticks play it, and the policy falls
    /// silent; a second policy is refused on the way.
    fn session() -> (FlightHeader, Vec<FlightEntry>) {
        let header = FlightHeader::new(
            "main",
            &TeleopConfig::default(),
            &ChunkConfig::default(),
            home(),
            0.0,
        );
        let mut arbiter = Arbiter::new(
            &header.teleop,
            header.chunk.clone(),
            header.measured,
            header.gripper,
        )
        .unwrap();
        let mut inputs: Vec<(f64, Input)> = vec![
            (
                1.0,
                Input::BindTeleop {
                    session: PHONE,
                    take_over: false,
                },
            ),
            (
                1.02,
                round(
                    Some(Ok(phone(0.0, 0.0))),
                    vec![TeleopButton::Clutch(ClutchKind::Engage)],
                ),
            ),
        ];
        for i in 1..=10 {
            // 4 mm and 0.02 rad a step; step 6 jumps 10 cm, which the default 6 cm threshold drops.
            let x_m = 0.004 * f64::from(i) + if i == 6 { 0.1 } else { 0.0 };
            inputs.push((
                1.02 + 0.02 * f64::from(i),
                round(Some(Ok(phone(x_m, 0.02 * f64::from(i)))), vec![]),
            ));
        }
        inputs.extend([
            (
                1.3,
                round(Some(Err("quaternion norm 1.5 is not 1".into())), vec![]),
            ),
            (
                1.32,
                round(
                    None,
                    vec![TeleopButton::Gripper(crate::gripper::GripperCommand::Set(0.8))],
                ),
            ),
            (
                1.34,
                round(None, vec![TeleopButton::Clutch(ClutchKind::Disengage)]),
            ),
            (
                1.4,
                Input::ClaimPolicy {
                    session: POLICY,
                    name: "replay".into(),
                    silence_timeout_s: 0.5,
                },
            ),
            (
                1.41,
                Input::ClaimPolicy {
                    session: POLICY + 1,
                    name: "other".into(),
                    silence_timeout_s: 0.5,
                },
            ),
            (
                1.42,
                Input::Chunk {
                    session: POLICY,
                    chunk: ActionChunk {
                        steps: (0..5)
                            .map(|k| ChunkStep {
                                robot_from_target: Isometry3::translation(
                                    0.25 + 0.005 * f64::from(k),
                                    0.0,
                                    0.2,
                                ),
                                gripper: 0.1 * f64::from(k),
                            })
                            .collect(),
                        anchor_time_s: 1.42,
                        step_period_s: 0.05,
                    },
                    observed_s: 1.42,
                },
            ),
        ]);
        for k in 1..=30 {
            inputs.push((1.42 + 0.05 * f64::from(k), Input::Tick));
        }
        let entries = inputs
            .into_iter()
            .map(|(now_s, input)| {
                let robot = ready(now_s);
                let outcome = Outcome::of(arbiter.handle(input.clone(), &robot, now_s).as_ref());
                FlightEntry {
                    now_s,
                    input,
                    robot,
                    outcome,
                }
            })
            .collect();
        (header, entries)
    }

    #[test]
    fn a_session_replays_to_the_same_commands_and_decisions() {
        let (header, entries) = session();
        let counts = replay(&header, &entries).unwrap().unwrap();
        assert_eq!(counts.inputs, entries.len());
        // The session is worth replaying: it commands, decides, and has a refusal in it.
        assert_eq!(counts.refused, 1, "{counts:?}");
        assert!(counts.commands >= 15, "{counts:?}");
        assert!(counts.decisions >= 5, "{counts:?}");
        let rejected = entries.iter().any(|e| {
            matches!(&e.outcome, Outcome::Applied(fx) if fx.decision.as_ref().is_some_and(|d| d.verdict == GateVerdict::RejectedJump))
        });
        assert!(rejected, "the jump was not in the session");
    }

    #[test]
    fn a_changed_gate_rule_is_named_at_the_first_decision_it_changes() {
        let (mut header, entries) = session();
        // A threshold between the 4 mm steps and the 10 cm jump would not change anything; one below 4 mm does.
        header.teleop.gate.jump_position_m = 0.003;
        let d = replay(&header, &entries).unwrap().unwrap_err();
        // Input 2 is the first phone step after the engage (inputs 0 and 1 bind and engage).
        assert_eq!(d.index, 2, "{d}");
        assert_eq!(d.now_s.to_bits(), entries[2].now_s.to_bits());
        // The gate now drops the step it passed: the decision says so (and the command is missing).
        assert_eq!(d.field, "decision", "{d}");
        assert!(d.replayed.contains("RejectedJump"), "{d}");
        assert!(d.input.starts_with("Teleop"), "{d}");
        assert!(d.to_string().contains("input 2 at 1.040000 s"), "{d}");
    }

    #[test]
    fn a_different_command_is_named_by_its_position_and_value() {
        let (header, mut entries) = session();
        let i = entries
            .iter()
            .position(
                |e| matches!(&e.outcome, Outcome::Applied(fx) if fx.commands.len() == 1 && e.now_s > 1.42),
            )
            .unwrap();
        let Outcome::Applied(fx) = &mut entries[i].outcome else {
            unreachable!()
        };
        fx.commands[0].gripper += 1e-12;
        let d = replay(&header, &entries).unwrap().unwrap_err();
        assert_eq!((d.index, d.field.as_str()), (i, "commands[0]"), "{d}");
        assert_ne!(d.recorded, d.replayed);
    }

    #[test]
    fn each_part_of_an_outcome_is_compared() {
        let (header, entries) = session();
        let base = |i: usize| match &entries[i].outcome {
            Outcome::Applied(fx) => fx.clone(),
            Outcome::Refused(_) => panic!("entry {i} was refused"),
        };
        // Entry 1 engages: it decides and re-indexes. The chunk entry reports its schedule.
        let chunk_at = entries
            .iter()
            .position(|e| matches!(e.input, Input::Chunk { .. }))
            .unwrap();
        let tampered: Vec<(usize, &str, Effects)> = vec![
            (
                1,
                "decision",
                Effects {
                    decision: None,
                    ..base(1)
                },
            ),
            (
                1,
                "reindexed",
                Effects {
                    reindexed: !base(1).reindexed,
                    ..base(1)
                },
            ),
            (
                1,
                "phone_error",
                Effects {
                    phone_error: "x".into(),
                    ..base(1)
                },
            ),
            (
                chunk_at,
                "chunk",
                Effects {
                    chunk: None,
                    ..base(chunk_at)
                },
            ),
            (
                chunk_at,
                "revoked",
                Effects {
                    revoked: Some(crate::arbiter::Revocation {
                        session: 1,
                        policy: "p".into(),
                        reason: "r".into(),
                    }),
                    ..base(chunk_at)
                },
            ),
            (
                1,
                "number of commands",
                Effects {
                    commands: vec![],
                    ..base(1)
                },
            ),
        ];
        for (i, field, fx) in tampered {
            let mut log = entries.clone();
            log[i].outcome = Outcome::Applied(fx);
            let d = replay(&header, &log).unwrap().unwrap_err();
            assert_eq!((d.index, d.field.as_str()), (i, field), "{d}");
        }
    }

    #[test]
    fn refusals_are_compared_by_their_message_and_against_an_applied_outcome() {
        let (header, mut entries) = session();
        let i = entries
            .iter()
            .position(|e| matches!(e.outcome, Outcome::Refused(_)))
            .unwrap();
        let Outcome::Refused(message) = entries[i].outcome.clone() else {
            unreachable!()
        };
        entries[i].outcome = Outcome::Refused(format!("{message}!"));
        let d = replay(&header, &entries).unwrap().unwrap_err();
        assert_eq!((d.index, d.field.as_str()), (i, "refusal"), "{d}");
        assert_eq!((d.recorded, d.replayed), (format!("{message}!"), message.clone()));
        entries[i].outcome = Outcome::Applied(Effects::default());
        let d = replay(&header, &entries).unwrap().unwrap_err();
        assert_eq!((d.index, d.field.as_str()), (i, "outcome"), "{d}");
        assert_eq!(d.recorded, "applied (0 commands)");
        assert_eq!(d.replayed, format!("refused: {message}"));
    }

    #[test]
    fn a_chunk_is_described_by_its_size() {
        let (_, entries) = session();
        let chunk = entries
            .iter()
            .find(|e| matches!(e.input, Input::Chunk { .. }))
            .unwrap();
        assert_eq!(
            describe(&chunk.input),
            "Chunk { session: 7, steps: 5, anchor_time_s: 1.42, step_period_s: 0.05, observed_s: 1.42 }"
        );
        assert_eq!(describe(&Input::Tick), "Tick");
    }

    #[test]
    fn another_format_version_or_a_bad_configuration_is_refused() {
        let (mut header, entries) = session();
        header.format_version = FLIGHT_FORMAT_VERSION + 1;
        assert_eq!(
            replay(&header, &entries).unwrap_err(),
            ReplayError::Version {
                found: FLIGHT_FORMAT_VERSION + 1
            }
        );
        header.format_version = FLIGHT_FORMAT_VERSION;
        header.chunk.max_steps = 0;
        assert!(matches!(replay(&header, &entries), Err(ReplayError::Config(_))));
    }

    #[test]
    fn the_replayer_counts_what_it_went_through() {
        let (header, entries) = session();
        let mut r = Replayer::new(&header).unwrap();
        assert_eq!(r.counts(), ReplayCounts::default());
        let mut commands = 0;
        let mut decisions = 0;
        for e in &entries {
            r.step(e).unwrap();
            if let Outcome::Applied(fx) = &e.outcome {
                commands += fx.commands.len();
                decisions += usize::from(fx.decision.is_some());
            }
        }
        assert_eq!(
            r.counts(),
            ReplayCounts {
                inputs: entries.len(),
                refused: 1,
                commands,
                decisions
            }
        );
    }
}

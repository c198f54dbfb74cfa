//! The scripted operator: records pick-and-place demonstrations through the public API exactly as a person
//! with a phone does. It is a `Teleop.Stream` client (poses at about 50 Hz with jittered timing, hand tremor
//! on position and orientation, clutch and gripper buttons) that sees what a person sees: where the ball and
//! the basket are (`Scene.Get`) and where the arm is (the arm state in every feedback message). Nothing
//! reaches the arm except the phone samples, through the same planner and safety gate as any phone.
//!
//! The phone-to-robot mapping is not read from the server's configuration: like a person, the operator
//! learns it by moving the phone along each of its axes once and watching the target move, then keeps its
//! estimate of the clutch's floating zero up to date from every accepted sample, so a re-index (a clutch
//! cycle, a stale stream) costs it nothing.
//!
//! Per episode: `Scene.Reset` with the episode's seed (homing the arm), `Episodes.Start`, reach above the
//! ball, descend, close, lift, carry above the basket (with a clutch cycle half way when asked), open, wait
//! for the ball to land, then `Episodes.Stop` if `Scene.Get` reports success, else `Episodes.Discard`.

use anyhow::{Context as _, bail};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use phone2act_sdk::proto as v1;
use phone2act_sdk::{Client, TeleopOptions, TeleopSession, buttons};
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::{RngCore, SeedableRng};
use std::time::{Duration, Instant};

/// The task text recorded when none is given.
pub const DEFAULT_TASK: &str = "pick up the ball and put it in the basket";

/// Nominal sample period of the phone (50 Hz, the Phone2Act app's rate).
const PERIOD_S: f64 = 0.02;
/// Uniform jitter on each period: a phone's frame callbacks are not evenly spaced.
const PERIOD_JITTER_S: f64 = 0.006;
/// Now and then a frame is late (GC pause, Wi-Fi retry): probability per sample and the extra delay range.
/// The extra stays below the server's 0.3 s staleness timeout, as a working phone's does.
const HICCUP_PROBABILITY: f64 = 0.02;
const HICCUP_S: (f64, f64) = (0.03, 0.08);
/// Hand tremor: standard deviation of the position noise on every sample, and of the rotation noise about
/// each axis.
const TREMOR_M: f64 = 0.0005;
const TREMOR_RAD: f64 = 0.003;
/// Where the hand holds the phone in the tracking frame (WebXR: y up, metres) when a session starts.
const PHONE_REST_M: [f64; 3] = [0.0, 1.2, -0.3];
/// Hand displacement used to learn the mapping, per axis.
const PROBE_M: f64 = 0.03;
/// Hand speeds: travelling through the air, and the last centimetres down to the ball.
const TRAVEL_M_S: f64 = 0.15;
const APPROACH_M_S: f64 = 0.06;
/// Height of the tool above the ball's centre before descending, and of the carry (tool centre, above the
/// table): the ball hangs below the tool, so its bottom clears the basket wall by several centimetres.
const HOVER_ABOVE_BALL_M: f64 = 0.08;
const CARRY_HEIGHT_M: f64 = 0.14;
/// "Close enough" as a person judges it before closing or opening the gripper; the sim grasps within 3 cm.
const REACHED_M: f64 = 0.008;
/// Largest move the hand asks of the arm's target in one sample, from where the server last put it: well
/// inside the safety gate's 6 cm jump threshold. On a starved machine the frame loop stalls, the path moves
/// on meanwhile, and one sample asking for the whole gap is refused as a jump; asking for that gap again on
/// every sample would be refused for ever (the episode times out), so the hand closes it in steps instead.
const MAX_STEP_M: f64 = 0.04;
/// Time given to the gripper to close on the ball, and to the ball to fall and settle after opening.
const CLOSE_S: f64 = 0.4;
const DROP_S: f64 = 0.8;
/// After the ball lands the operator keeps still this long, so the episode ends with frames of success.
const TAIL_S: f64 = 0.5;
/// Times a seed is tried again after the server refused a phone sample during it (the arm not ready: its
/// measured pose went stale on a starved machine); after that the seed is skipped with the refusal as reason.
pub const MAX_REFUSED_TRIES: u32 = 3;
/// How long the operator waits, streaming disengaged, for the server to accept samples again after a refusal
/// before giving up the run: a stale pose that does not freshen in this long is a stuck bridge, not load.
const RECOVER_S: f64 = 30.0;

/// What to record.
#[derive(Clone, Debug)]
pub struct OperatorOptions {
    pub arm: String,
    pub episodes: u64,
    /// Episode `k` (from 0) uses scene seed `seed + k`.
    pub seed: u64,
    pub task: String,
    /// Longest an episode may take; one that has not succeeded by then is discarded.
    pub episode_time_s: f64,
    /// Pause after each scene reset, before recording starts.
    pub reset_time_s: f64,
    /// Release and re-grip the clutch half way through the carry, re-centring the hand as people do.
    pub clutch_cycles: bool,
}

impl Default for OperatorOptions {
    fn default() -> Self {
        Self {
            arm: "main".to_owned(),
            episodes: 10,
            seed: 0,
            task: DEFAULT_TASK.to_owned(),
            episode_time_s: 30.0,
            reset_time_s: 1.0,
            clutch_cycles: false,
        }
    }
}

/// One episode's outcome.
#[derive(Clone, Debug)]
pub struct EpisodeReport {
    /// 0-based attempt number.
    pub attempt: u64,
    pub seed: u64,
    pub success: bool,
    /// Saved as dataset episode `episode_index` (only successes are saved).
    pub saved: bool,
    pub episode_index: Option<u64>,
    pub frames: u64,
    pub duration_s: f64,
    /// Why it failed, if it did.
    pub note: String,
}

/// The run's outcome; [`Summary::to_json`] is the machine-readable line.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Summary {
    /// Seeds played to their end (saved or discarded as failed); a skipped seed is not counted.
    pub attempted: u64,
    pub succeeded: u64,
    pub saved: u64,
    /// The seeds attempted, in order.
    pub seeds: Vec<u64>,
    /// Tries the server cut short by refusing a phone sample; each was discarded and its seed tried again.
    pub refused: u64,
    /// Seeds given up after [`MAX_REFUSED_TRIES`] refused tries, with the last refusal.
    pub skipped: Vec<(u64, String)>,
}

impl Summary {
    pub fn success_rate(&self) -> f64 {
        if self.attempted == 0 {
            0.0
        } else {
            self.succeeded as f64 / self.attempted as f64
        }
    }

    /// `{"attempted":..,"succeeded":..,"saved":..,"success_rate":..,"seeds":[..],"refused":..,"skipped":[..]}`,
    /// keys in that order; `skipped` lists `{"seed":..,"reason":..}`.
    pub fn to_json(&self) -> String {
        let skipped: Vec<serde_json::Value> = self
            .skipped
            .iter()
            .map(|(seed, reason)| serde_json::json!({"seed": seed, "reason": reason}))
            .collect();
        let fields = [
            ("attempted", serde_json::json!(self.attempted)),
            ("succeeded", serde_json::json!(self.succeeded)),
            ("saved", serde_json::json!(self.saved)),
            ("success_rate", serde_json::json!(self.success_rate())),
            ("seeds", serde_json::json!(self.seeds)),
            ("refused", serde_json::json!(self.refused)),
            ("skipped", serde_json::json!(skipped)),
        ];
        let body: Vec<String> = fields.iter().map(|(k, v)| format!("\"{k}\":{v}")).collect();
        format!("{{{}}}", body.join(","))
    }
}

/// What became of one try of a seed.
enum Try {
    /// Played to its end: saved, or discarded as failed.
    Done(EpisodeReport),
    /// The server refused a phone sample (the reason); whatever was recorded was discarded.
    Refused(String),
}

/// Records `options.episodes` episodes through `client`, calling `on_episode` after each and `on_refused`
/// (seed, try from 1, reason) after each try the server cut short.
pub async fn run(
    client: &Client,
    options: &OperatorOptions,
    mut on_episode: impl FnMut(&EpisodeReport),
    mut on_refused: impl FnMut(u64, u32, &str),
) -> anyhow::Result<Summary> {
    if !(options.episode_time_s.is_finite() && options.episode_time_s > 0.0) {
        bail!("episode time must be a positive number of seconds");
    }
    if !(options.reset_time_s.is_finite() && options.reset_time_s >= 0.0) {
        bail!("reset time must be zero or more seconds");
    }
    let session = client
        .teleop(
            &options.arm,
            TeleopOptions {
                client_name: "scripted-operator".to_owned(),
                take_over: false,
            },
        )
        .await
        .context("opening the phone's teleop stream")?;
    let mut phone = Hand::new(session, options.seed);
    // The phone's first sample binds the arm; an unknown arm ends the stream here.
    phone.tick(Vec::new(), None).await?;
    // Learned once, before anything is recorded: the home pose leaves room to move 3 cm every way.
    client.scene().reset(&options.arm, None, true).await?;
    phone.engage(None).await.map_err(Stop::into_error)?;
    phone.probe().await?;
    phone.disengage(None).await?;

    let mut summary = Summary::default();
    for attempt in 0..options.episodes {
        let seed = options.seed.wrapping_add(attempt);
        let mut budget = RefusalBudget::new(MAX_REFUSED_TRIES);
        loop {
            match episode(client, &mut phone, options, attempt, seed).await? {
                Try::Done(report) => {
                    summary.attempted += 1;
                    summary.succeeded += u64::from(report.success);
                    summary.saved += u64::from(report.saved);
                    summary.seeds.push(seed);
                    on_episode(&report);
                    break;
                }
                Try::Refused(reason) => {
                    summary.refused += 1;
                    let next = budget.refused(&reason);
                    on_refused(seed, budget.tries(), &reason);
                    // The clutch is let go before the next try, which starts like any episode: a scene
                    // reset, the gripper opened.
                    phone.recover().await?;
                    if let Next::Skip(reason) = next {
                        summary.skipped.push((seed, reason));
                        break;
                    }
                }
            }
        }
    }
    Ok(summary)
}

async fn episode(
    client: &Client,
    phone: &mut Hand,
    options: &OperatorOptions,
    attempt: u64,
    seed: u64,
) -> anyhow::Result<Try> {
    let arm = options.arm.as_str();
    let mut scene_api = client.scene();
    scene_api.reset(arm, Some(seed), true).await?;
    // The phone's gripper setting outlives the reset (the server keeps it while the homed gripper opens): after
    // a try that ended with the ball held, the next episode's first move would close the fingers again. A
    // person opens the gripper before starting, outside the recording.
    let ready = async {
        phone.tick(vec![buttons::gripper_set(0.0)], None).await?;
        phone.idle(options.reset_time_s).await
    };
    if let Err(e) = ready.await {
        // Refused before recording started: nothing to discard.
        return refusal(&e).map(Try::Refused).ok_or(e);
    }
    let scene = scene_api.get(arm).await?;
    let mut episodes = client.episodes();
    episodes.start(&options.task).await?;
    let started = Instant::now();
    // From here every way out either saves the episode (a success) or discards it, so the dataset never holds
    // half an episode, whatever the server or the stream does.
    let played = play(client, phone, options, &scene, started).await;
    let duration_s = started.elapsed().as_secs_f64();
    let (success, note) = match played {
        Ok(outcome) => outcome,
        Err(e) => {
            let discarded = episodes.discard().await;
            return match refusal(&e) {
                Some(reason) => {
                    discarded.context("discarding an episode the server cut short")?;
                    Ok(Try::Refused(reason))
                }
                // The stream or the server failed: nothing to save, and nothing more to do this run.
                None => Err(e),
            };
        }
    };
    let (saved, episode_index, frames) = if success {
        let info = episodes
            .stop()
            .await?
            .episode
            .context("Stop answered without an episode")?;
        (true, Some(info.episode_index), info.length_frames)
    } else {
        (false, None, episodes.discard().await?)
    };
    Ok(Try::Done(EpisodeReport {
        attempt,
        seed,
        success,
        saved,
        episode_index,
        frames,
        duration_s,
        note: if success || !note.is_empty() {
            note
        } else {
            "the ball did not end in the basket".to_owned()
        },
    }))
}

/// The recorded part of an episode: the pick-and-place, letting go of the clutch, and the scene's verdict.
/// Returns (success, why it stopped early if it did).
async fn play(
    client: &Client,
    phone: &mut Hand,
    options: &OperatorOptions,
    scene: &v1::SceneState,
    started: Instant,
) -> anyhow::Result<(bool, String)> {
    let deadline = started + Duration::from_secs_f64(options.episode_time_s);
    let note = match pick_and_place(phone, scene, deadline, options.clutch_cycles).await {
        Ok(()) => String::new(),
        Err(Stop::TimeUp(what)) => format!("time up while {what} ({})", phone.account()),
        Err(Stop::Api(e)) => return Err(e),
    };
    phone.disengage(None).await?;
    let success = client.scene().get(&options.arm).await?.success;
    Ok((success, note))
}

/// The server's reason, if `error` is its refusal of a phone sample.
fn refusal(error: &anyhow::Error) -> Option<String> {
    error.downcast_ref::<Refused>().map(|r| r.0.clone())
}

/// What the operator does after the server cut a try short.
#[derive(Debug, PartialEq)]
enum Next {
    Retry,
    /// Give the seed up, for this reason.
    Skip(String),
}

/// Counts one seed's refused tries.
struct RefusalBudget {
    max_tries: u32,
    tries: u32,
}

impl RefusalBudget {
    fn new(max_tries: u32) -> Self {
        Self { max_tries, tries: 0 }
    }

    /// Refused tries so far.
    fn tries(&self) -> u32 {
        self.tries
    }

    fn refused(&mut self, reason: &str) -> Next {
        self.tries += 1;
        if self.tries >= self.max_tries {
            Next::Skip(format!(
                "the server refused a phone sample on {} tries; last: {reason}",
                self.tries
            ))
        } else {
            Next::Retry
        }
    }
}

/// Why a pick-and-place stopped early.
enum Stop {
    /// The episode's time ran out during the named phase.
    TimeUp(&'static str),
    Api(anyhow::Error),
}

impl Stop {
    fn into_error(self) -> anyhow::Error {
        match self {
            Self::TimeUp(what) => anyhow::anyhow!("time up while {what}"),
            Self::Api(e) => e,
        }
    }
}

impl From<anyhow::Error> for Stop {
    fn from(e: anyhow::Error) -> Self {
        Self::Api(e)
    }
}

async fn pick_and_place(
    phone: &mut Hand,
    scene: &v1::SceneState,
    deadline: Instant,
    clutch_cycle: bool,
) -> Result<(), Stop> {
    let ball = vec3(scene.ball_position_m.as_ref());
    let basket = vec3(scene.basket_position_m.as_ref());
    let above_ball = ball + Vector3::new(0.0, 0.0, HOVER_ABOVE_BALL_M);
    let above_basket = Vector3::new(basket.x, basket.y, CARRY_HEIGHT_M);
    let lifted = Vector3::new(ball.x, ball.y, CARRY_HEIGHT_M);

    phone.engage(Some(deadline)).await?;
    phone
        .move_to(above_ball, TRAVEL_M_S, deadline, "reaching")
        .await?;
    phone.move_to(ball, APPROACH_M_S, deadline, "descending").await?;
    phone.settle(REACHED_M, deadline, "descending").await?;
    phone.gripper(1.0, CLOSE_S, deadline, "closing").await?;
    phone.move_to(lifted, APPROACH_M_S, deadline, "lifting").await?;
    if clutch_cycle {
        let half_way = lifted + (above_basket - lifted) * 0.5;
        phone.move_to(half_way, TRAVEL_M_S, deadline, "carrying").await?;
        phone.clutch_cycle(deadline).await?;
    }
    phone
        .move_to(above_basket, TRAVEL_M_S, deadline, "carrying")
        .await?;
    phone.settle(REACHED_M, deadline, "carrying").await?;
    phone.gripper(0.0, DROP_S, deadline, "dropping").await?;
    phone.hold(TAIL_S, deadline, "watching the ball").await?;
    Ok(())
}

fn vec3(v: Option<&v1::Vec3>) -> Vector3<f64> {
    v.map_or_else(Vector3::zeros, |v| Vector3::new(v.x, v.y, v.z))
}

fn position(pose: Option<&v1::Pose>) -> Option<Vector3<f64>> {
    pose.and_then(|p| p.position_m.as_ref())
        .map(|p| Vector3::new(p.x, p.y, p.z))
}

/// `goal`, or the point `max_m` from `from` toward it if it is farther.
fn step_toward(from: Vector3<f64>, goal: Vector3<f64>, max_m: f64) -> Vector3<f64> {
    let gap = goal - from;
    let gap_m = gap.norm();
    if gap_m <= max_m {
        goal
    } else {
        from + gap * (max_m / gap_m)
    }
}

/// Minimum-jerk profile: the smooth start and stop of a human reach.
fn min_jerk(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

/// The operator's hand and the phone in it.
struct Hand {
    session: TeleopSession,
    rng: ChaCha8Rng,
    /// Robot target displacement per phone displacement (column `i`: phone axis `i`), and its inverse.
    robot_per_phone: Matrix3<f64>,
    phone_per_robot: Matrix3<f64>,
    /// The floating zero as the operator understands it: target = `offset_m` + `robot_per_phone` · phone.
    offset_m: Vector3<f64>,
    /// Where the hand means the phone to be (before tremor), and the robot target it means by that.
    phone_m: Vector3<f64>,
    goal_m: Vector3<f64>,
    state: v1::ArmState,
    next_tick: Instant,
    epoch: Instant,
}

impl Hand {
    fn new(session: TeleopSession, seed: u64) -> Self {
        Self {
            session,
            // Its own stream, so the hand does not repeat the scene generator's numbers.
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x0123_4567_89ab_cdef),
            robot_per_phone: Matrix3::identity(),
            phone_per_robot: Matrix3::identity(),
            offset_m: Vector3::zeros(),
            phone_m: Vector3::from(PHONE_REST_M),
            goal_m: Vector3::zeros(),
            state: v1::ArmState::default(),
            next_tick: Instant::now(),
            epoch: Instant::now(),
        }
    }

    fn uniform(&mut self) -> f64 {
        (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A standard normal sample (Box-Muller).
    fn normal(&mut self) -> f64 {
        let u = self.uniform().max(f64::MIN_POSITIVE);
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// One phone frame: waits for the frame's (jittered) time, sends the hand's pose with tremor and
    /// `buttons`, and reads the arm state the server answers with.
    async fn tick(&mut self, buttons: Vec<v1::ButtonEvent>, deadline: Option<Instant>) -> anyhow::Result<()> {
        tokio::time::sleep_until(self.next_tick.into()).await;
        let mut period_s = PERIOD_S + (2.0 * self.uniform() - 1.0) * PERIOD_JITTER_S;
        if self.uniform() < HICCUP_PROBABILITY {
            period_s += HICCUP_S.0 + self.uniform() * (HICCUP_S.1 - HICCUP_S.0);
        }
        // A late frame is not made up for: the next one follows a period after this one.
        self.next_tick = Instant::now().max(self.next_tick) + Duration::from_secs_f64(period_s);
        let tremor = Vector3::new(self.normal(), self.normal(), self.normal()) * TREMOR_M;
        let sent = self.phone_m + tremor;
        let wobble = UnitQuaternion::from_scaled_axis(
            Vector3::new(self.normal(), self.normal(), self.normal()) * TREMOR_RAD,
        );
        let q = wobble.quaternion();
        let pose = v1::Pose::from_parts([sent.x, sent.y, sent.z], [q.i, q.j, q.k, q.w]);
        let capture_time_ns = i64::try_from(self.epoch.elapsed().as_nanos()).unwrap_or(i64::MAX);
        let seq = self.session.send_pose(pose, buttons, capture_time_ns).await?;
        let feedback = self.session.feedback_for(seq).await?;
        if !feedback.error.is_empty() {
            return Err(Refused(feedback.error).into());
        }
        self.state = feedback.arm_state.context("feedback without arm state")?;
        let decision = self.state.last_decision.clone().unwrap_or_default();
        let clean = decision.verdict() == v1::GateVerdict::Accepted
            && !decision.workspace_clamped
            && !decision.velocity_limited;
        if self.state.engaged
            && clean
            && let Some(target) = position(self.state.robot_from_target.as_ref())
        {
            self.offset_m = target - self.robot_per_phone * sent;
        }
        if deadline.is_some_and(|d| Instant::now() > d) {
            bail!(TimeUp);
        }
        Ok(())
    }

    /// Where things stood, for a failed episode's note: how far the arm's target and the measured tool are
    /// from the goal, the gripper, and what the gate last did.
    fn account(&self) -> String {
        let cm = |p: Option<Vector3<f64>>| {
            p.map_or_else(
                || "unknown".to_owned(),
                |p| format!("{:.1} cm", (p - self.goal_m).norm() * 100.0),
            )
        };
        let decision = self.state.last_decision.clone().unwrap_or_default();
        format!(
            "target {} from the goal, tool {}, gripper {:.2} (target {:.2}), gate {:?}{}{}, joint-limited {}, \
             orientation unreachable {}",
            cm(self.target_m()),
            cm(self.measured_m()),
            self.state.gripper_position,
            self.state.gripper_target,
            decision.verdict(),
            if decision.workspace_clamped {
                ", clamped"
            } else {
                ""
            },
            if decision.velocity_limited {
                ", velocity-limited"
            } else {
                ""
            },
            self.state.commands_joint_limited,
            self.state.commands_orientation_unreachable,
        )
    }

    fn target_m(&self) -> Option<Vector3<f64>> {
        position(self.state.robot_from_target.as_ref())
    }

    fn measured_m(&self) -> Option<Vector3<f64>> {
        position(self.state.robot_from_ee.as_ref())
    }

    /// Presses the clutch where the hand is; the arm's target there becomes the goal.
    async fn engage(&mut self, deadline: Option<Instant>) -> Result<(), Stop> {
        self.tick(vec![buttons::clutch_engage()], deadline)
            .await
            .map_err(|e| phase(e, "engaging"))?;
        if !self.state.engaged {
            return Err(Stop::Api(anyhow::anyhow!(
                "engaging did not engage arm {:?}: {:?}",
                self.state.arm,
                self.state.last_decision
            )));
        }
        let target = self.target_m().context("no target after engaging")?;
        self.offset_m = target - self.robot_per_phone * self.phone_m;
        self.goal_m = target;
        Ok(())
    }

    async fn disengage(&mut self, deadline: Option<Instant>) -> anyhow::Result<()> {
        self.tick(vec![buttons::clutch_disengage()], deadline).await
    }

    /// Moves the phone by `PROBE_M` along each of its axes and back, and reads the mapping off the targets.
    async fn probe(&mut self) -> anyhow::Result<()> {
        let rest = self.phone_m;
        let base = self.target_m().context("no target to probe from")?;
        let mut columns = [Vector3::zeros(); 3];
        for (axis, column) in columns.iter_mut().enumerate() {
            let mut out = rest;
            out[axis] += PROBE_M;
            self.phone_path(rest, out, 0.3).await?;
            for _ in 0..3 {
                self.tick(Vec::new(), None).await?;
            }
            // Read against the tremor-free hand: the tremor's 0.5 mm is noise on a 30 mm probe.
            *column = (self.target_m().context("no target while probing")? - base) / PROBE_M;
            self.phone_path(out, rest, 0.3).await?;
        }
        let robot_per_phone = Matrix3::from_columns(&columns);
        let Some(phone_per_robot) = robot_per_phone.try_inverse() else {
            bail!("the phone's axes do not move the arm independently: {robot_per_phone}");
        };
        if robot_per_phone.determinant().abs() < 1e-3 {
            bail!("the phone barely moves the arm (mapping {robot_per_phone}); is the position scale tiny?");
        }
        self.robot_per_phone = robot_per_phone;
        self.phone_per_robot = phone_per_robot;
        self.engage_estimate();
        Ok(())
    }

    fn engage_estimate(&mut self) {
        if let Some(target) = self.target_m() {
            self.offset_m = target - self.robot_per_phone * self.phone_m;
            self.goal_m = target;
        }
    }

    /// The phone along a straight minimum-jerk path, in the phone's own frame.
    async fn phone_path(&mut self, from: Vector3<f64>, to: Vector3<f64>, seconds: f64) -> anyhow::Result<()> {
        let start = Instant::now();
        loop {
            let s = min_jerk(start.elapsed().as_secs_f64() / seconds);
            self.phone_m = from + (to - from) * s;
            self.tick(Vec::new(), None).await?;
            if s >= 1.0 {
                return Ok(());
            }
        }
    }

    /// Puts the phone where the arm's target goes toward the goal: at the goal, or `MAX_STEP_M` toward it
    /// from the arm's present target while the clutch is in and the goal is farther.
    fn aim(&mut self) {
        let toward = match self.target_m() {
            Some(target) if self.state.engaged => step_toward(target, self.goal_m, MAX_STEP_M),
            _ => self.goal_m,
        };
        self.phone_m = self.phone_for(toward);
    }

    /// Where the phone must be for the arm's target to be `robot_m`.
    fn phone_for(&self, robot_m: Vector3<f64>) -> Vector3<f64> {
        self.phone_per_robot * (robot_m - self.offset_m)
    }

    /// Moves the arm's target from the current goal to `goal` at about `speed_m_s`, as a reach.
    async fn move_to(
        &mut self,
        goal: Vector3<f64>,
        speed_m_s: f64,
        deadline: Instant,
        what: &'static str,
    ) -> Result<(), Stop> {
        let from = self.goal_m;
        let seconds = ((goal - from).norm() / speed_m_s).max(0.3);
        let start = Instant::now();
        loop {
            let s = min_jerk(start.elapsed().as_secs_f64() / seconds);
            self.goal_m = from + (goal - from) * s;
            self.aim();
            self.tick(Vec::new(), Some(deadline))
                .await
                .map_err(|e| phase(e, what))?;
            if s >= 1.0 {
                return Ok(());
            }
        }
    }

    /// Holds the goal until the measured tool is within `tolerance_m` of it: a person waits to see the
    /// gripper around the ball before closing it.
    async fn settle(&mut self, tolerance_m: f64, deadline: Instant, what: &'static str) -> Result<(), Stop> {
        loop {
            self.aim();
            self.tick(Vec::new(), Some(deadline))
                .await
                .map_err(|e| phase(e, what))?;
            if self
                .measured_m()
                .is_some_and(|m| (m - self.goal_m).norm() <= tolerance_m)
            {
                return Ok(());
            }
        }
    }

    /// Keeps the hand on the goal for `seconds`.
    async fn hold(&mut self, seconds: f64, deadline: Instant, what: &'static str) -> Result<(), Stop> {
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < seconds {
            self.aim();
            self.tick(Vec::new(), Some(deadline))
                .await
                .map_err(|e| phase(e, what))?;
        }
        Ok(())
    }

    /// Sets the gripper and holds still while it acts.
    async fn gripper(
        &mut self,
        position: f64,
        seconds: f64,
        deadline: Instant,
        what: &'static str,
    ) -> Result<(), Stop> {
        self.aim();
        self.tick(vec![buttons::gripper_set(position)], Some(deadline))
            .await
            .map_err(|e| phase(e, what))?;
        self.hold(seconds, deadline, what).await
    }

    /// Releases the clutch, brings the hand back toward its rest position (the arm holds), and grips again.
    async fn clutch_cycle(&mut self, deadline: Instant) -> Result<(), Stop> {
        self.tick(vec![buttons::clutch_disengage()], Some(deadline))
            .await
            .map_err(|e| phase(e, "re-gripping the clutch"))?;
        let from = self.phone_m;
        let to = from + (Vector3::from(PHONE_REST_M) - from) * 0.7;
        self.phone_path(from, to, 0.4)
            .await
            .map_err(|e| phase(e, "re-gripping the clutch"))?;
        self.engage(Some(deadline)).await
    }

    /// After a refused sample: lets go of the clutch (sent until the server takes it; a refused sample
    /// changes nothing) and streams on until the server accepts samples again, at most `RECOVER_S`.
    async fn recover(&mut self) -> anyhow::Result<()> {
        let give_up = Instant::now() + Duration::from_secs_f64(RECOVER_S);
        loop {
            match self.tick(vec![buttons::clutch_disengage()], None).await {
                Ok(()) if !self.state.engaged => return Ok(()),
                Ok(()) => {}
                Err(e) if e.is::<Refused>() && Instant::now() < give_up => {}
                Err(e) => {
                    return Err(e.context(format!(
                        "the server still refuses phone samples after {RECOVER_S} s"
                    )));
                }
            }
        }
    }

    /// Keeps the phone streaming, disengaged, for `seconds` (the reset phase).
    async fn idle(&mut self, seconds: f64) -> anyhow::Result<()> {
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < seconds {
            self.tick(Vec::new(), None).await?;
        }
        Ok(())
    }
}

/// The server refused a phone sample (its reason, e.g. the arm not ready because its measured pose is stale).
#[derive(Debug)]
struct Refused(String);

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "the server refused a phone sample: {}", self.0)
    }
}

impl std::error::Error for Refused {}

/// Marker error: the episode's deadline passed.
#[derive(Debug)]
struct TimeUp;

impl std::fmt::Display for TimeUp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("episode time is up")
    }
}

impl std::error::Error for TimeUp {}

fn phase(error: anyhow::Error, what: &'static str) -> Stop {
    if error.is::<TimeUp>() {
        Stop::TimeUp(what)
    } else {
        Stop::Api(error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn min_jerk_starts_and_ends_at_rest() {
        assert!(min_jerk(0.0).abs() < 1e-15 && (min_jerk(1.0) - 1.0).abs() < 1e-15);
        assert!((min_jerk(0.5) - 0.5).abs() < 1e-15);
        // Slope zero at both ends: small steps where a reach starts and stops.
        assert!(min_jerk(0.01) < 1e-4 && 1.0 - min_jerk(0.99) < 1e-4);
        assert!((min_jerk(2.0) - 1.0).abs() < 1e-15 && min_jerk(-1.0).abs() < 1e-15);
    }

    #[test]
    fn a_step_toward_the_goal_is_bounded() {
        let from = Vector3::new(0.2, 0.0, 0.1);
        let near = Vector3::new(0.21, 0.01, 0.1);
        assert_eq!(step_toward(from, near, MAX_STEP_M), near);
        let far = Vector3::new(0.2, 0.15, 0.1);
        let step = step_toward(from, far, MAX_STEP_M);
        assert!(((step - from).norm() - MAX_STEP_M).abs() < 1e-12);
        assert!((step - from).normalize().dot(&(far - from).normalize()) > 1.0 - 1e-12);
        // Repeated from where each step ends, it arrives: a refused jump is not asked for again.
        let mut at = from;
        for _ in 0..4 {
            at = step_toward(at, far, MAX_STEP_M);
        }
        assert_eq!(at, far);
    }

    #[test]
    fn the_summary_line_is_the_documented_json() {
        let summary = Summary {
            attempted: 4,
            succeeded: 3,
            saved: 3,
            seeds: vec![10, 11, 12, 13],
            refused: 4,
            skipped: vec![(14, "arm not ready".to_owned())],
        };
        let line = summary.to_json();
        assert!(
            line.starts_with(r#"{"attempted":4,"succeeded":3,"saved":3,"success_rate":0.75,"seeds":["#),
            "{line}"
        );
        let value: serde_json::Value = serde_json::from_str(&line).unwrap();
        assert_eq!(
            value,
            serde_json::json!({"attempted": 4, "succeeded": 3, "saved": 3, "success_rate": 0.75,
                               "seeds": [10, 11, 12, 13], "refused": 4,
                               "skipped": [{"seed": 14, "reason": "arm not ready"}]})
        );
    }

    #[test]
    fn a_refused_seed_is_tried_again_then_skipped_with_the_last_reason() {
        let mut budget = RefusalBudget::new(3);
        assert_eq!(budget.refused("pose 1.00 s old"), Next::Retry);
        assert_eq!(budget.refused("pose 1.20 s old"), Next::Retry);
        assert_eq!(budget.tries(), 2);
        let Next::Skip(reason) = budget.refused("pose 1.50 s old") else {
            panic!("a third refusal must skip the seed");
        };
        assert!(
            reason.contains("3 tries") && reason.ends_with("pose 1.50 s old"),
            "{reason}"
        );
    }

    #[test]
    fn only_the_servers_refusal_counts_as_one() {
        let refused = anyhow::Error::from(Refused("arm \"main\" is not ready".to_owned()));
        // Through the context a phase adds, as the episode sees it.
        let wrapped = refused.context("carrying");
        assert_eq!(refusal(&wrapped).as_deref(), Some("arm \"main\" is not ready"));
        assert_eq!(refusal(&anyhow::anyhow!("stream closed")), None);
        assert_eq!(refusal(&anyhow::Error::from(TimeUp)), None);
    }
}

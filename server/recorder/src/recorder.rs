//! The recorder: a tick thread on a fixed grid at the dataset fps on the monotonic clock, and a sampler
//! thread that keeps the robot's recent samples with their capture times. Frame i of an episode is the tick
//! at `first_tick + i / fps`: it holds the robot sample and each camera's frame captured at or before that
//! instant (see [`crate::timeline`]), whenever the tick thread gets to write it, so a late wake-up writes the
//! ticks it missed each at its own time. `timestamp` follows `frame_index` (see
//! [`crate::dataset::timestamp_s`]).
//!
//! What could not be kept at its time is counted. A tick whose sample was captured farther from it than
//! `sample_tolerance_s` is still written (skipping it would shift every later frame off its time) and
//! counted as a late tick, with a `late_tick` event in the episode's sidecar. A source that has sent nothing
//! within `hold_tolerance_s` before a tick *pauses* the episode: those ticks are not recorded (counted in
//! `paused_ticks`, phase `Paused`, the warning names the source) and a `paused` event marks the frame where
//! the episode's time jumps. A tick that reuses the previous tick's sample of a source (a camera slower than
//! the dataset) is counted as held.

use crate::camera::{Frame, FrameSlot};
use crate::dataset::{Dataset, EpisodeSummary, EpisodeWriter, FrameFlags};
use crate::error::RecorderError;
use crate::events::{ArmActivity, EventKind};
use crate::spec::DatasetSpec;
use crate::timeline::{Pick, TickClock, TimedRing, Timing, judge};
use parking_lot::{Condvar, Mutex};
use phone2act_clock::monotonic_ns;
use serde::Serialize;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The newest measured state and the executed action (after the safety gate), in the dataset's layout.
#[derive(Clone, Debug, PartialEq)]
pub struct RobotSample {
    pub state: Vec<f64>,
    pub action: Vec<f64>,
    /// The task's success flag at this sample (recorded as `next.success` when the dataset has it).
    pub success: bool,
    pub capture_time_ns: i64,
    /// Each arm's clutch state and gate counters, from which the episode's events sidecar is derived
    /// (see [`crate::events`]); empty for a source without arms.
    pub arms: Vec<ArmActivity>,
}

/// Where the recorder reads robot samples from.
pub trait RobotSource: Send + Sync {
    /// The newest sample, if any.
    fn sample(&self) -> Option<RobotSample>;
}

/// Recorder phase.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Phase {
    Idle,
    Recording,
    /// Recording, but a source is stale beyond tolerance: ticks are not recorded.
    Paused,
    Saving,
}

/// What the operator sees.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RecorderStatus {
    pub phase: Phase,
    /// The episode being recorded, or the index the next one will get.
    pub episode_index: u64,
    pub task: String,
    /// Who records the episode in progress (empty when unknown or idle).
    pub operator: String,
    pub frames_recorded: u64,
    pub duration_s: f64,
    pub held_ticks: u64,
    pub paused_ticks: u64,
    pub late_ticks: u64,
    pub dropped_frames: u64,
    pub episodes_saved: u64,
    pub warning: Option<String>,
    pub fps: u32,
    /// Increases on every change; see [`Recorder::watch`].
    pub version: u64,
}

/// Sync gate settings.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SyncConfig {
    /// A source that has sent nothing within this before a tick pauses the episode.
    pub hold_tolerance_s: f64,
    /// A tick whose sample of a source was captured farther than this from the tick is recorded but counted
    /// as late.
    pub sample_tolerance_s: f64,
    /// How long after its time a tick is written, so that samples captured just before it have arrived.
    pub settle_s: f64,
    /// How often the sampler thread reads the robot while an episode is recorded.
    pub sample_period_s: f64,
    /// Robot samples kept (the sampler keeps only new ones: at 200 Hz, 2.5 s).
    pub robot_history: usize,
    /// Encoder queue length per camera, in frames.
    pub queue_frames: usize,
}

impl SyncConfig {
    /// Defaults for `fps`: hold up to 0.25 s (5 ticks at 20 fps); late beyond 0.1 s, two periods of a 20 fps
    /// camera (a camera slower than the dataset is held, not late); ticks written 20 ms after their time; the
    /// robot read every 5 ms (the simulator's step, faster than any bridge's feedback) and 512 samples kept;
    /// half a second of encoder queue.
    pub fn for_fps(fps: u32) -> Self {
        SyncConfig {
            hold_tolerance_s: 0.25,
            sample_tolerance_s: 0.1,
            settle_s: 0.02,
            sample_period_s: 0.005,
            robot_history: 512,
            queue_frames: (fps as usize / 2).max(4),
        }
    }
}

struct Active {
    writer: EpisodeWriter,
    /// The tick that is the episode's frame 0.
    first_tick: u64,
    held: u64,
    paused: u64,
    /// Ticks paused since the last recorded frame, and why (the `paused` event of the next frame).
    paused_run: u64,
    pause_why: String,
    late: u64,
    start_unix_ns: i64,
    last_robot_ns: Option<i64>,
    last_seq: Vec<Option<u64>>,
    error: Option<RecorderError>,
    operator: String,
}

struct TickState {
    active: Option<Active>,
    phase: Phase,
    warning: Option<String>,
    version: u64,
    /// Committed episodes, cached so that status never waits for a save in progress.
    saved: u64,
}

struct Shared {
    dataset: Mutex<Dataset>,
    tick: Mutex<TickState>,
    changed: Condvar,
    stop: AtomicBool,
    robot: Arc<dyn RobotSource>,
    /// The robot's recent samples by capture time, filled by the sampler thread.
    robot_history: Mutex<TimedRing<RobotSample>>,
    /// Whether the sampler reads the robot (while an episode is recorded); it waits on `sampler_wake`.
    sampling: Mutex<bool>,
    sampler_wake: Condvar,
    clock: TickClock,
    cameras: Vec<Arc<FrameSlot>>,
    camera_names: Vec<String>,
    fps: u32,
    sync: SyncConfig,
    commit_hook: Mutex<Option<Arc<dyn CommitHook>>>,
    /// Frames an episode holds at most (0: no limit); ticks past it are not written, so an episode saved at
    /// its time limit has exactly the limit's frames whenever the save comes.
    frame_limit: std::sync::atomic::AtomicU64,
}

/// Told about every committed episode, on the recorder's thread and under its dataset lock (so before the
/// next commit can replace any file): an uploader takes its snapshot here. Must return quickly.
pub trait CommitHook: Send + Sync {
    /// `files`: dataset-relative, in the order the commit made them visible (`info.json` last).
    fn committed(&self, episode: &EpisodeSummary, files: &[String]);
}

/// A recorder over one dataset. Dropping it (or [`Recorder::close`]) stops the tick thread; an episode
/// still being recorded is discarded.
pub struct Recorder {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    sampler: Option<JoinHandle<()>>,
}

fn unix_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i64)
}

impl Recorder {
    /// Creates or resumes the dataset at `spec.root` with default sync settings.
    #[allow(clippy::needless_pass_by_value)]
    pub fn open(
        spec: DatasetSpec,
        robot: Arc<dyn RobotSource>,
        cameras: Vec<(String, Arc<FrameSlot>)>,
    ) -> Result<Recorder, RecorderError> {
        let sync = SyncConfig::for_fps(spec.fps);
        Self::open_with(spec, robot, cameras, sync)
    }

    /// Like [`Recorder::open`] with explicit sync settings.
    #[allow(clippy::needless_pass_by_value)] // the server hands over its camera list; keeps the call simple
    pub fn open_with(
        spec: DatasetSpec,
        robot: Arc<dyn RobotSource>,
        cameras: Vec<(String, Arc<FrameSlot>)>,
        sync: SyncConfig,
    ) -> Result<Recorder, RecorderError> {
        let mut slots = Vec::new();
        for c in &spec.cameras {
            let slot = cameras
                .iter()
                .find(|(n, _)| *n == c.name)
                .map(|(_, s)| Arc::clone(s))
                .ok_or_else(|| {
                    RecorderError::InvalidSpec(format!(
                        "camera {} is in the dataset spec but has no source",
                        c.name
                    ))
                })?;
            slots.push(slot);
        }
        let fps = spec.fps;
        let camera_names = spec.cameras.iter().map(|c| c.name.clone()).collect();
        let mut dataset = Dataset::open(spec)?;
        dataset.set_sync_provenance(serde_json::to_value(&sync).unwrap_or_default());
        let saved = dataset.total_episodes();
        let shared = Arc::new(Shared {
            dataset: Mutex::new(dataset),
            tick: Mutex::new(TickState {
                active: None,
                phase: Phase::Idle,
                warning: None,
                version: 0,
                saved,
            }),
            changed: Condvar::new(),
            stop: AtomicBool::new(false),
            robot,
            robot_history: Mutex::new(TimedRing::new(sync.robot_history)),
            sampling: Mutex::new(false),
            sampler_wake: Condvar::new(),
            clock: TickClock::new(monotonic_ns(), fps),
            cameras: slots,
            camera_names,
            fps,
            sync,
            commit_hook: Mutex::new(None),
            frame_limit: std::sync::atomic::AtomicU64::new(0),
        });
        let s2 = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("recorder-tick".into())
            .spawn(move || tick_loop(&s2))
            .map_err(|e| RecorderError::io("recorder tick thread", e))?;
        let mut recorder = Recorder {
            shared: Arc::clone(&shared),
            thread: Some(thread),
            sampler: None,
        };
        let s3 = Arc::clone(&shared);
        let sampler = std::thread::Builder::new()
            .name("recorder-sampler".into())
            .spawn(move || sample_loop(&s3))
            .map_err(|e| RecorderError::io("recorder sampler thread", e))?;
        recorder.sampler = Some(sampler);
        Ok(recorder)
    }

    /// Sets the hook told about every committed episode (see [`CommitHook`]).
    pub fn set_commit_hook(&self, hook: Arc<dyn CommitHook>) {
        *self.shared.commit_hook.lock() = Some(hook);
    }

    /// Sets the most frames an episode holds (`None`: no limit; see `[recorder] episode_time_s`).
    pub fn set_frame_limit(&self, frames: Option<u64>) {
        self.shared
            .frame_limit
            .store(frames.unwrap_or(0), Ordering::Relaxed);
    }

    /// Starts recording an episode of `task`.
    pub fn start_episode(&self, task: &str) -> Result<RecorderStatus, RecorderError> {
        self.start_episode_by(task, "")
    }

    /// Starts recording an episode of `task` by `operator` (recorded in the episode's provenance).
    pub fn start_episode_by(&self, task: &str, operator: &str) -> Result<RecorderStatus, RecorderError> {
        // Parked cameras start drawing now, all at once; each first frame is then waited for here (not under
        // the tick lock), so that frame 0 has a frame captured before it.
        for slot in &self.shared.cameras {
            slot.touch();
        }
        for slot in &self.shared.cameras {
            let _ = slot.latest();
        }
        {
            // Samples left from before (the sampler was idle) say nothing of the robot now: an episode starts
            // from what the robot reports at its start.
            // The tick lock is never taken under the history's (the tick thread takes them the other way).
            let idle = self.shared.tick.lock().active.is_none();
            let mut history = self.shared.robot_history.lock();
            if idle {
                *history = TimedRing::new(self.shared.sync.robot_history);
            }
            if let Some(sample) = self.shared.robot.sample() {
                history.push(sample.capture_time_ns, sample);
            }
        }
        self.set_sampling(true);
        let mut ds = self.shared.dataset.lock();
        {
            let t = self.shared.tick.lock();
            if let Some(a) = &t.active {
                return Err(RecorderError::AlreadyRecording(a.writer.index));
            }
        }
        let writer = match ds.begin_episode(task, self.shared.sync.queue_frames) {
            Ok(w) => w,
            Err(e) => {
                drop(ds);
                self.set_sampling(self.shared.tick.lock().active.is_some());
                return Err(e);
            }
        };
        let saved = ds.total_episodes();
        drop(ds);
        let mut t = self.shared.tick.lock();
        t.saved = saved;
        if let Some(a) = &t.active {
            return Err(RecorderError::AlreadyRecording(a.writer.index));
        }
        tracing::info!(episode = writer.index, task = %writer.task, "recording started");
        // The first tick not yet written: the tick thread writes tick i only once `settle_s` has passed it.
        let first_tick = self.shared.clock.first_at_or_after(monotonic_ns());
        t.active = Some(Active {
            last_seq: vec![None; self.shared.cameras.len()],
            writer,
            first_tick,
            held: 0,
            paused: 0,
            paused_run: 0,
            pause_why: String::new(),
            late: 0,
            start_unix_ns: unix_ns(),
            last_robot_ns: None,
            error: None,
            operator: operator.trim().to_owned(),
        });
        t.phase = Phase::Recording;
        t.warning = None;
        bump(&self.shared, &mut t);
        drop(t);
        Ok(self.status())
    }

    fn take_active(&self) -> Result<Active, RecorderError> {
        let mut t = self.shared.tick.lock();
        let a = t.active.take().ok_or(RecorderError::NotRecording)?;
        t.phase = Phase::Saving;
        bump(&self.shared, &mut t);
        drop(t);
        self.set_sampling(false);
        Ok(a)
    }

    fn set_sampling(&self, on: bool) {
        *self.shared.sampling.lock() = on;
        self.shared.sampler_wake.notify_all();
    }

    fn set_idle(&self, warning: Option<String>) {
        // The episode's encoders are gone: give their memory back (see `memory`).
        crate::memory::release_freed_memory();
        let saved = self.shared.dataset.lock().total_episodes();
        let mut t = self.shared.tick.lock();
        t.saved = saved;
        t.phase = Phase::Idle;
        t.warning = warning;
        bump(&self.shared, &mut t);
    }

    /// Stops recording and saves the episode. Returns when it is committed to disk.
    pub fn stop_episode(&self) -> Result<EpisodeSummary, RecorderError> {
        self.stop_episode_with(None)
    }

    /// Stops recording and saves the episode with the operator's outcome (`Some(true)`: a success), kept in
    /// its provenance and, in a dataset with `next.success`, as the last frame's value: the task is done (or
    /// not) after that frame, as LeRobot's evaluation and HIL recordings mark it. The frames before keep what
    /// was sampled (a scene's success flag, false without one). Returns when it is committed to disk.
    pub fn stop_episode_with(&self, success: Option<bool>) -> Result<EpisodeSummary, RecorderError> {
        let t0 = std::time::Instant::now();
        let mut ds = self.shared.dataset.lock();
        let mut active = self.take_active()?;
        if let Some(v) = success {
            active.writer.set_last_success(v);
        }
        let summary = EpisodeSummary {
            index: active.writer.index,
            task: active.writer.task.clone(),
            held_ticks: active.held,
            paused_ticks: active.paused,
            late_ticks: active.late,
            start_unix_ns: active.start_unix_ns,
            operator: active.operator.clone(),
            first_frame_time_ns: self.shared.clock.time_ns(active.first_tick),
            success,
            ..EpisodeSummary::default()
        };
        if let Some(e) = active.error {
            let index = active.writer.index;
            ds.abort_episode(active.writer);
            drop(ds);
            let msg = format!("episode {index} was not saved: {e}");
            tracing::error!("{msg}");
            self.set_idle(Some(msg));
            return Err(e);
        }
        if active.writer.frames() == 0 {
            let index = active.writer.index;
            ds.abort_episode(active.writer);
            drop(ds);
            self.set_idle(Some(format!("episode {index} had no frames and was discarded")));
            return Err(RecorderError::EmptyEpisode(index));
        }
        let r = ds.commit_episode(active.writer, summary);
        if let (Ok(s), Some(hook)) = (&r, self.shared.commit_hook.lock().as_ref()) {
            hook.committed(s, ds.last_commit_files());
        }
        drop(ds);
        match r {
            Ok(mut s) => {
                s.save_latency_s = t0.elapsed().as_secs_f64();
                tracing::info!(
                    episode = s.index,
                    frames = s.length_frames,
                    save_ms = s.save_latency_s * 1e3,
                    "episode saved"
                );
                let warning = (s.dropped_frames > 0 || s.paused_ticks > 0 || s.late_ticks > 0).then(|| {
                    format!(
                        "episode {} saved with {} dropped video frames, {} paused and {} late ticks",
                        s.index, s.dropped_frames, s.paused_ticks, s.late_ticks
                    )
                });
                self.set_idle(warning);
                Ok(s)
            }
            Err(e) => {
                tracing::error!(error = %e, "episode not saved");
                self.set_idle(Some(format!("episode not saved: {e}")));
                Err(e)
            }
        }
    }

    /// Throws away the episode being recorded; returns its frame count.
    pub fn discard_episode(&self) -> Result<u64, RecorderError> {
        let mut ds = self.shared.dataset.lock();
        let active = self.take_active()?;
        let frames = active.writer.frames();
        ds.abort_episode(active.writer);
        drop(ds);
        self.set_idle(None);
        Ok(frames)
    }

    /// Re-records: discards the take in progress and starts it again, with `task` or the same task.
    /// Refused when nothing is being recorded (saved episodes are never deleted here), and refused before
    /// anything is discarded when `task` is not a valid task.
    pub fn rerecord(&self, task: Option<&str>) -> Result<RecorderStatus, RecorderError> {
        let task = task
            .map(crate::dataset::check_task)
            .transpose()?
            .map(str::to_owned);
        let current = self
            .shared
            .tick
            .lock()
            .active
            .as_ref()
            .map(|a| a.writer.task.clone())
            .ok_or(RecorderError::NothingToRerecord)?;
        self.discard_episode()?;
        self.start_episode(&task.unwrap_or(current))
    }

    /// Saved episodes.
    pub fn episodes(&self) -> Vec<EpisodeSummary> {
        self.shared.dataset.lock().episodes()
    }

    /// The current status.
    pub fn status(&self) -> RecorderStatus {
        let t = self.shared.tick.lock();
        status_of(&self.shared, &t)
    }

    /// Waits until the status version is above `since` (or `timeout` passes) and returns the status.
    pub fn watch(&self, since: u64, timeout: Duration) -> RecorderStatus {
        let mut t = self.shared.tick.lock();
        self.shared
            .changed
            .wait_while_for(&mut t, |t| t.version <= since, timeout);
        let v = t.version;
        drop(t);
        let mut s = self.status();
        s.version = s.version.max(v);
        s
    }

    /// Stops the tick thread. An episode still being recorded is discarded (call stop_episode to keep it).
    pub fn close(mut self) -> Result<(), RecorderError> {
        self.shutdown();
        Ok(())
    }

    fn shutdown(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        self.shared.sampler_wake.notify_all();
        if let Some(h) = self.thread.take() {
            let _ = h.join();
        }
        if let Some(h) = self.sampler.take() {
            let _ = h.join();
        }
        let active = self.shared.tick.lock().active.take();
        if let Some(a) = active {
            self.shared.dataset.lock().abort_episode(a.writer);
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn bump(shared: &Shared, t: &mut TickState) {
    t.version += 1;
    shared.changed.notify_all();
}

fn status_of(shared: &Shared, t: &TickState) -> RecorderStatus {
    let fps = shared.fps;
    let (episode_index, task, operator, frames, held, paused, late, dropped) = match &t.active {
        Some(a) => (
            a.writer.index,
            a.writer.task.clone(),
            a.operator.clone(),
            a.writer.frames(),
            a.held,
            a.paused,
            a.late,
            a.writer.dropped(),
        ),
        None => (t.saved, String::new(), String::new(), 0, 0, 0, 0, 0),
    };
    RecorderStatus {
        phase: t.phase,
        episode_index,
        task,
        operator,
        frames_recorded: frames,
        duration_s: frames as f64 / f64::from(fps),
        held_ticks: held,
        paused_ticks: paused,
        late_ticks: late,
        dropped_frames: dropped,
        episodes_saved: t.saved,
        warning: t.warning.clone(),
        fps,
        version: t.version,
    }
}

/// Reads the robot every `sample_period_s` while an episode is recorded, keeping each new sample with its
/// capture time; idle otherwise. A reader of its own, so that a tick thread that wakes late still finds the
/// samples of the ticks it missed.
fn sample_loop(shared: &Shared) {
    let period = Duration::from_secs_f64(shared.sync.sample_period_s.max(1e-4));
    while !shared.stop.load(Ordering::Relaxed) {
        {
            let mut on = shared.sampling.lock();
            if !*on {
                // The timeout only bounds how late a stop is seen.
                shared.sampler_wake.wait_for(&mut on, Duration::from_millis(100));
                continue;
            }
        }
        if let Some(sample) = shared.robot.sample() {
            shared.robot_history.lock().push(sample.capture_time_ns, sample);
        }
        std::thread::sleep(period);
    }
}

fn tick_loop(shared: &Shared) {
    let settle_ns = (shared.sync.settle_s * 1e9) as i64;
    let mut next = shared.clock.ticks_through(monotonic_ns());
    while !shared.stop.load(Ordering::Relaxed) {
        let now = monotonic_ns();
        let due = shared.clock.ticks_through(now - settle_ns);
        if due <= next {
            let wait_ns = shared.clock.time_ns(next) + settle_ns - now;
            std::thread::sleep(Duration::from_nanos(wait_ns.max(0) as u64).min(Duration::from_millis(50)));
            continue;
        }
        // Woke up late (an overloaded machine): every tick missed is written now, each with the samples of
        // its own time.
        let mut t = shared.tick.lock();
        for i in next..due {
            tick(shared, &mut t, i);
        }
        drop(t);
        next = due;
    }
}

/// A source's sample for one tick: why the tick cannot be recorded, or how late it is.
fn timing_note(what: &str, timing: Timing, stale: &mut Option<String>, late: &mut Vec<String>) {
    match timing {
        Timing::OnTime => {}
        Timing::Late { off_ns } => late.push(format!("{what} {:.0} ms off", off_ns as f64 / 1e6)),
        Timing::Stale { age_ns: None } => {
            stale.get_or_insert_with(|| format!("{what}: nothing received yet"));
        }
        Timing::Stale { age_ns: Some(age_ns) } => {
            stale.get_or_insert_with(|| format!("{what} has sent nothing for {:.2} s", age_ns as f64 / 1e9));
        }
    }
}

fn picked<T: Clone>(pick: &Pick<'_, T>) -> Option<T> {
    match pick {
        Pick::AtOrBefore { sample, .. } | Pick::After { sample, .. } => Some((*sample).clone()),
        Pick::Empty => None,
    }
}

fn tick(shared: &Shared, t: &mut TickState, index: u64) {
    let Some(a) = &mut t.active else { return };
    if a.error.is_some() || index < a.first_tick {
        return;
    }
    let limit = shared.frame_limit.load(Ordering::Relaxed);
    if limit > 0 && a.writer.frames() >= limit {
        return;
    }
    let tick_ns = shared.clock.time_ns(index);
    let tol_ns = (shared.sync.sample_tolerance_s * 1e9) as i64;
    let hold_ns = (shared.sync.hold_tolerance_s * 1e9) as i64;
    let dims = (a.writer_state_dims(), a.writer_action_dims());
    let mut stale: Option<String> = None;
    let mut late = Vec::new();
    let (timing, sample) = {
        let history = shared.robot_history.lock();
        let pick = history.pick(tick_ns);
        (judge(&pick, tick_ns, tol_ns, hold_ns), picked(&pick))
    };
    timing_note("robot sample", timing, &mut stale, &mut late);
    match &sample {
        Some(s) if (s.state.len(), s.action.len()) != dims => {
            stale = Some(format!(
                "robot sample has {} state and {} action values, the dataset expects {} and {}",
                s.state.len(),
                s.action.len(),
                dims.0,
                dims.1
            ));
        }
        Some(s) if s.state.iter().chain(&s.action).any(|v| !v.is_finite()) => {
            stale = Some("robot sample contains NaN or infinity".into());
        }
        _ => {}
    }
    let mut frames: Vec<Option<Frame>> = Vec::with_capacity(shared.cameras.len());
    for (slot, name) in shared.cameras.iter().zip(&shared.camera_names) {
        let (timing, frame) = slot.with_history(|history| {
            let pick = history.pick(tick_ns);
            (judge(&pick, tick_ns, tol_ns, hold_ns), picked(&pick))
        });
        timing_note(&format!("camera {name}"), timing, &mut stale, &mut late);
        frames.push(frame);
    }
    if let Some(why) = stale {
        a.paused += 1;
        a.paused_run += 1;
        a.pause_why.clone_from(&why);
        let msg = format!("recording paused: {why}");
        if t.phase != Phase::Paused || t.warning.as_deref() != Some(&msg) {
            if t.phase != Phase::Paused {
                tracing::warn!("{msg}");
            }
            t.phase = Phase::Paused;
            t.warning = Some(msg);
            bump(shared, t);
        }
        return;
    }
    if t.phase == Phase::Paused {
        t.phase = Phase::Recording;
        t.warning = Some(format!("resumed after {} paused ticks", a.paused));
        tracing::info!("recording resumed");
        bump(shared, t);
    }
    let Some(a) = &mut t.active else { return };
    let Some(s) = sample else { return };
    let mut held = a.last_robot_ns == Some(s.capture_time_ns);
    a.last_robot_ns = Some(s.capture_time_ns);
    let index = a.writer.frames();
    for (i, f) in frames.into_iter().enumerate() {
        let Some(f) = f else { continue };
        held |= a.last_seq[i] == Some(f.seq);
        a.last_seq[i] = Some(f.seq);
        a.writer.encoders[i].push(index, f);
    }
    if held {
        a.held += 1;
    }
    let mut pushed = Ok(());
    if a.paused_run > 0 {
        let why = std::mem::take(&mut a.pause_why);
        pushed = a.writer.note_timeline(EventKind::Paused, a.paused_run, why);
        a.paused_run = 0;
    }
    if !late.is_empty() {
        a.late += 1;
        pushed = pushed.and_then(|()| a.writer.note_timeline(EventKind::LateTick, 1, late.join(", ")));
    }
    let pushed = pushed
        .and_then(|()| a.writer.note_activity(&s.arms))
        .and_then(|()| {
            let flags = FrameFlags {
                success: s.success,
                // LeRobot's DAgger `intervention`: a person drove (the clutch was in on) at least one arm.
                intervention: s.arms.iter().any(|arm| arm.arbiter.engaged),
            };
            a.writer.push_row(&s.state, &s.action, flags)
        });
    if let Err(e) = pushed {
        let msg = format!("recording failed, the episode cannot be saved: {e}");
        tracing::error!("{msg}");
        a.error = Some(e);
        t.warning = Some(msg);
        bump(shared, t);
        return;
    }
    if let Some(cam) = a.writer.failed_camera() {
        let msg = format!("video encoder for camera {cam} failed, the episode cannot be saved");
        if t.warning.as_deref() != Some(&msg) {
            tracing::error!("{msg}");
            t.warning = Some(msg);
            bump(shared, t);
        }
    }
}

impl Active {
    fn writer_state_dims(&self) -> usize {
        self.writer.state_dims()
    }
    fn writer_action_dims(&self) -> usize {
        self.writer.action_dims()
    }
}

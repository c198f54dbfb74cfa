//! The recorder: a tick thread on a fixed grid at the dataset fps on the monotonic clock, and a sampler
//! thread that keeps the robot's recent samples with their capture times. Frame i of an episode is the tick
//! at `first_tick + i / fps`: it holds the robot sample and each camera's frame captured at or before that
//! instant (see [`phone2act_capture::timeline`]), whenever the tick thread gets to write it, so a late wake-up writes the
//! ticks it missed each at its own time. `timestamp` follows `frame_index` (see
//! [`phone2act_dataset::dataset::timestamp_s`]).
//!
//! What could not be kept at its time is counted. A tick whose sample was captured farther from it than
//! `sample_tolerance_s` is still written (skipping it would shift every later frame off its time) and
//! counted as a late tick, with a `late_tick` event in the episode's sidecar. A source that has sent nothing
//! within `hold_tolerance_s` before a tick *pauses* the episode: those ticks are not recorded (counted in
//! `paused_ticks`, phase `Paused`, the warning names the source) and a `paused` event marks the frame where
//! the episode's time jumps. A tick that reuses the previous tick's sample of a source (a camera slower than
//! the dataset) is counted as held.

use crate::av::EncoderThread;
use crate::episode::Episode;
use parking_lot::{Condvar, Mutex};
use phone2act_capture::camera::{Frame, FrameSlot};
use phone2act_capture::timeline::{Pick, TickClock, TimedRing, Timing, judge};
use phone2act_clock::monotonic_ns;
use phone2act_dataset::dataset::{Dataset, EpisodeSummary, FrameFlags};
use phone2act_dataset::error::RecorderError;
use phone2act_dataset::events::{ArmActivity, EventKind};
use phone2act_dataset::spec::DatasetSpec;
use serde::Serialize;
use std::collections::VecDeque;
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
    /// Seconds the recorder keeps while idle for [`Recorder::save_highlight`] (`[recorder] highlight_s`); 0 when
    /// off.
    pub highlight_s: f64,
    /// Seconds it holds now (less than `highlight_s` right after it starts or after a source went stale).
    pub highlight_buffered_s: f64,
    /// Encoded video bytes it holds now, all cameras.
    pub highlight_video_bytes: u64,
    /// Increases on every change; see [`Recorder::watch`].
    pub version: u64,
}

/// What [`Recorder::save_highlight`] did.
#[derive(Clone, Debug, PartialEq)]
pub enum Highlight {
    /// The kept seconds were saved as an episode.
    Saved(EpisodeSummary),
    /// The kept seconds start the episode now recorded; Stop saves it.
    Recording(RecorderStatus),
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
    writer: Episode,
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

/// What the recorder keeps while idle when `[recorder] highlight_s` is set (LeRobot's `highlight` ring buffer):
/// the newest rows and, per camera, an encoder thread that keeps the newest frames encoded (see
/// [`EncoderThread::spawn_ring`]). [`Recorder::save_highlight`] makes them the start of an episode.
struct Ring {
    encoders: Vec<EncoderThread>,
    rows: VecDeque<RingRow>,
    /// The ring frame number of `rows[0]` (frames are numbered from 0 when the ring starts, as the encoders
    /// number them).
    first: u64,
    /// The ring frame number of the next row.
    next: u64,
    /// The first tick the ring records.
    first_tick: u64,
    last_robot_ns: Option<i64>,
    last_seq: Vec<Option<u64>>,
}

/// One tick the ring kept, with what an episode's writer needs to record it as its own.
struct RingRow {
    tick: u64,
    sample: RobotSample,
    held: bool,
    /// Why the tick is late, if it is (see [`phone2act_capture::timeline`]).
    late: Option<String>,
}

impl Active {
    fn new(
        writer: Episode,
        first_tick: u64,
        start_unix_ns: i64,
        last_seq: Vec<Option<u64>>,
        operator: &str,
    ) -> Self {
        Active {
            writer,
            first_tick,
            held: 0,
            paused: 0,
            paused_run: 0,
            pause_why: String::new(),
            late: 0,
            start_unix_ns,
            last_robot_ns: None,
            last_seq,
            error: None,
            operator: operator.trim().to_owned(),
        }
    }
}

struct TickState {
    active: Option<Active>,
    ring: Option<Ring>,
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
    /// Frames the ring keeps while idle (0: no ring; see [`Recorder::set_highlight`]).
    highlight_frames: std::sync::atomic::AtomicU64,
    /// The state and action lengths of the dataset.
    dims: (usize, usize),
    /// The GOP of the dataset's videos: a ring's saved episode starts at a multiple of it.
    gop: u64,
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
        let dims = (spec.state_names.len(), spec.action_names.len());
        let mut dataset = Dataset::open(spec)?;
        let gop = u64::from(dataset.video_settings().gop.max(1));
        dataset.set_sync_provenance(serde_json::to_value(&sync).unwrap_or_default());
        let saved = dataset.total_episodes();
        let shared = Arc::new(Shared {
            dataset: Mutex::new(dataset),
            tick: Mutex::new(TickState {
                active: None,
                ring: None,
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
            highlight_frames: std::sync::atomic::AtomicU64::new(0),
            dims,
            gop,
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
        // An episode records these seconds itself: the ring stops (and starts again when it ends).
        self.stop_ring();
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
        let writer = match Episode::begin(&mut ds, task, self.shared.sync.queue_frames) {
            Ok(w) => w,
            Err(e) => {
                drop(ds);
                self.set_sampling(self.shared.tick.lock().active.is_some());
                self.start_ring();
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
        t.active = Some(Active::new(
            writer,
            first_tick,
            unix_ns(),
            vec![None; self.shared.cameras.len()],
            operator,
        ));
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
        drop(t);
        self.start_ring();
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
        let ds = self.shared.dataset.lock();
        self.stop_locked(ds, success, t0)
    }

    /// [`Recorder::stop_episode_with`] under the dataset lock `ds`.
    fn stop_locked(
        &self,
        ds: parking_lot::MutexGuard<'_, Dataset>,
        success: Option<bool>,
        t0: std::time::Instant,
    ) -> Result<EpisodeSummary, RecorderError> {
        let active = self.take_active()?;
        self.save_active(ds, active, success, t0)
    }

    /// Saves `active`, taken from the tick state (phase `Saving`), under the dataset lock `ds`.
    fn save_active(
        &self,
        mut ds: parking_lot::MutexGuard<'_, Dataset>,
        mut active: Active,
        success: Option<bool>,
        t0: std::time::Instant,
    ) -> Result<EpisodeSummary, RecorderError> {
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
            active.writer.abort(&mut ds);
            drop(ds);
            let msg = format!("episode {index} was not saved: {e}");
            tracing::error!("{msg}");
            self.set_idle(Some(msg));
            return Err(e);
        }
        if active.writer.frames() == 0 {
            let index = active.writer.index;
            active.writer.abort(&mut ds);
            drop(ds);
            self.set_idle(Some(format!("episode {index} had no frames and was discarded")));
            return Err(RecorderError::EmptyEpisode(index));
        }
        let r = active.writer.commit(&mut ds, summary);
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
        active.writer.abort(&mut ds);
        drop(ds);
        self.set_idle(None);
        Ok(frames)
    }

    /// Re-records: discards the take in progress and starts it again, with `task` or the same task.
    /// Refused when nothing is being recorded (saved episodes are never deleted here), and refused before
    /// anything is discarded when `task` is not a valid task.
    pub fn rerecord(&self, task: Option<&str>) -> Result<RecorderStatus, RecorderError> {
        let task = task
            .map(phone2act_dataset::dataset::check_task)
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

    /// Keeps the last `seconds` while idle (LeRobot's `highlight`, `[recorder] highlight_s`), for
    /// [`Recorder::save_highlight`]; `None` or 0 turns it off. The ring runs whenever no episode is recorded:
    /// one encoder thread per camera (the memory and CPU of an episode in progress) and the newest rows.
    pub fn set_highlight(&self, seconds: Option<f64>) {
        let frames = seconds
            .filter(|s| s.is_finite() && *s > 0.0)
            .map_or(0, |s| (s * f64::from(self.shared.fps)).round().max(1.0) as u64);
        self.shared.highlight_frames.store(frames, Ordering::Relaxed);
        self.stop_ring();
        self.start_ring();
    }

    /// Starts the ring if it is on, nothing is recorded and it is not running.
    fn start_ring(&self) {
        let keep = self.shared.highlight_frames.load(Ordering::Relaxed);
        if keep == 0 || self.shared.stop.load(Ordering::Relaxed) {
            return;
        }
        {
            let t = self.shared.tick.lock();
            if t.active.is_some() || t.ring.is_some() {
                return;
            }
        }
        let encoders = {
            let ds = self.shared.dataset.lock();
            let spec = ds.spec();
            spec.cameras
                .iter()
                .map(|c| {
                    EncoderThread::spawn_ring(
                        &c.name,
                        c.width,
                        c.height,
                        spec.fps,
                        ds.video_settings().clone(),
                        self.shared.sync.queue_frames,
                        keep + self.shared.gop,
                    )
                })
                .collect::<Result<Vec<_>, _>>()
        };
        let encoders = match encoders {
            Ok(e) => e,
            Err(e) => {
                tracing::error!(error = %e, "cannot keep the last seconds");
                let mut t = self.shared.tick.lock();
                t.warning = Some(format!("cannot keep the last seconds: {e}"));
                bump(&self.shared, &mut t);
                return;
            }
        };
        for slot in &self.shared.cameras {
            slot.touch();
        }
        self.set_sampling(true);
        let mut t = self.shared.tick.lock();
        if t.active.is_some() || t.ring.is_some() {
            drop(t);
            drop(encoders);
            return;
        }
        t.ring = Some(Ring {
            last_seq: vec![None; encoders.len()],
            encoders,
            rows: VecDeque::new(),
            first: 0,
            next: 0,
            first_tick: self.shared.clock.first_at_or_after(monotonic_ns()),
            last_robot_ns: None,
        });
        bump(&self.shared, &mut t);
    }

    /// Stops the ring, throwing away what it keeps.
    fn stop_ring(&self) {
        let ring = self.shared.tick.lock().ring.take();
        // Outside the lock: the encoder threads are joined.
        drop(ring);
    }

    /// Saves the last seconds the recorder kept while idle (`[recorder] highlight_s`, LeRobot's `highlight`) as
    /// episode `total_episodes` of `task` by `operator`: frame 0 is the oldest kept tick at a multiple of the
    /// video GOP (so the episode holds between `highlight_s` and `highlight_s` plus a GOP of frames, or all the
    /// ring holds when it holds less), and it is an episode like any other: timestamps from 0, the executed
    /// actions, the events of its frames. With `keep_recording` it stays the episode in progress (LeRobot's
    /// behaviour: it records on until Stop, which saves it); otherwise it is saved now with the operator's
    /// `success`, and the ring starts again.
    ///
    /// Refused while an episode is recorded (it holds these seconds itself), when the ring is off, and when it
    /// holds nothing yet (a source has not sent since it started, or was stale). A save that fails (a full disk)
    /// loses the kept seconds and keeps every episode saved before.
    pub fn save_highlight(
        &self,
        task: &str,
        operator: &str,
        keep_recording: bool,
        success: Option<bool>,
    ) -> Result<Highlight, RecorderError> {
        let t0 = std::time::Instant::now();
        let task = phone2act_dataset::dataset::check_task(task)?.to_owned();
        let keep = self.shared.highlight_frames.load(Ordering::Relaxed);
        if keep == 0 {
            return Err(RecorderError::HighlightOff);
        }
        let mut ds = self.shared.dataset.lock();
        let mut t = self.shared.tick.lock();
        if let Some(a) = &t.active {
            return Err(RecorderError::HighlightWhileRecording(a.writer.index));
        }
        let Some(mut ring) = t.ring.take() else {
            return Err(RecorderError::NothingBuffered);
        };
        let gop = self.shared.gop;
        let mut cut = (ring.next.saturating_sub(keep) / gop * gop).max(ring.first.div_ceil(gop) * gop);
        let limit = self.shared.frame_limit.load(Ordering::Relaxed);
        if limit > 0 && ring.next - cut.min(ring.next) > limit {
            // Never more than an episode may hold (`episode_time_s`).
            cut = (ring.next - limit).div_ceil(gop) * gop;
        }
        if cut >= ring.next {
            t.ring = Some(ring);
            return Err(RecorderError::NothingBuffered);
        }
        let writer = match Episode::begin_from_ring(&mut ds, &task, &mut ring.encoders, cut) {
            Ok(w) => w,
            Err(e) => {
                t.ring = Some(ring);
                return Err(e);
            }
        };
        let from = (cut - ring.first) as usize;
        let first_tick = ring.rows[from].tick;
        let since_first_ns = monotonic_ns() - self.shared.clock.time_ns(first_tick);
        let mut active = Active::new(
            writer,
            first_tick,
            unix_ns() - since_first_ns.max(0),
            ring.last_seq.clone(),
            operator,
        );
        active.last_robot_ns = ring.last_robot_ns;
        for row in ring.rows.drain(from..) {
            active.held += u64::from(row.held);
            let mut pushed = Ok(());
            if let Some(why) = row.late {
                active.late += 1;
                pushed = active.writer.note_timeline(EventKind::LateTick, 1, why);
            }
            let s = row.sample;
            let pushed = pushed
                .and_then(|()| active.writer.note_activity(&s.arms))
                .and_then(|()| active.writer.push_row(&s.state, &s.action, flags_of(&s)));
            if let Err(e) = pushed {
                active.error = Some(e);
                break;
            }
        }
        tracing::info!(
            episode = active.writer.index,
            frames = active.writer.frames(),
            "recording started from the last seconds kept"
        );
        t.warning = None;
        if !keep_recording {
            // Saved as kept: no tick after the request joins it.
            t.phase = Phase::Saving;
            bump(&self.shared, &mut t);
            drop(t);
            self.set_sampling(false);
            return self.save_active(ds, active, success, t0).map(Highlight::Saved);
        }
        t.active = Some(active);
        t.phase = Phase::Recording;
        bump(&self.shared, &mut t);
        drop(t);
        drop(ds);
        Ok(Highlight::Recording(self.status()))
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
        let ring = self.shared.tick.lock().ring.take();
        drop(ring);
        let active = self.shared.tick.lock().active.take();
        if let Some(a) = active {
            a.writer.abort(&mut self.shared.dataset.lock());
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
        highlight_s: shared.highlight_frames.load(Ordering::Relaxed) as f64 / f64::from(fps),
        highlight_buffered_s: t.ring.as_ref().map_or(0.0, |r| {
            let keep = shared.highlight_frames.load(Ordering::Relaxed);
            (r.rows.len() as u64).min(keep) as f64 / f64::from(fps)
        }),
        highlight_video_bytes: t
            .ring
            .as_ref()
            .map_or(0, |r| r.encoders.iter().map(EncoderThread::kept_bytes).sum()),
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

/// The robot sample and camera frames of one tick, and how they were judged.
struct Gathered {
    /// Why the tick cannot be recorded.
    stale: Option<String>,
    /// The sources captured farther from the tick than the sample tolerance.
    late: Vec<String>,
    sample: Option<RobotSample>,
    frames: Vec<Option<Frame>>,
}

fn gather(shared: &Shared, tick_ns: i64) -> Gathered {
    let tol_ns = (shared.sync.sample_tolerance_s * 1e9) as i64;
    let hold_ns = (shared.sync.hold_tolerance_s * 1e9) as i64;
    let dims = shared.dims;
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
    Gathered {
        stale,
        late,
        sample,
        frames,
    }
}

/// A frame's flags as recorded.
fn flags_of(s: &RobotSample) -> FrameFlags {
    FrameFlags {
        success: s.success,
        // LeRobot's DAgger `intervention`: a person drove (the clutch was in on) at least one arm.
        intervention: s.arms.iter().any(|arm| arm.arbiter.engaged),
    }
}

/// A tick while idle with the ring on: kept as the ring's next row, its frames queued to the ring's encoders.
/// A stale source empties the ring (a saved episode never spans a gap: its time would jump).
fn ring_tick(shared: &Shared, t: &mut TickState, index: u64) {
    let keep = shared.highlight_frames.load(Ordering::Relaxed);
    let Some(r) = &mut t.ring else { return };
    if index < r.first_tick {
        return;
    }
    let g = gather(shared, shared.clock.time_ns(index));
    if g.stale.is_some() {
        r.rows.clear();
        r.first = r.next;
        return;
    }
    let Some(sample) = g.sample else { return };
    let mut held = r.last_robot_ns == Some(sample.capture_time_ns);
    r.last_robot_ns = Some(sample.capture_time_ns);
    for (i, f) in g.frames.into_iter().enumerate() {
        let Some(f) = f else { continue };
        held |= r.last_seq[i] == Some(f.seq);
        r.last_seq[i] = Some(f.seq);
        r.encoders[i].push(r.next, f);
    }
    r.rows.push_back(RingRow {
        tick: index,
        sample,
        held,
        late: (!g.late.is_empty()).then(|| g.late.join(", ")),
    });
    r.next += 1;
    // A GOP more than asked: the saved episode starts at a key frame at or before the oldest asked-for tick.
    while r.rows.len() as u64 > keep + shared.gop {
        r.rows.pop_front();
        r.first += 1;
    }
}

fn tick(shared: &Shared, t: &mut TickState, index: u64) {
    if t.active.is_none() {
        ring_tick(shared, t, index);
        return;
    }
    let Some(a) = &mut t.active else { return };
    if a.error.is_some() || index < a.first_tick {
        return;
    }
    let limit = shared.frame_limit.load(Ordering::Relaxed);
    if limit > 0 && a.writer.frames() >= limit {
        return;
    }
    let Gathered {
        stale,
        late,
        sample,
        frames,
    } = gather(shared, shared.clock.time_ns(index));
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
        .and_then(|()| a.writer.push_row(&s.state, &s.action, flags_of(&s)));
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

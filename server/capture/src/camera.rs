//! Camera sources. Each source runs on its own thread and publishes into a [`FrameSlot`], which hands readers
//! the newest frame (latest wins) and keeps the last [`HISTORY_FRAMES`] with their capture times on the
//! process monotonic clock, so that the recorder can take the frame of an instant that has just passed (see
//! [`crate::timeline`]). Generated sources draw only while someone reads their slot, and at a lower CPU priority
//! while nobody records them (see [`spawn_generated`]).

use crate::timeline::TimedRing;
use parking_lot::{Condvar, Mutex};
use phone2act_clock::{ClockFn, monotonic_ns};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub use phone2act_dataset::frame::Frame;

/// A latest-frame slot shared between a capture thread and its readers.
///
/// A generated source (a rendered or test-pattern camera) renders only while someone reads the slot: after
/// [`IDLE_AFTER_NS`] without a read it parks, and the next [`FrameSlot::latest`] wakes it and waits for its
/// first fresh frame (one render, a few milliseconds), so nobody is handed a picture from before the park. An
/// idle server then draws nothing. Real devices keep streaming: a V4L2 stream restarts slowly and its
/// auto-exposure needs frames.
#[derive(Debug)]
pub struct FrameSlot {
    state: Mutex<SlotState>,
    /// Signals both ways under `state`: a new frame to readers waiting for a parked source, a read to the
    /// parked source.
    changed: Condvar,
    frames_captured: AtomicU64,
    clock: ClockFn,
}

#[derive(Debug)]
struct SlotState {
    latest: Option<Frame>,
    /// The last [`HISTORY_FRAMES`] frames by capture time (their pixels are shared with `latest` and the
    /// encoders through the `Arc`).
    history: TimedRing<Frame>,
    /// When a reader last asked for a frame (process clock); starts at the slot's creation so that a new
    /// source runs for [`IDLE_AFTER_NS`] before it first parks.
    last_read_ns: i64,
    /// When the recorder last read the history or touched the slot (process clock); `None` until it does.
    last_recorded_ns: Option<i64>,
    parked: bool,
}

/// Frames a slot keeps for the recorder: 8 periods of the camera (267 ms at 30 fps, longer than the hold
/// tolerance), so a recorder tick written late still finds the frame of its time. Memory: 8 frames of
/// `width * height * 3` bytes per camera (7.4 MB at 640x480), given back to one frame when the source parks.
pub const HISTORY_FRAMES: usize = 8;

/// How long a generated source keeps rendering after its last reader: longer than any reader's period (the
/// recorder reads every tick, a policy or the phone preview at its own rate), short enough that an idle
/// server goes quiet soon after its last client leaves.
pub const IDLE_AFTER_NS: i64 = 2_000_000_000;

/// The longest a reader waits for a parked source's first frame before it takes what is in the slot.
const WAKE_TIMEOUT: Duration = Duration::from_millis(250);

impl Default for FrameSlot {
    fn default() -> Self {
        FrameSlot::with_clock(monotonic_ns)
    }
}

impl FrameSlot {
    /// A slot whose idle time is measured on `clock` (tests pass their own).
    pub fn with_clock(clock: ClockFn) -> Self {
        FrameSlot {
            state: Mutex::new(SlotState {
                latest: None,
                history: TimedRing::new(HISTORY_FRAMES),
                last_read_ns: clock(),
                last_recorded_ns: None,
                parked: false,
            }),
            changed: Condvar::new(),
            frames_captured: AtomicU64::new(0),
            clock,
        }
    }

    /// Replaces the newest frame.
    pub fn publish(&self, frame: Frame) {
        let mut state = self.state.lock();
        state.history.push(frame.capture_time_ns, frame.clone());
        state.latest = Some(frame);
        self.frames_captured.fetch_add(1, Ordering::Relaxed);
        drop(state);
        self.changed.notify_all();
    }

    /// The newest frame, if any; a read that keeps an on-demand source rendering. If the source has parked,
    /// this wakes it and waits (at most 250 ms) for its next frame.
    pub fn latest(&self) -> Option<Frame> {
        let mut state = self.state.lock();
        state.last_read_ns = (self.clock)();
        if state.parked {
            let before = self.frames_captured.load(Ordering::Relaxed);
            self.changed.notify_all();
            // `publish` counts under the lock, so the count cannot move between the check and the wait.
            self.changed.wait_while_for(
                &mut state,
                |_| self.frames_captured.load(Ordering::Relaxed) == before,
                WAKE_TIMEOUT,
            );
        }
        state.latest.clone()
    }

    /// Runs `f` on the recent frames by capture time (see [`HISTORY_FRAMES`]); counts as a read, without
    /// waiting for a parked source (the recorder has woken it at the episode's start).
    pub fn with_history<R>(&self, f: impl FnOnce(&TimedRing<Frame>) -> R) -> R {
        let mut state = self.state.lock();
        state.last_read_ns = (self.clock)();
        state.last_recorded_ns = Some(state.last_read_ns);
        if state.parked {
            self.changed.notify_all();
        }
        f(&state.history)
    }

    /// Counts as a read without waiting: a parked source starts drawing, and a reader about to come (the
    /// recorder at an episode's start) finds its frame ready instead of waiting for it.
    pub fn touch(&self) {
        let mut state = self.state.lock();
        state.last_read_ns = (self.clock)();
        state.last_recorded_ns = Some(state.last_read_ns);
        if state.parked {
            self.changed.notify_all();
        }
    }

    /// The newest frame without counting as a read (health checks must not keep a camera rendering).
    pub fn peek(&self) -> Option<Frame> {
        self.state.lock().latest.clone()
    }

    /// Whether an on-demand source is parked for want of readers (it is healthy, and renders on the next
    /// read).
    pub fn parked(&self) -> bool {
        self.state.lock().parked
    }

    /// Whether the recorder has read the history or touched the slot within the last [`IDLE_AFTER_NS`]: a
    /// generated source then renders at full priority, so that no recorded frame waits for the CPU behind the
    /// control path.
    pub fn recorded(&self) -> bool {
        let state = self.state.lock();
        state
            .last_recorded_ns
            .is_some_and(|t| (self.clock)() - t <= IDLE_AFTER_NS)
    }

    /// Frames published since start.
    pub fn frames_captured(&self) -> u64 {
        self.frames_captured.load(Ordering::Relaxed)
    }

    /// Called by an on-demand source after each frame: if nobody has read for [`IDLE_AFTER_NS`], parks until a
    /// reader comes or `stop` is set, and says whether it parked (so the source can restart its pacing).
    fn park_while_unread(&self, stop: &AtomicBool) -> bool {
        let mut state = self.state.lock();
        if (self.clock)() - state.last_read_ns <= IDLE_AFTER_NS {
            return false;
        }
        let parked_at_ns = state.last_read_ns;
        state.parked = true;
        // Nobody reads: the history's memory goes back, and a reader after the wake waits for a fresh frame.
        state.history.keep_newest();
        // Woken by a reader; the timeout only bounds how late a stop request is seen.
        while state.last_read_ns == parked_at_ns && !stop.load(Ordering::Relaxed) {
            self.changed.wait_for(&mut state, Duration::from_millis(100));
        }
        state.parked = false;
        true
    }
}

/// A running capture thread; stops and joins when dropped.
#[derive(Debug)]
pub struct CaptureThread {
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl CaptureThread {
    /// Asks the thread to stop and waits for it.
    pub fn stop(mut self) {
        self.stop_inner();
    }

    fn stop_inner(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(handle) = self.handle.take() {
            let _ = handle.join();
        }
    }
}

impl Drop for CaptureThread {
    fn drop(&mut self) {
        self.stop_inner();
    }
}

/// Draws the synthetic test pattern for frame `seq`: colour bars with a moving bar and the frame number
/// encoded as a row of black/white blocks, so a decoder test can tell frames apart.
pub fn draw_test_pattern(width: u32, height: u32, seq: u64, out: &mut Vec<u8>) {
    const BARS: [[u8; 3]; 8] = [
        [235, 235, 235],
        [235, 235, 16],
        [16, 235, 235],
        [16, 235, 16],
        [235, 16, 235],
        [235, 16, 16],
        [16, 16, 235],
        [16, 16, 16],
    ];
    let (w, h) = (width as usize, height as usize);
    out.clear();
    out.resize(w * h * 3, 0);
    let moving_x = (seq as usize * 4) % w.max(1);
    let block = (w / 32).max(1);
    for y in 0..h {
        for x in 0..w {
            let mut px = BARS[(x * 8 / w.max(1)).min(7)];
            if x.abs_diff(moving_x) < 4 {
                px = [255, 255, 255];
            }
            if y < block.min(h) {
                let bit = x / block;
                let on = bit < 32 && (seq >> bit) & 1 == 1;
                px = if on { [255, 255, 255] } else { [0, 0, 0] };
            }
            let i = (y * w + x) * 3;
            out[i..i + 3].copy_from_slice(&px);
        }
    }
}

/// Starts the synthetic test-pattern camera at `fps`, publishing into `slot`.
pub fn spawn_test_pattern(
    name: &str,
    width: u32,
    height: u32,
    fps: f64,
    slot: Arc<FrameSlot>,
) -> std::io::Result<CaptureThread> {
    spawn_generated(
        name,
        width,
        height,
        fps,
        move |seq, buf| draw_test_pattern(width, height, seq, buf),
        slot,
    )
}

/// A generated camera's drawing function, shared by its capture thread and its background renderer.
type SharedGenerator = Arc<Mutex<dyn FnMut(u64, &mut Vec<u8>) + Send>>;

/// A thread at [`crate::priority::BACKGROUND_NICE`] that draws a generated camera's frames while nobody records
/// it (a live view or a policy reads it): on a busy machine the control path's threads then get the CPU first
/// and the view is what slows down. Ends when dropped.
struct BackgroundRenderer {
    jobs: Option<std::sync::mpsc::SyncSender<(u64, Vec<u8>)>>,
    done: std::sync::mpsc::Receiver<Vec<u8>>,
    handle: Option<JoinHandle<()>>,
}

impl BackgroundRenderer {
    fn spawn(name: &str, generator: SharedGenerator) -> std::io::Result<Self> {
        let (jobs, job_rx) = std::sync::mpsc::sync_channel::<(u64, Vec<u8>)>(1);
        let (done_tx, done) = std::sync::mpsc::sync_channel(1);
        let handle = std::thread::Builder::new()
            .name(format!("camera-{name}-bg"))
            .spawn(move || {
                crate::priority::lower_current_thread(crate::priority::BACKGROUND_NICE);
                while let Ok((seq, mut buf)) = job_rx.recv() {
                    (generator.lock())(seq, &mut buf);
                    if done_tx.send(buf).is_err() {
                        return;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jobs),
            done,
            handle: Some(handle),
        })
    }

    /// Frame `seq` drawn on the background thread; `None` if that thread is gone (the generator panicked).
    fn render(&self, seq: u64, buf: Vec<u8>) -> Option<Vec<u8>> {
        self.jobs.as_ref()?.send((seq, buf)).ok()?;
        self.done.recv().ok()
    }
}

impl Drop for BackgroundRenderer {
    fn drop(&mut self) {
        // Closing the job channel ends the thread's loop.
        self.jobs = None;
        if let Some(handle) = self.handle.take() {
            let _ = handle.join();
        }
    }
}

/// Starts a camera whose frames are drawn by `generator(seq, &mut rgb)` at `fps` (the simulated arm's
/// rendered view, test patterns). The generator must fill `width * height * 3` bytes. It draws only while the
/// slot is read (see [`FrameSlot`]); while the recorder reads it ([`FrameSlot::recorded`]) it draws on the
/// capture thread at full priority, otherwise on a background thread at a lower priority (a live view must not
/// take the CPU from the control path; a recorded frame must not wait for it).
pub fn spawn_generated(
    name: &str,
    width: u32,
    height: u32,
    fps: f64,
    generator: impl FnMut(u64, &mut Vec<u8>) + Send + 'static,
    slot: Arc<FrameSlot>,
) -> std::io::Result<CaptureThread> {
    let stop = Arc::new(AtomicBool::new(false));
    let stop_flag = Arc::clone(&stop);
    let period = Duration::from_secs_f64(1.0 / fps.max(0.1));
    let expected = width as usize * height as usize * 3;
    let generator: SharedGenerator = Arc::new(Mutex::new(generator));
    let background = BackgroundRenderer::spawn(name, Arc::clone(&generator))?;
    let handle = std::thread::Builder::new()
        .name(format!("camera-{name}"))
        .spawn(move || {
            let mut start = Instant::now();
            // Frames are paced from `start` and `start_seq`; a park restarts both.
            let mut start_seq = 0u64;
            let mut seq = 0u64;
            while !stop_flag.load(Ordering::Relaxed) {
                // A fresh buffer per frame: readers may still hold the previous one through its Arc.
                let mut buf = Vec::with_capacity(expected);
                if slot.recorded() {
                    (generator.lock())(seq, &mut buf);
                } else if let Some(drawn) = background.render(seq, buf) {
                    buf = drawn;
                } else {
                    buf = Vec::with_capacity(expected);
                    (generator.lock())(seq, &mut buf);
                }
                // Captured when drawing finished, like a real sensor's exposure end.
                let capture_time_ns = monotonic_ns();
                if buf.len() == expected {
                    slot.publish(Frame {
                        width,
                        height,
                        rgb: Arc::new(buf),
                        capture_time_ns,
                        seq,
                    });
                }
                seq += 1;
                if slot.park_while_unread(&stop_flag) {
                    // Woken by a reader who is waiting: draw at once.
                    start = Instant::now();
                    start_seq = seq;
                    continue;
                }
                // Pace on absolute deadlines so the rate does not drift with drawing time.
                let next = start + period.mul_f64((seq - start_seq) as f64);
                let now = Instant::now();
                if let Some(wait) = next.checked_duration_since(now) {
                    sleep_unless_stopped(wait, &stop_flag);
                } else {
                    // Too slow for this rate: skip the missed deadlines instead of bursting.
                    let due = (now - start).as_secs_f64().div_euclid(period.as_secs_f64()) as u64;
                    seq = seq.max(start_seq + due);
                }
            }
        })?;
    Ok(CaptureThread {
        stop,
        handle: Some(handle),
    })
}

/// Sleeps in short slices so that a stop request is honoured within ~20 ms even at low rates.
fn sleep_unless_stopped(total: Duration, stop: &AtomicBool) {
    let deadline = Instant::now() + total;
    while !stop.load(Ordering::Relaxed) {
        let now = Instant::now();
        let Some(left) = deadline.checked_duration_since(now) else {
            return;
        };
        std::thread::sleep(left.min(Duration::from_millis(20)));
    }
}

impl CaptureThread {
    /// Wraps a thread that watches `stop` (for capture sources defined in other modules).
    pub(crate) fn from_parts(stop: Arc<AtomicBool>, handle: JoinHandle<()>) -> Self {
        CaptureThread {
            stop,
            handle: Some(handle),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn test_pattern_encodes_the_frame_number() {
        let mut a = Vec::new();
        let mut b = Vec::new();
        draw_test_pattern(64, 48, 1, &mut a);
        draw_test_pattern(64, 48, 2, &mut b);
        assert_eq!(a.len(), 64 * 48 * 3);
        assert_ne!(a, b, "consecutive frames must differ");
        // Block 0 of frame 1 is white, of frame 2 black.
        assert_eq!(&a[0..3], &[255, 255, 255]);
        assert_eq!(&b[0..3], &[0, 0, 0]);
    }

    /// A 4x2 camera at 200 fps whose every byte is its frame number (mod 256).
    fn counting_camera(slot: &Arc<FrameSlot>) -> CaptureThread {
        spawn_generated(
            "count",
            4,
            2,
            200.0,
            |seq, buf| buf.resize(24, seq as u8),
            Arc::clone(slot),
        )
        .unwrap()
    }

    #[test]
    fn generated_camera_publishes_what_the_generator_draws() {
        let slot = Arc::new(FrameSlot::default());
        let cam = counting_camera(&slot);
        wait_for("three frames", || slot.frames_captured() >= 3);
        cam.stop();
        let f = slot.latest().unwrap();
        assert_eq!(f.rgb.len(), 24);
        assert_eq!(u64::from(f.rgb[0]), f.seq % 256);
    }

    static FAKE_NOW_NS: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);
    fn fake_now_ns() -> i64 {
        FAKE_NOW_NS.load(Ordering::SeqCst)
    }

    fn wait_for(what: &str, mut done: impl FnMut() -> bool) {
        // Generous: the camera thread may be starved for a while on a loaded 2-core machine.
        let deadline = Instant::now() + Duration::from_secs(10);
        while !done() {
            assert!(Instant::now() < deadline, "timed out waiting for {what}");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    #[test]
    fn an_unread_generated_camera_parks_and_the_next_read_gets_a_fresh_frame() {
        let slot = Arc::new(FrameSlot::with_clock(fake_now_ns));
        let cam = counting_camera(&slot);
        wait_for("the first frames", || slot.frames_captured() >= 3);
        assert!(!slot.parked(), "read within the idle time: still rendering");

        // Nobody has read for longer than the idle time: the source parks after its next frame.
        FAKE_NOW_NS.store(IDLE_AFTER_NS + 1, Ordering::SeqCst);
        wait_for("the source to park", || slot.parked());
        let parked_count = slot.frames_captured();
        let before = slot.peek().expect("frames were drawn before the park");
        std::thread::sleep(Duration::from_millis(100));
        assert_eq!(
            slot.frames_captured(),
            parked_count,
            "a parked source draws nothing (200 fps for 0.1 s)"
        );
        assert!(slot.parked(), "peek is no read: the source stays parked");

        // A read wakes it and returns the frame drawn after the wake, not the one from before the park.
        let woken_at_ns = monotonic_ns();
        let fresh = slot.latest().unwrap();
        assert!(
            fresh.seq > before.seq,
            "seq {} after the park, {} before",
            fresh.seq,
            before.seq
        );
        assert!(
            fresh.capture_time_ns >= woken_at_ns,
            "the frame was drawn after the read asked for it"
        );
        assert_eq!(u64::from(fresh.rgb[0]), fresh.seq % 256);
        wait_for("the source to render again", || {
            slot.frames_captured() > parked_count + 2
        });
        assert!(!slot.parked());
        cam.stop();
    }

    #[test]
    fn a_read_at_the_idle_time_keeps_the_source_rendering() {
        static NOW_NS: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);
        let slot = Arc::new(FrameSlot::with_clock(|| NOW_NS.load(Ordering::SeqCst)));
        let cam =
            spawn_generated("kept", 4, 2, 200.0, |_, buf| buf.resize(24, 0), Arc::clone(&slot)).unwrap();
        // Reads exactly the idle time apart, for well over the idle time: at the boundary it still draws.
        for step in 1..=4 {
            NOW_NS.store(step * IDLE_AFTER_NS, Ordering::SeqCst);
            let n = slot.frames_captured();
            wait_for("two more frames", || slot.frames_captured() > n + 1);
            assert!(
                !slot.parked(),
                "step {step}: read {} s ago",
                IDLE_AFTER_NS / 1_000_000_000
            );
            let _ = slot.latest();
        }
        cam.stop();
    }

    #[test]
    fn a_touch_wakes_a_parked_source_without_waiting_for_it() {
        static NOW_NS: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);
        let slot = Arc::new(FrameSlot::with_clock(|| NOW_NS.load(Ordering::SeqCst)));
        let cam = counting_camera(&slot);
        NOW_NS.store(IDLE_AFTER_NS + 1, Ordering::SeqCst);
        wait_for("the source to park", || slot.parked());
        let parked_count = slot.frames_captured();
        slot.touch();
        wait_for("the source to draw again", || {
            slot.frames_captured() > parked_count
        });
        assert!(!slot.parked());
        cam.stop();
    }

    #[test]
    fn an_unrecorded_source_draws_at_a_lower_priority_and_a_recorded_one_at_full() {
        static NOW_NS: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);
        let slot = Arc::new(FrameSlot::with_clock(|| NOW_NS.load(Ordering::SeqCst)));
        // The drawing thread's name and nice value of the newest frame.
        let drawn_by = Arc::new(Mutex::new((String::new(), None)));
        let cam = {
            let drawn_by = Arc::clone(&drawn_by);
            spawn_generated(
                "prio",
                4,
                2,
                200.0,
                move |_, buf| {
                    let name = std::thread::current().name().unwrap_or_default().to_owned();
                    *drawn_by.lock() = (name, crate::priority::current_thread_nice());
                    buf.resize(24, 0);
                },
                Arc::clone(&slot),
            )
            .unwrap()
        };
        let full_nice = crate::priority::current_thread_nice();
        let frames_by = |what: &str, thread: &str| {
            let n = slot.frames_captured();
            wait_for(what, || {
                slot.frames_captured() > n + 1 && drawn_by.lock().0 == thread
            });
            drawn_by.lock().1
        };
        // Read (a live view), not recorded: the background thread draws.
        let _ = slot.latest();
        let nice = frames_by("frames drawn in the background", "camera-prio-bg");
        if let (Some(full), Some(low)) = (full_nice, nice) {
            assert_eq!(low, (full + crate::priority::BACKGROUND_NICE).min(19));
        }
        // The recorder reads the history: the capture thread draws, at the priority it was started with.
        slot.with_history(|_| ());
        assert!(slot.recorded());
        assert_eq!(
            frames_by("frames drawn at full priority", "camera-prio"),
            full_nice
        );
        // Past the idle time without a recorder read: back to the background.
        NOW_NS.store(IDLE_AFTER_NS + 1, Ordering::SeqCst);
        let _ = slot.latest();
        assert!(!slot.recorded());
        frames_by("frames drawn in the background again", "camera-prio-bg");
        cam.stop();
    }

    #[test]
    fn stop_ends_a_parked_source() {
        static NOW_NS: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);
        let slot = Arc::new(FrameSlot::with_clock(|| NOW_NS.load(Ordering::SeqCst)));
        let cam = counting_camera(&slot);
        NOW_NS.store(IDLE_AFTER_NS + 1, Ordering::SeqCst);
        wait_for("the source to park", || slot.parked());
        // Returns (joins the thread) instead of hanging on the parked source.
        cam.stop();
    }

    #[test]
    fn test_pattern_camera_publishes_at_its_rate() {
        let slot = Arc::new(FrameSlot::default());
        let started = Instant::now();
        let cam = spawn_test_pattern("t", 32, 24, 100.0, Arc::clone(&slot)).unwrap();
        std::thread::sleep(Duration::from_millis(200));
        cam.stop();
        let elapsed_s = started.elapsed().as_secs_f64();
        let n = slot.frames_captured();
        // Never faster than its rate (frame 0 is drawn at once, then one per 10 ms deadline). A lower bound
        // on a loaded machine is only "it ran": a starved thread skips deadlines instead of bursting.
        assert!(
            n >= 1 && n as f64 <= 1.0 + elapsed_s * 100.0,
            "100 fps for {elapsed_s:.3} s gave {n} frames"
        );
        let f = slot.latest().unwrap();
        assert_eq!((f.width, f.height, f.rgb.len()), (32, 24, 32 * 24 * 3));
    }
}

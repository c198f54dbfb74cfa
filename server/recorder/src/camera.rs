//! Camera sources. Each source runs on its own thread and publishes into a [`FrameSlot`] that keeps only the
//! newest frame (latest wins), stamped with its capture time on the process monotonic clock.

use phone2act_clock::monotonic_ns;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// One RGB8 frame.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Packed RGB, row-major, `width * height * 3` bytes.
    pub rgb: Arc<Vec<u8>>,
    /// Capture time on the process monotonic clock.
    pub capture_time_ns: i64,
    /// Sequence number at the source, +1 per captured frame.
    pub seq: u64,
}

/// A latest-frame slot shared between a capture thread and its readers.
#[derive(Debug, Default)]
pub struct FrameSlot {
    latest: Mutex<Option<Frame>>,
    frames_captured: AtomicU64,
}

impl FrameSlot {
    /// Replaces the newest frame.
    pub fn publish(&self, frame: Frame) {
        *self
            .latest
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(frame);
        self.frames_captured.fetch_add(1, Ordering::Relaxed);
    }

    /// The newest frame, if any.
    pub fn latest(&self) -> Option<Frame> {
        self.latest
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Frames published since start.
    pub fn frames_captured(&self) -> u64 {
        self.frames_captured.load(Ordering::Relaxed)
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

/// Starts a camera whose frames are drawn by `generator(seq, &mut rgb)` at `fps` (the simulated arm's
/// rendered view, test patterns). The generator must fill `width * height * 3` bytes.
pub fn spawn_generated(
    name: &str,
    width: u32,
    height: u32,
    fps: f64,
    mut generator: impl FnMut(u64, &mut Vec<u8>) + Send + 'static,
    slot: Arc<FrameSlot>,
) -> std::io::Result<CaptureThread> {
    let stop = Arc::new(AtomicBool::new(false));
    let stop_flag = Arc::clone(&stop);
    let period = Duration::from_secs_f64(1.0 / fps.max(0.1));
    let expected = width as usize * height as usize * 3;
    let handle = std::thread::Builder::new()
        .name(format!("camera-{name}"))
        .spawn(move || {
            let start = std::time::Instant::now();
            let mut seq = 0u64;
            while !stop_flag.load(Ordering::Relaxed) {
                // A fresh buffer per frame: readers may still hold the previous one through its Arc.
                let mut buf = Vec::with_capacity(expected);
                generator(seq, &mut buf);
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
                // Pace on absolute deadlines so the rate does not drift with drawing time.
                let next = start + period.mul_f64(seq as f64);
                let now = std::time::Instant::now();
                match next.checked_duration_since(now) {
                    Some(wait) => sleep_unless_stopped(wait, &stop_flag),
                    // Too slow for this rate: skip the missed deadlines instead of bursting.
                    None => {
                        seq = seq.max((now - start).as_secs_f64().div_euclid(period.as_secs_f64()) as u64);
                    }
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
    let deadline = std::time::Instant::now() + total;
    while !stop.load(Ordering::Relaxed) {
        let now = std::time::Instant::now();
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

    #[test]
    fn generated_camera_publishes_what_the_generator_draws() {
        let slot = Arc::new(FrameSlot::default());
        let cam = spawn_generated(
            "g",
            4,
            2,
            200.0,
            |seq, buf| buf.resize(24, seq as u8),
            Arc::clone(&slot),
        )
        .unwrap();
        std::thread::sleep(Duration::from_millis(60));
        cam.stop();
        let f = slot.latest().unwrap();
        assert_eq!(f.rgb.len(), 24);
        assert_eq!(u64::from(f.rgb[0]), f.seq % 256);
        assert!(slot.frames_captured() >= 3);
    }

    #[test]
    fn test_pattern_camera_publishes_at_its_rate() {
        let slot = Arc::new(FrameSlot::default());
        let cam = spawn_test_pattern("t", 32, 24, 100.0, Arc::clone(&slot)).unwrap();
        std::thread::sleep(Duration::from_millis(200));
        cam.stop();
        let n = slot.frames_captured();
        assert!((10..=30).contains(&n), "100 fps for 0.2 s gave {n} frames");
        let f = slot.latest().unwrap();
        assert_eq!((f.width, f.height, f.rgb.len()), (32, 24, 32 * 24 * 3));
    }
}

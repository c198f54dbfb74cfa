//! Faults that are not a clean kill: a write that fails while an encoder flushes, a save that fails half
//! way through its metadata. Each must end in a clear error, keep every saved episode, and leave the
//! recorder able to record. The failures are injected by putting something unwritable where the recorder
//! writes (`/dev/full`, a directory), so these run everywhere, without mounting anything.

mod common;

use common::{ManualRobot, copy_dir, read_json, spec, wait_for};
use phone2act_capture::camera::{Frame, FrameSlot};
use phone2act_dataset::Format;
use phone2act_recorder::{Phase, Recorder};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, mpsc};
use std::time::Duration;

/// Generous: a 64x64 episode of a few frames saves in well under a second even in a debug build on a
/// loaded 2-core machine; the bound only separates "returned" from "hangs forever".
const T: Duration = Duration::from_mins(1);
const SIZE: (u32, u32) = (64, 64);
const STAGING: &str = ".phone2act-staging";

/// A camera the test feeds by hand, so that nothing is encoded before the test has set its trap.
struct HandCamera {
    slot: Arc<FrameSlot>,
    on: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl HandCamera {
    fn new() -> Self {
        let slot = Arc::new(FrameSlot::default());
        let on = Arc::new(AtomicBool::new(true));
        let stop = Arc::new(AtomicBool::new(false));
        let (s, o, st) = (Arc::clone(&slot), Arc::clone(&on), Arc::clone(&stop));
        let thread = std::thread::spawn(move || {
            let mut seq = 0u64;
            let mut x = 0x2545_f491_u32;
            while !st.load(Ordering::Relaxed) {
                if o.load(Ordering::Relaxed) {
                    seq += 1;
                    // Noise: it does not compress, so every frame costs the disk a few kilobytes.
                    let rgb = (0..SIZE.0 * SIZE.1 * 3)
                        .map(|_| {
                            x ^= x << 13;
                            x ^= x >> 17;
                            x ^= x << 5;
                            x as u8
                        })
                        .collect();
                    s.publish(Frame {
                        width: SIZE.0,
                        height: SIZE.1,
                        rgb: Arc::new(rgb),
                        capture_time_ns: phone2act_clock::monotonic_ns(),
                        seq,
                    });
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        });
        HandCamera {
            slot,
            on,
            stop,
            thread: Some(thread),
        }
    }
}

impl Drop for HandCamera {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn open(root: &Path, format: Format, cam: &HandCamera, robot: &Arc<ManualRobot>) -> Recorder {
    Recorder::open(
        spec(root, format, &["front"], SIZE),
        robot.clone(),
        vec![("front".into(), Arc::clone(&cam.slot))],
    )
    .unwrap()
}

fn record(rec: &Recorder, task: &str, frames: u64) {
    rec.start_episode(task).unwrap();
    wait_for(rec, T, "frames", |s| s.frames_recorded >= frames);
    rec.stop_episode().unwrap();
}

/// Runs `f` on a thread and fails the test if it does not return within `T` (a hang, not a slow save).
fn within<R: Send + 'static>(what: &str, f: impl FnOnce() -> R + Send + 'static) -> R {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(T)
        .unwrap_or_else(|_| panic!("{what} did not return within {T:?}: the recorder is stuck"))
}

#[test]
fn a_video_file_that_cannot_be_written_fails_the_stop_and_the_recorder_keeps_working() {
    for format in [Format::V30, Format::V21] {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("ds");
        let cam = HandCamera::new();
        let robot = Arc::new(ManualRobot::default());
        let rec = Arc::new(open(&root, format, &cam, &robot));
        record(&rec, "good", 3);
        // No frames while the trap is set: the encoder opens its file with the first frame.
        cam.on.store(false, Ordering::Relaxed);
        std::thread::sleep(Duration::from_millis(50));
        rec.start_episode("flush fails").unwrap();
        let key = "observation.images.front.mp4";
        // Every write to /dev/full fails with ENOSPC: the encoder fails as it opens its file, which used to
        // hang in SVT-AV1's teardown of an encoder that never received a frame.
        std::os::unix::fs::symlink("/dev/full", root.join(STAGING).join(key)).unwrap();
        cam.on.store(true, Ordering::Relaxed);
        wait_for(&rec, T, "frames", |s| s.frames_recorded >= 4);
        let r = Arc::clone(&rec);
        let e = within("Stop", move || r.stop_episode()).unwrap_err();
        assert!(e.to_string().contains("disk full"), "{format:?}: {e}");
        let st = rec.status();
        assert_eq!(st.phase, Phase::Idle, "{format:?}");
        assert!(st.warning.unwrap().contains("not saved"), "{format:?}");
        // Everything still answers, and the next episode saves.
        let r = Arc::clone(&rec);
        within("Start/Stop after the failure", move || {
            record(&r, "good again", 3);
        });
        assert_eq!(rec.episodes().len(), 2, "{format:?}");
        let r = Arc::clone(&rec);
        within("Start/Discard after the failure", move || {
            r.start_episode("thrown away").unwrap();
            r.discard_episode().unwrap();
        });
        drop(rec);
        assert_eq!(read_json(&root.join("meta/info.json"))["total_episodes"], 2);
    }
}

#[test]
fn a_v21_save_that_fails_writing_its_metadata_leaves_no_duplicate_episode_line() {
    for file in ["provenance.json", "info.json", "episodes_stats.jsonl"] {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("ds");
        let cam = HandCamera::new();
        let robot = Arc::new(ManualRobot::default());
        let rec = open(&root, Format::V21, &cam, &robot);
        record(&rec, "one", 3);
        rec.start_episode("fails").unwrap();
        // A directory where the save writes a file: that write fails, as it would on a full disk.
        std::fs::create_dir_all(root.join(STAGING).join(file).join("x")).unwrap();
        wait_for(&rec, T, "frames", |s| s.frames_recorded >= 3);
        let e = rec.stop_episode().unwrap_err();
        assert!(!e.to_string().is_empty());
        record(&rec, "two", 3);
        rec.close().unwrap();
        let lines = std::fs::read_to_string(root.join("meta/episodes.jsonl")).unwrap();
        let indices: Vec<u64> = lines
            .lines()
            .map(|l| {
                serde_json::from_str::<serde_json::Value>(l).unwrap()["episode_index"]
                    .as_u64()
                    .unwrap()
            })
            .collect();
        assert_eq!(indices, [0, 1], "{file}: {lines}");
        let stats = std::fs::read_to_string(root.join("meta/episodes_stats.jsonl")).unwrap();
        assert_eq!(stats.lines().count(), 2, "{file}");
        let report = phone2act_dataset::verify::verify(&root);
        assert!(report.ok(), "{file}: {:?}", report.problems);
        // And the server reopens it.
        let rec = open(&root, Format::V21, &cam, &robot);
        assert_eq!(rec.episodes().len(), 2, "{file}");
    }
}

struct Unmount(std::path::PathBuf);
impl Drop for Unmount {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

/// The disk fills at every point of an episode in turn: while the encoder opens its file, while it
/// writes frames, while it flushes at Stop, while the metadata is saved. Each Stop returns (an error or
/// a saved episode), and once space is freed the recorder saves again.
#[test]
fn a_disk_that_fills_at_any_point_of_a_save_never_locks_the_recorder() {
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("mnt");
    std::fs::create_dir_all(&mnt).unwrap();
    let ok = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=8m", "tmpfs"])
        .arg(&mnt)
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        eprintln!("SKIPPED: cannot mount a tmpfs here (needs root) to fill a disk");
        return;
    }
    let _guard = Unmount(mnt.clone());
    for format in [Format::V30, Format::V21] {
        let root = mnt.join(format.codebase_version());
        let cam = HandCamera::new();
        let robot = Arc::new(ManualRobot::default());
        let rec = Arc::new(open(&root, format, &cam, &robot));
        record(&rec, "room", 3);
        let mut saved = 1;
        let mut failed = 0;
        // Free space from 4 KB to 512 KB: the small ends fail early, the large ones inside the flush or
        // the metadata, the largest save.
        for free_kb in [4u64, 12, 16, 24, 32, 48, 64, 96, 128, 160, 200, 256, 330, 512] {
            let filler = mnt.join("filler");
            fill_leaving(&mnt, &filler, free_kb * 1024);
            rec.start_episode("tight").unwrap();
            // 12 frames of 64x64 noise: tens of kilobytes of video, about what is left.
            wait_for(&rec, T, "frames or failure", |s| {
                s.frames_recorded >= 12 || s.warning.as_deref().is_some_and(|w| w.contains("failed"))
            });
            let r = Arc::clone(&rec);
            match within(&format!("Stop with {free_kb} KB free"), move || r.stop_episode()) {
                Ok(_) => saved += 1,
                Err(e) => {
                    failed += 1;
                    assert!(!e.to_string().is_empty());
                }
            }
            assert_eq!(rec.status().phase, Phase::Idle, "{free_kb} KB");
            std::fs::remove_file(&filler).unwrap();
            let r = Arc::clone(&rec);
            within(&format!("a save after {free_kb} KB"), move || {
                record(&r, "room again", 3);
            });
            saved += 1;
        }
        assert!(
            failed > 0,
            "{format:?}: the disk never filled; the test proves nothing"
        );
        let rec = Arc::try_unwrap(rec).ok().unwrap();
        assert_eq!(rec.episodes().len(), saved, "{format:?}");
        rec.close().unwrap();
        let report = phone2act_dataset::verify::verify(&root);
        assert!(report.ok(), "{format:?}: {:?}", report.problems);
        let rec = open(&root, format, &cam, &robot);
        assert_eq!(rec.episodes().len(), saved, "{format:?}");
        rec.close().unwrap();
        std::fs::remove_dir_all(&root).unwrap();
    }
}

/// Writes `filler` until the filesystem at `mnt` has about `free` bytes left.
fn fill_leaving(mnt: &Path, filler: &Path, free: u64) {
    use std::io::Write;
    let avail = fs_available(mnt);
    let mut f = std::fs::File::create(filler).unwrap();
    let block = vec![0xa5u8; 4096];
    let mut to_write = avail.saturating_sub(free);
    while to_write > 0 {
        let n = to_write.min(4096) as usize;
        if f.write_all(&block[..n]).is_err() {
            break;
        }
        to_write -= n as u64;
    }
    f.sync_all().unwrap();
}

fn fs_available(mnt: &Path) -> u64 {
    let out = std::process::Command::new("df")
        .args(["--output=avail", "-B1"])
        .arg(mnt)
        .output()
        .unwrap();
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .nth(1)
        .and_then(|l| l.trim().parse().ok())
        .unwrap()
}

/// `verify` reads the metadata files against each other: a duplicated episode index (what the failed v2.1
/// save used to leave) and any disagreement between them are reported in words.
#[test]
fn verify_finds_duplicated_episode_indices_and_disagreeing_metadata() {
    use phone2act_dataset::verify::verify;
    let problems = |root: &Path| verify(root).problems.join("\n");
    for format in [Format::V21, Format::V30] {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("ds");
        let cam = HandCamera::new();
        let robot = Arc::new(ManualRobot::default());
        // Nothing is written before the first episode.
        let rec = open(&root, format, &cam, &robot);
        rec.close().unwrap();
        assert!(!root.join("meta/info.json").exists(), "{format:?}");
        assert!(problems(&root).contains("before the first episode"), "{format:?}");
        let rec = open(&root, format, &cam, &robot);
        record(&rec, "one", 3);
        record(&rec, "two", 3);
        rec.close().unwrap();
        assert!(verify(&root).ok(), "{format:?}: {}", problems(&root));

        let copy = dir.path().join("dup");
        copy_dir(&root, &copy);
        if format == Format::V21 {
            // The second line again, as the failed save wrote it.
            let p = copy.join("meta/episodes.jsonl");
            let text = std::fs::read_to_string(&p).unwrap();
            let second = text.lines().nth(1).unwrap().to_owned();
            std::fs::write(&p, format!("{text}{second}\n")).unwrap();
        } else {
            let from = copy.join("meta/episodes/chunk-000/file-001.parquet");
            std::fs::copy(&from, copy.join("meta/episodes/chunk-000/file-002.parquet")).unwrap();
        }
        let text = problems(&copy);
        assert!(
            text.contains("episode index 1 appears twice"),
            "{format:?}: {text}"
        );

        // info.json disagreeing with the episode metadata and the task table.
        let copy = dir.path().join("disagree");
        copy_dir(&root, &copy);
        let p = copy.join("meta/info.json");
        let info = std::fs::read_to_string(&p)
            .unwrap()
            .replace("\"total_tasks\": 2", "\"total_tasks\": 3");
        std::fs::write(&p, info).unwrap();
        let text = problems(&copy);
        assert!(
            text.contains("info.json says 3 tasks, the task table has 2"),
            "{format:?}: {text}"
        );
        if format == Format::V21 {
            // episodes_stats.jsonl missing an episode.
            let copy = dir.path().join("stats");
            copy_dir(&root, &copy);
            let p = copy.join("meta/episodes_stats.jsonl");
            let first = std::fs::read_to_string(&p)
                .unwrap()
                .lines()
                .next()
                .unwrap()
                .to_owned();
            std::fs::write(&p, format!("{first}\n")).unwrap();
            let text = problems(&copy);
            assert!(text.contains("episodes_stats.jsonl covers 1 episodes"), "{text}");
        }
    }
}

//! The Dobot bridge against committed transcripts of the controller's side of the conversation
//! (`tests/fixtures/dobot/`, written from Dobot's protocol guide; see the README there): a replayer on
//! loopback TCP checks every byte the bridge sends against the transcript and answers with the transcript's
//! bytes, and a second listener streams the committed 1440-byte feedback packets.

use parking_lot::Mutex;
use phone2act_bridges::dobot::feedback::{FeedbackPacket, PACKET_LEN};
use phone2act_bridges::dobot::{ControlRequest, DobotBridge, DobotConfig};
use phone2act_bridges::{Bridge, Command, Health};
use std::io::{ErrorKind, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fixtures/dobot")
        .join(name)
}

#[derive(Clone, Debug, PartialEq)]
enum Step {
    /// Bytes the client must send.
    Expect(String),
    /// Bytes the controller answers.
    Answer(String),
}

fn load_transcript(name: &str) -> Vec<Step> {
    let text = std::fs::read_to_string(fixture(name)).unwrap();
    text.lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            if let Some(sent) = l.strip_prefix("> ") {
                Step::Expect(sent.to_owned())
            } else if let Some(answer) = l.strip_prefix("< ") {
                Step::Answer(answer.to_owned())
            } else {
                panic!("{name}: line {l:?} is neither '> ' nor '< '")
            }
        })
        .collect()
}

/// What the replayer saw.
#[derive(Debug, Default)]
struct Replay {
    /// Steps done, in order.
    done: usize,
    /// The first difference between what the client sent and the transcript.
    mismatch: Option<String>,
    /// Bytes the client sent after the transcript ended.
    extra: Vec<u8>,
}

struct Controller {
    dashboard_port: u16,
    feedback_port: u16,
    replay: Arc<Mutex<Replay>>,
    /// The packet streamed every 8 ms; a test swaps it to change the robot's state.
    packet: Arc<Mutex<Vec<u8>>>,
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Controller {
    fn start(transcript: &str, packet_file: &str) -> Self {
        let steps = load_transcript(transcript);
        let dashboard = TcpListener::bind("127.0.0.1:0").unwrap();
        let feedback = TcpListener::bind("127.0.0.1:0").unwrap();
        let replay = Arc::new(Mutex::new(Replay::default()));
        let packet = Arc::new(Mutex::new(std::fs::read(fixture(packet_file)).unwrap()));
        let stop = Arc::new(AtomicBool::new(false));
        let mut controller = Self {
            dashboard_port: dashboard.local_addr().unwrap().port(),
            feedback_port: feedback.local_addr().unwrap().port(),
            replay: Arc::clone(&replay),
            packet: Arc::clone(&packet),
            stop: Arc::clone(&stop),
            threads: Vec::new(),
        };
        let stop_d = Arc::clone(&stop);
        controller.threads.push(std::thread::spawn(move || {
            let Some(stream) = accept(&dashboard, &stop_d) else {
                return;
            };
            replay_steps(stream, &steps, &replay, &stop_d);
        }));
        controller.threads.push(std::thread::spawn(move || {
            let Some(mut stream) = accept(&feedback, &stop) else {
                return;
            };
            // The controller's 30004 period.
            while !stop.load(Ordering::SeqCst) {
                let bytes = packet.lock().clone();
                if stream.write_all(&bytes).is_err() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(8));
            }
        }));
        controller
    }

    fn config(&self) -> DobotConfig {
        let mut c = DobotConfig::new("127.0.0.1");
        c.dashboard_port = self.dashboard_port;
        c.feedback_port = self.feedback_port;
        c
    }

    fn set_packet(&self, packet_file: &str) {
        *self.packet.lock() = std::fs::read(fixture(packet_file)).unwrap();
    }

    /// Waits until the transcript is played to its end, and checks nothing differed.
    fn finish(&self, steps: usize) {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            {
                let r = self.replay.lock();
                assert_eq!(r.mismatch, None, "after {} steps", r.done);
                if r.done == steps {
                    return;
                }
            }
            assert!(
                Instant::now() < deadline,
                "transcript not played to its end: {:?}",
                self.replay.lock()
            );
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

impl Drop for Controller {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

fn accept(listener: &TcpListener, stop: &AtomicBool) -> Option<TcpStream> {
    listener.set_nonblocking(true).unwrap();
    while !stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((s, _)) => {
                s.set_nonblocking(false).unwrap();
                s.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
                return Some(s);
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(Duration::from_millis(2)),
            Err(e) => panic!("accept: {e}"),
        }
    }
    None
}

/// Reads exactly what each `Expect` step says (and compares it), writes each `Answer`; afterwards keeps
/// whatever else arrives as `extra`.
fn replay_steps(mut stream: TcpStream, steps: &[Step], replay: &Mutex<Replay>, stop: &AtomicBool) {
    let mut writer = stream.try_clone().unwrap();
    let mut chunk = [0u8; 512];
    let mut pending: Vec<u8> = Vec::new();
    let mut read_more = |pending: &mut Vec<u8>| -> bool {
        match stream.read(&mut chunk) {
            Ok(0) => false,
            Ok(n) => {
                pending.extend_from_slice(&chunk[..n]);
                true
            }
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => true,
            Err(_) => false,
        }
    };
    for step in steps {
        match step {
            Step::Expect(text) => {
                while pending.len() < text.len() && !stop.load(Ordering::SeqCst) {
                    if !read_more(&mut pending) {
                        return;
                    }
                }
                if stop.load(Ordering::SeqCst) {
                    return;
                }
                let got: Vec<u8> = pending.drain(..text.len()).collect();
                if got != text.as_bytes() {
                    replay.lock().mismatch = Some(format!(
                        "expected {text:?}, the client sent {:?}",
                        String::from_utf8_lossy(&got)
                    ));
                    return;
                }
            }
            Step::Answer(text) => {
                if writer.write_all(text.as_bytes()).is_err() {
                    return;
                }
            }
        }
        replay.lock().done += 1;
    }
    while !stop.load(Ordering::SeqCst) && read_more(&mut pending) {
        if !pending.is_empty() {
            replay.lock().extra.append(&mut pending);
        }
    }
}

fn wait_for(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + timeout;
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// The committed packets parse to the values the generator wrote (guide §4 offsets).
#[test]
#[allow(clippy::float_cmp)] // the generator wrote these exact, exactly representable values
fn committed_feedback_packets_parse_to_their_documented_values() {
    let bytes = std::fs::read(fixture("feedback_enabled.bin")).unwrap();
    assert_eq!(bytes.len(), PACKET_LEN);
    let p = FeedbackPacket::parse(&bytes).unwrap();
    assert_eq!(p.robot_mode, 5);
    assert_eq!(p.robot_type, 5, "CR5");
    assert_eq!(p.enable_status, 1);
    assert_eq!(p.tool_vector_actual, [-400.0, 0.0, 350.0, 170.0, 10.0, 30.0]);
    assert_eq!(p.q_actual_deg, [10.0, -20.0, 90.0, -70.0, -90.0, 30.0]);
    let q = p.actual_quaternion_wxyz;
    assert!((q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-12);
    let error = FeedbackPacket::parse(&std::fs::read(fixture("feedback_error.bin")).unwrap()).unwrap();
    assert_eq!((error.robot_mode, error.error_status), (9, 1));
}

#[test]
fn v46_start_servo_and_gripper_match_the_transcript_byte_for_byte() {
    let steps = load_transcript("start_v46.transcript").len();
    let controller = Controller::start("start_v46.transcript", "feedback_enabled.bin");
    let bridge = DobotBridge::start(controller.config()).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    assert_eq!(bridge.stats().control_request, ControlRequest::Granted);
    // The Euler angles and the quaternion in the committed packet agree under the fixed-axis convention.
    wait_for("the convention confirmed", Duration::from_secs(2), || {
        bridge.stats().convention_verified
    });
    // Hold where the robot is: the ServoP the transcript expects.
    let here = bridge.feedback().unwrap().robot_from_ee;
    bridge.send(Command {
        seq: 1,
        robot_from_target: here,
        gripper_target: 0.0,
        issue_time_ns: 0,
        joint_targets_rad: None,
    });
    wait_for("applied", Duration::from_secs(2), || {
        bridge.feedback().is_some_and(|f| f.applied_seq == 1)
    });
    controller.finish(steps);
    bridge.shutdown();
    assert!(
        controller.replay.lock().extra.is_empty(),
        "{:?}",
        controller.replay.lock()
    );
}

#[test]
fn a_v45_controller_needs_no_control_request() {
    let steps = load_transcript("start_v45.transcript").len();
    let controller = Controller::start("start_v45.transcript", "feedback_enabled.bin");
    let bridge = DobotBridge::start(controller.config()).unwrap();
    controller.finish(steps);
    assert_eq!(bridge.stats().control_request, ControlRequest::NotSupported);
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
}

#[test]
fn a_reply_nobody_asked_for_is_set_aside() {
    let steps = load_transcript("stray_reply.transcript").len();
    let controller = Controller::start("stray_reply.transcript", "feedback_enabled.bin");
    let bridge = DobotBridge::start(controller.config()).unwrap();
    controller.finish(steps);
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    let stats = bridge.stats();
    assert_eq!(stats.replies_discarded, 1);
    assert_eq!(stats.last_command_error, None);
}

#[test]
fn a_servo_alarm_from_the_transcript_is_named() {
    let steps = load_transcript("servo_alarm.transcript").len();
    let controller = Controller::start("servo_alarm.transcript", "feedback_enabled.bin");
    let bridge = DobotBridge::start(controller.config()).unwrap();
    wait_for("ready", Duration::from_secs(2), || {
        bridge.health() == Health::Ready
    });
    controller.set_packet("feedback_error.bin");
    wait_for(
        "the alarm named",
        Duration::from_secs(2),
        || matches!(bridge.health(), Health::Error(m) if m.contains("J2 servo alarm 4368")),
    );
    controller.finish(steps);
}

//! The example bridge of `BRIDGE_TEMPLATE.md`, compiled and tested: a position-only arm that speaks a
//! line protocol over TCP (`MOVE x_mm y_mm z_mm` → `OK`, `POS` → `x_mm y_mm z_mm`), plus a tiny robot that
//! answers it. Keep the two in step: the document quotes the code between the `template:` markers.

// template: start
use nalgebra::{Isometry3, Translation3};
use parking_lot::Mutex;
use phone2act_bridges::{Bridge, BridgeError, Command, Control, Feedback, FeedbackCell, Health, LatestSlot};
use serde::Deserialize;
use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// `[arms.example]` in the server config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExampleConfig {
    pub address: String,
    #[serde(default = "default_rate_hz")]
    pub rate_hz: f64,
}

fn default_rate_hz() -> f64 {
    50.0
}

struct Inner {
    config: ExampleConfig,
    joint_names: Vec<String>,
    slot: LatestSlot<Command>,
    feedback: FeedbackCell,
    health: Mutex<Health>,
    applied_seq: AtomicU64,
    stop: AtomicBool,
    epoch: Instant,
}

pub struct ExampleBridge {
    inner: Arc<Inner>,
    thread: Mutex<Option<std::thread::JoinHandle<()>>>,
}

impl ExampleBridge {
    pub fn start(config: ExampleConfig) -> Result<Arc<Self>, BridgeError> {
        if !(config.rate_hz > 0.0 && config.rate_hz <= 1000.0) {
            return Err(BridgeError::Config(format!(
                "rate_hz {} outside (0, 1000]",
                config.rate_hz
            )));
        }
        // Fail at start if the robot is not there: the server reports it instead of running a dead arm.
        let stream = TcpStream::connect(&config.address).map_err(|e| BridgeError::Connect {
            target: config.address.clone(),
            message: e.to_string(),
        })?;
        stream.set_nodelay(true)?;
        stream.set_read_timeout(Some(Duration::from_millis(200)))?;
        let inner = Arc::new(Inner {
            config,
            joint_names: vec!["x".into(), "y".into(), "z".into()],
            slot: LatestSlot::default(),
            feedback: FeedbackCell::default(),
            health: Mutex::new(Health::Ready),
            applied_seq: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            epoch: Instant::now(),
        });
        let worker = Arc::clone(&inner);
        let thread = std::thread::Builder::new()
            .name("example-bridge".into())
            .spawn(move || worker.run(stream))?;
        Ok(Arc::new(Self {
            inner,
            thread: Mutex::new(Some(thread)),
        }))
    }
}

impl Inner {
    fn set_health(&self, health: Health) {
        *self.health.lock() = health;
    }

    /// One request, one reply line.
    fn request(reader: &mut BufReader<TcpStream>, line: &str) -> std::io::Result<String> {
        reader.get_mut().write_all(line.as_bytes())?;
        let mut reply = String::new();
        if reader.read_line(&mut reply)? == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        Ok(reply.trim().to_owned())
    }

    fn run(&self, stream: TcpStream) {
        let mut reader = BufReader::new(stream);
        let period = Duration::from_secs_f64(1.0 / self.config.rate_hz);
        while !self.stop.load(Ordering::SeqCst) {
            // The newest target only: a slow robot never works through a backlog.
            if let Some(command) = self.slot.take_wait(period) {
                // Metres inside phone2act; the robot wants millimetres, so convert here and only here.
                let p = command.robot_from_target.translation.vector * 1000.0;
                if !p.iter().all(|v| v.is_finite()) {
                    continue; // never send garbage; the arm holds
                }
                match Self::request(&mut reader, &format!("MOVE {:.2} {:.2} {:.2}\n", p.x, p.y, p.z)) {
                    Ok(reply) if reply == "OK" => self.applied_seq.store(command.seq, Ordering::SeqCst),
                    Ok(reply) => self.set_health(Health::Error(format!("robot refused MOVE: {reply}"))),
                    Err(e) => {
                        self.set_health(Health::Disconnected(e.to_string()));
                        return;
                    }
                }
            }
            match Self::request(&mut reader, "POS\n") {
                Ok(reply) => {
                    let v: Vec<f64> = reply.split_whitespace().filter_map(|s| s.parse().ok()).collect();
                    let [x, y, z] = v[..] else {
                        self.set_health(Health::Error(format!("bad POS reply {reply:?}")));
                        continue;
                    };
                    *self.feedback.lock() = Some(Feedback {
                        capture_time_ns: self.epoch.elapsed().as_nanos() as i64,
                        joint_positions_rad: vec![x / 1000.0, y / 1000.0, z / 1000.0],
                        robot_from_ee: Isometry3::from_parts(
                            Translation3::new(x / 1000.0, y / 1000.0, z / 1000.0),
                            nalgebra::UnitQuaternion::identity(),
                        ),
                        gripper_position: 0.0,
                        applied_seq: self.applied_seq.load(Ordering::SeqCst),
                        task_success: false,
                    });
                }
                Err(e) => {
                    self.set_health(Health::Disconnected(e.to_string()));
                    return;
                }
            }
        }
    }
}

impl Bridge for ExampleBridge {
    fn kind(&self) -> &'static str {
        "example"
    }
    fn joint_names(&self) -> &[String] {
        &self.inner.joint_names
    }
    fn supports_orientation(&self) -> bool {
        false // position only: the planner keeps the orientation at its reference
    }
    fn send(&self, command: Command) {
        self.inner.slot.put(command);
    }
    fn feedback(&self) -> Option<Feedback> {
        self.inner.feedback.lock().clone()
    }
    fn health(&self) -> Health {
        self.inner.health.lock().clone()
    }
    fn control(&self, request: Control) -> Result<(), BridgeError> {
        match request {
            Control::ClearError => {
                self.inner.set_health(Health::Ready);
                Ok(())
            }
            other => Err(BridgeError::Protocol(format!(
                "{other:?} is not supported by this robot"
            ))),
        }
    }
    fn shutdown(&self) {
        self.inner.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.lock().take() {
            let _ = t.join();
        }
    }
}
// template: end

/// The robot: a point that jumps to each MOVE.
fn toy_robot() -> std::net::SocketAddr {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        let Ok((stream, _)) = listener.accept() else {
            return;
        };
        let mut writer = stream.try_clone().unwrap();
        let mut position = [100.0, 0.0, 50.0];
        for line in BufReader::new(stream).lines() {
            let Ok(line) = line else { return };
            let reply = match line.split_whitespace().collect::<Vec<_>>().as_slice() {
                ["POS"] => format!("{} {} {}\n", position[0], position[1], position[2]),
                ["MOVE", x, y, z] => match (x.parse(), y.parse(), z.parse()) {
                    (Ok(x), Ok(y), Ok(z)) if f64::abs(x) < 1000.0 => {
                        position = [x, y, z];
                        "OK\n".to_owned()
                    }
                    _ => "ERR out of range\n".to_owned(),
                },
                _ => "ERR unknown\n".to_owned(),
            };
            if writer.write_all(reply.as_bytes()).is_err() {
                return;
            }
        }
    });
    addr
}

#[test]
fn the_template_bridge_follows_targets_and_reports_refusals() {
    let config: ExampleConfig = toml::from_str(&format!("address = \"{}\"", toy_robot())).unwrap();
    let bridge = ExampleBridge::start(config).unwrap();
    let deadline = Instant::now() + Duration::from_secs(2);
    while bridge.feedback().is_none() {
        assert!(Instant::now() < deadline);
        std::thread::sleep(Duration::from_millis(5));
    }
    let first = bridge.feedback().unwrap().robot_from_ee.translation.vector;
    assert!((first - nalgebra::Vector3::new(0.1, 0.0, 0.05)).norm() < 1e-9);
    let target = Isometry3::translation(0.2, -0.05, 0.1);
    bridge.send(Command {
        seq: 3,
        robot_from_target: target,
        gripper_target: 0.0,
        issue_time_ns: 0,
        joint_targets_rad: None,
    });
    while !bridge.feedback().is_some_and(|f| {
        f.applied_seq == 3 && (f.robot_from_ee.translation.vector - target.translation.vector).norm() < 1e-6
    }) {
        assert!(
            Instant::now() < deadline + Duration::from_secs(1),
            "target not reached"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    bridge.send(Command {
        seq: 4,
        robot_from_target: Isometry3::translation(5.0, 0.0, 0.0),
        gripper_target: 0.0,
        issue_time_ns: 0,
        joint_targets_rad: None,
    });
    while !matches!(bridge.health(), Health::Error(m) if m.contains("out of range")) {
        assert!(
            Instant::now() < deadline + Duration::from_secs(2),
            "refusal not reported"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    bridge.control(Control::ClearError).unwrap();
    assert_eq!(bridge.health(), Health::Ready);
    assert!(bridge.control(Control::Enable).is_err());
    bridge.shutdown();
}

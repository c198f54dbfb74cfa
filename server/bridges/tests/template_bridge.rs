//! The example bridge of `BRIDGE_TEMPLATE.md`, compiled and tested: a position-only arm that speaks a
//! line protocol over TCP (`MOVE x_mm y_mm z_mm` → `OK`, `POS` → `x_mm y_mm z_mm`), plus a tiny robot that
//! answers it. Keep the two in step: the document quotes the code between the `template:` markers.

// template: start
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use parking_lot::Mutex;
use phone2act_bridges::runtime::{LinkContext, Measured, RobotLink, Schedule, ThreadedBridge};
use phone2act_bridges::{BridgeError, Command, Control, Health};
use serde::Deserialize;
use std::io::{BufRead, BufReader, Write};
use std::net::{Shutdown, TcpStream};
use std::sync::Arc;
use std::time::Duration;

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

/// The robot's protocol: one request line, one reply line, over one TCP connection.
pub struct ExampleLink {
    config: ExampleConfig,
    joint_names: Vec<String>,
    conn: Mutex<BufReader<TcpStream>>,
    /// The last fault, shown as health until it is cleared; `None` when all is well.
    fault: Mutex<Option<Health>>,
}

/// The bridge: the runtime's threads, slot and rules around the link.
pub type ExampleBridge = ThreadedBridge<ExampleLink>;

pub fn start(config: ExampleConfig) -> Result<Arc<ExampleBridge>, BridgeError> {
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
    // Every blocking call has a timeout, so shutdown and control return promptly.
    stream.set_read_timeout(Some(Duration::from_millis(200)))?;
    let link = ExampleLink {
        config,
        joint_names: vec!["x".into(), "y".into(), "z".into()],
        conn: Mutex::new(BufReader::new(stream)),
        fault: Mutex::new(None),
    };
    Ok(Arc::new(ThreadedBridge::spawn(
        link,
        phone2act_clock::monotonic_ns,
    )?))
}

impl ExampleLink {
    /// One request, one reply line; a failed socket is a `Disconnected` fault.
    fn request(&self, line: &str) -> Option<String> {
        let mut conn = self.conn.lock();
        let mut reply = String::new();
        let result = conn
            .get_mut()
            .write_all(line.as_bytes())
            .and_then(|()| conn.read_line(&mut reply));
        match result {
            Ok(n) if n > 0 => Some(reply.trim().to_owned()),
            Ok(_) => self.fail(Health::Disconnected("closed by the robot".into())),
            Err(e) => self.fail(Health::Disconnected(e.to_string())),
        }
    }

    fn fail<T>(&self, health: Health) -> Option<T> {
        *self.fault.lock() = Some(health);
        None
    }
}

impl RobotLink for ExampleLink {
    fn kind(&self) -> &'static str {
        "example"
    }
    fn joint_names(&self) -> &[String] {
        &self.joint_names
    }
    fn supports_orientation(&self) -> bool {
        false // position only: the planner keeps the orientation at its reference
    }
    fn schedule(&self) -> Schedule {
        // One line to the robot: write, then read, once a period.
        Schedule::Cycle {
            period: Duration::from_secs_f64(1.0 / self.config.rate_hz),
        }
    }
    fn health(&self, _ctx: &LinkContext) -> Health {
        self.fault.lock().clone().unwrap_or(Health::Ready)
    }
    /// Called only while health is `Ready`, with the newest target and only finite numbers in it.
    fn write_command(&self, ctx: &LinkContext, command: Option<&Command>) -> bool {
        let Some(command) = command else { return true };
        // Metres inside phone2act; the robot wants millimetres, so convert here and only here.
        let p = command.robot_from_target.translation.vector * 1000.0;
        match self.request(&format!("MOVE {:.2} {:.2} {:.2}\n", p.x, p.y, p.z)) {
            Some(reply) if reply == "OK" => ctx.applied(command.seq),
            Some(reply) => *self.fault.lock() = Some(Health::Error(format!("robot refused MOVE: {reply}"))),
            None => return false,
        }
        true
    }
    fn read_feedback(&self, _ctx: &LinkContext) -> Option<Measured> {
        let reply = self.request("POS\n")?;
        let v: Vec<f64> = reply.split_whitespace().filter_map(|s| s.parse().ok()).collect();
        let [x, y, z] = v[..] else {
            return self.fail(Health::Error(format!("bad POS reply {reply:?}")));
        };
        let p = Translation3::new(x / 1000.0, y / 1000.0, z / 1000.0);
        Some(Measured {
            joint_positions_rad: vec![p.x, p.y, p.z],
            robot_from_ee: Isometry3::from_parts(p, UnitQuaternion::identity()),
            gripper_position: 0.0,
        })
    }
    fn control(&self, _ctx: &LinkContext, request: Control) -> Result<(), BridgeError> {
        match request {
            Control::ClearError => {
                let mut fault = self.fault.lock();
                if !matches!(*fault, Some(Health::Disconnected(_))) {
                    *fault = None;
                }
                Ok(())
            }
            other => Err(BridgeError::Protocol(format!(
                "{other:?} is not supported by this robot"
            ))),
        }
    }
    fn close(&self) {
        let _ = self.conn.lock().get_ref().shutdown(Shutdown::Both);
    }
}
// template: end

use phone2act_bridges::Bridge;
use std::time::Instant;

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
    let bridge = start(config).unwrap();
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
    // Held while in error: a target sent now is not written (nothing can make this fail by being slow).
    bridge.send(Command {
        seq: 5,
        robot_from_target: Isometry3::translation(0.1, 0.0, 0.1),
        gripper_target: 0.0,
        issue_time_ns: 0,
        joint_targets_rad: None,
    });
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(
        bridge.feedback().unwrap().applied_seq,
        3,
        "a target was written while in error"
    );
    bridge.control(Control::ClearError).unwrap();
    assert_eq!(bridge.health(), Health::Ready);
    assert!(bridge.control(Control::Enable).is_err());
    bridge.shutdown();
}

//! Checks a Dobot CR controller before the first teleoperation: it is reachable and in TCP/IP mode, answers
//! commands sent without a terminator with their own echo, what it does with a stray line end, its firmware
//! generation (by its answer to `RequestControl()`, only with `--request-control`), robot mode, alarms
//! (`GetErrorID`'s seven lists), the feedback stream (packet size, test value, robot type, joint angles) and
//! the Euler convention of its tool pose, and the HTTP tool endpoint's port.
//!
//! `dobot-check --host 192.168.5.1 [--dashboard-port 29999] [--feedback-port 30004] [--http-port 22000]
//!  [--request-control] [--gripper-test]`
//!
//! Moves nothing: it sends queries only (`RobotMode()`, `GetErrorID()`). `--request-control` also sends
//! `RequestControl()`, which switches a V4.6+ controller to TCP control (allowed only while disabled).
//! `--gripper-test` posts the open and then the close frame of the default Modbus gripper to the tool
//! endpoint: the gripper moves. Prints one line per check with `OK`, `WARN` or `FAIL`; exits 1 on a `FAIL`.

use phone2act_bridges::dobot::feedback::{
    ConventionCheck, EulerConvention, FrameReader, PACKET_LEN, check_convention,
};
use phone2act_bridges::dobot::gripper::{http_post_json, modbus_http_body, modbus_write_register};
use phone2act_bridges::dobot::protocol::{ErrorIds, RobotMode, error_text, parse_reply};
use phone2act_bridges::dobot::{CommandConn, DobotConfig, LinkError};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::{Duration, Instant};

const USAGE: &str = "dobot-check --host ADDRESS [--dashboard-port 29999] [--feedback-port 30004] \
                     [--http-port 22000] [--request-control] [--gripper-test]";

#[derive(Default)]
struct Verdict {
    passed: usize,
    warnings: usize,
    failures: usize,
}

impl Verdict {
    fn ok(&mut self, what: &str) {
        self.passed += 1;
        println!("OK   {what}");
    }
    fn warn(&mut self, what: &str) {
        self.warnings += 1;
        println!("WARN {what}");
    }
    fn fail(&mut self, what: &str) {
        self.failures += 1;
        println!("FAIL {what}");
    }
}

fn resolve(host: &str, port: u16) -> Result<SocketAddr, Box<dyn std::error::Error>> {
    (host, port)
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| format!("{host}:{port} did not resolve").into())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut config = DobotConfig::new("");
    let mut http_port = 22000u16;
    let mut request_control = false;
    let mut gripper_test = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().ok_or_else(|| format!("{a} needs a value\n{USAGE}"));
        match a.as_str() {
            "--host" => config.host = value()?,
            "--dashboard-port" => config.dashboard_port = value()?.parse()?,
            "--feedback-port" => config.feedback_port = value()?.parse()?,
            "--http-port" => http_port = value()?.parse()?,
            "--request-control" => request_control = true,
            "--gripper-test" => gripper_test = true,
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            other => return Err(format!("unknown argument {other}\n{USAGE}").into()),
        }
    }
    if config.host.is_empty() {
        return Err(format!("--host is required\n{USAGE}").into());
    }
    let mut v = Verdict::default();
    check_dashboard(&config, request_control, &mut v)?;
    check_feedback(&config, &mut v)?;
    check_gripper_endpoint(&config.host, http_port, gripper_test, &mut v)?;
    if v.failures == 0 {
        println!("OK ({} checks passed, {} warnings)", v.passed, v.warnings);
        Ok(())
    } else {
        println!("NOT READY ({} failures, {} warnings)", v.failures, v.warnings);
        std::process::exit(1);
    }
}

fn check_dashboard(
    config: &DobotConfig,
    request_control: bool,
    v: &mut Verdict,
) -> Result<(), Box<dyn std::error::Error>> {
    let addr = resolve(&config.host, config.dashboard_port)?;
    let discarded = Arc::new(AtomicU64::new(0));
    let mut conn = match CommandConn::connect(addr, config, Arc::clone(&discarded)) {
        Ok(c) => c,
        Err(e) => {
            v.fail(&format!("dashboard {addr}: {e}"));
            return Ok(());
        }
    };
    v.ok(&format!("dashboard {addr} accepts a connection"));
    // Terminator: the command alone, as Dobot's clients send it; the reply must echo it.
    match conn.request("RobotMode()") {
        Ok(reply) => {
            v.ok(&format!(
                "RobotMode() without a terminator answered with its own echo ({:?})",
                reply.echo
            ));
            let mode = reply
                .values
                .first()
                .and_then(|m| m.parse::<u64>().ok())
                .map(RobotMode::from_code);
            match mode {
                Some(m) if m.is_fault() => {
                    v.fail(&format!("robot mode {m:?} ({}): clear the error first", m.code()));
                }
                Some(RobotMode::PowerOff) => {
                    v.warn("robot mode PowerOff (3): power the arm on (PowerOn(), about 10 s)");
                }
                Some(m) => v.ok(&format!("robot mode {m:?} ({})", m.code())),
                None => v.fail(&format!("RobotMode() answered {:?}", reply.values)),
            }
        }
        Err(LinkError::NotTcpMode) => {
            v.fail("the controller is not in TCP/IP mode: select it in DobotStudio Pro (or use --request-control)");
            return Ok(());
        }
        Err(e) => {
            v.fail(&format!("RobotMode(): {e}"));
            return Ok(());
        }
    }
    check_stray_terminator(config, addr, v)?;
    if request_control {
        match conn.request("RequestControl()") {
            Ok(r) if r.error_id == 0 => v.ok("RequestControl() granted: firmware V4.6 or newer"),
            Ok(r) if r.error_id == -10000 => {
                v.ok("RequestControl() unknown: firmware older than V4.6 (no control request needed)");
            }
            Ok(r) => v.warn(&format!(
                "RequestControl() refused: error {} ({}); the guide allows it only while the robot is disabled",
                r.error_id,
                error_text(r.error_id)
            )),
            Err(e) => v.fail(&format!("RequestControl(): {e}")),
        }
    } else {
        println!("SKIP RequestControl() (firmware generation): add --request-control to send it");
    }
    match conn.request("GetErrorID()") {
        Ok(r) if r.error_id == 0 => match ErrorIds::parse(&r.values.join(",")) {
            Ok(ids) if ids.is_empty() => v.ok("GetErrorID(): no alarms (seven lists)"),
            Ok(ids) => v.fail(&format!(
                "GetErrorID(): {ids}; look the ids up in alarm_controller.json / alarm_servo.json"
            )),
            Err(e) => v.fail(&format!("GetErrorID(): {e}")),
        },
        Ok(r) => v.fail(&format!(
            "GetErrorID(): error {} ({})",
            r.error_id,
            error_text(r.error_id)
        )),
        Err(e) => v.fail(&format!("GetErrorID(): {e}")),
    }
    Ok(())
}

/// Sends `RobotMode()` followed by `\r\n` on a fresh connection and counts the replies within 500 ms: a
/// second one means the controller answers a line end as a command of its own.
fn check_stray_terminator(
    config: &DobotConfig,
    addr: SocketAddr,
    v: &mut Verdict,
) -> Result<(), Box<dyn std::error::Error>> {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs_f64(config.connect_timeout_s))?;
    stream.write_all(b"RobotMode()\r\n")?;
    let deadline = Instant::now() + Duration::from_millis(500);
    let mut text = Vec::new();
    let mut chunk = [0u8; 512];
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        stream.set_read_timeout(Some(left.max(Duration::from_millis(1))))?;
        match stream.read(&mut chunk) {
            Ok(n) if n > 0 => text.extend_from_slice(&chunk[..n]),
            _ => break,
        }
    }
    let replies: Vec<String> = String::from_utf8_lossy(&text)
        .split_inclusive(';')
        .filter(|r| parse_reply(r).is_ok())
        .map(str::to_owned)
        .collect();
    match replies.len() {
        0 => v.warn("RobotMode() followed by \\r\\n got no reply in 500 ms: keep terminator = \"none\""),
        1 => v.ok("a trailing \\r\\n is ignored (terminator \"none\" is still what Dobot's clients send)"),
        _ => v.warn(&format!(
            "the controller answers a stray \\r\\n as a command ({replies:?}): keep terminator = \"none\""
        )),
    }
    Ok(())
}

fn check_feedback(config: &DobotConfig, v: &mut Verdict) -> Result<(), Box<dyn std::error::Error>> {
    let addr = resolve(&config.host, config.feedback_port)?;
    let mut stream =
        match TcpStream::connect_timeout(&addr, Duration::from_secs_f64(config.connect_timeout_s)) {
            Ok(s) => s,
            Err(e) => {
                v.fail(&format!("feedback {addr}: {e}"));
                return Ok(());
            }
        };
    stream.set_read_timeout(Some(Duration::from_millis(200)))?;
    let mut reader = FrameReader::default();
    let mut chunk = vec![0u8; 4 * PACKET_LEN];
    let deadline = Instant::now() + Duration::from_secs(2);
    let packet = loop {
        if let Some(result) = reader.next_packet() {
            match result {
                Ok(p) => break Some(p),
                Err(e) => v.warn(&format!("feedback packet rejected: {e}")),
            }
            continue;
        }
        if Instant::now() > deadline {
            break None;
        }
        match stream.read(&mut chunk) {
            Ok(0) => break None,
            Ok(n) => reader.push(&chunk[..n]),
            Err(_) => {}
        }
    };
    let Some(p) = packet else {
        v.fail(&format!(
            "feedback {addr}: no valid {PACKET_LEN}-byte packet in 2 s"
        ));
        return Ok(());
    };
    v.ok(&format!(
        "feedback {addr}: {PACKET_LEN}-byte packets with the test value"
    ));
    match p.robot_type {
        5 | 115 => v.ok(&format!("robot type {} (CR5)", p.robot_type)),
        other => v.warn(&format!("robot type {other}: not a CR5 (5 or 115)")),
    }
    let joints: Vec<String> = p.q_actual_deg.iter().map(|d| format!("{d:.2}")).collect();
    println!("joints_deg {}", joints.join(" "));
    let [x, y, z, rx, ry, rz] = p.tool_vector_actual;
    println!("tool_mm_deg {x:.1} {y:.1} {z:.1} {rx:.2} {ry:.2} {rz:.2}");
    match check_convention(&p, EulerConvention::ExtrinsicXyz) {
        ConventionCheck::Confirmed => v.ok("Euler angles fit the packet quaternion as fixed-axis X-Y-Z (extrinsic_xyz)"),
        ConventionCheck::Contradicted { fits } => v.warn(&format!("Euler angles fit {fits:?}, not extrinsic_xyz: set euler_convention or let the bridge detect it")),
        ConventionCheck::Inconclusive => v.warn("the pose cannot tell the Euler conventions apart (or no quaternion): check again with the tool turned about two axes"),
        ConventionCheck::NeitherFits => v.fail("the Euler angles and the quaternion disagree under both conventions"),
    }
    Ok(())
}

fn check_gripper_endpoint(
    host: &str,
    port: u16,
    gripper_test: bool,
    v: &mut Verdict,
) -> Result<(), Box<dyn std::error::Error>> {
    let addr = resolve(host, port)?;
    if let Err(e) = TcpStream::connect_timeout(&addr, Duration::from_secs(2)) {
        v.warn(&format!(
            "HTTP tool endpoint {addr}: {e} (needed only for a Modbus gripper)"
        ));
        return Ok(());
    }
    v.ok(&format!("HTTP tool endpoint {addr} accepts a connection"));
    if !gripper_test {
        println!("SKIP gripper frames: add --gripper-test to open and close the gripper");
        return Ok(());
    }
    let path = "/interface/toolDataExchange";
    for (name, value) in [("open", 1000u16), ("close", 0)] {
        let body = modbus_http_body(&modbus_write_register(1, 0x0103, value));
        match http_post_json(host, port, path, &body, Duration::from_secs(2)) {
            Ok(200) => v.ok(&format!("POST {path} ({name}) answered 200")),
            Ok(status) => v.fail(&format!("POST {path} ({name}) answered {status}")),
            Err(e) => v.fail(&format!("POST {path} ({name}): {e}")),
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    Ok(())
}

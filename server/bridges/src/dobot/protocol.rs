//! Dobot TCP command text: formatting requests and parsing `ErrorID,{values},Cmd;` replies.
//!
//! Both the bridge and the emulator use these helpers, so the emulator's replies are checked by the same parser
//! that reads the real controller. The shapes follow the Dobot V4 protocol document (V3 differences noted).

// Replies arrive from the network: slicing a `str` by byte index would panic on a multi-byte character.
#![deny(clippy::string_slice)]

use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// Which firmware generation the controller runs; sets the default motion port and command names.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Firmware {
    /// CR firmware 3.5.x: motion commands on their own port (30003), `ServoP` without optional parameters,
    /// `DOExecute`/`ToolDOExecute` for immediate outputs.
    V3,
    /// V4 firmware: every command, motion included, on the dashboard port (29999); `ServoP` takes `t`,
    /// `aheadtime`, `gain`; `DOInstant`/`ToolDOInstant`.
    #[default]
    V4,
}

impl Firmware {
    /// Default port for motion commands.
    pub fn default_motion_port(self) -> u16 {
        match self {
            Firmware::V3 => 30003,
            Firmware::V4 => 29999,
        }
    }
}

/// What ends a command on the wire. Dobot's own clients send none: TCP-IP-Python-V4 `dobot_api.py`
/// `DobotApi.send_data` sends the bare command text (66295e9), the ROS 2 driver sends `strlen(cmd)` bytes
/// (DOBOT_6Axis_ROS2_V4 `dobot_bringup_v4/src/command.cpp`, a1eabef), and the protocol guide (§2.1) says a
/// command ends with its right parenthesis. `lf`/`crlf` exist for controllers known to want one; a
/// controller that answers a stray terminator as a command of its own is caught by the echo check
/// ([`echo_matches`]), not trusted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Terminator {
    #[default]
    None,
    Lf,
    Crlf,
}

impl Terminator {
    pub fn as_str(self) -> &'static str {
        match self {
            Terminator::None => "",
            Terminator::Lf => "\n",
            Terminator::Crlf => "\r\n",
        }
    }
}

/// A parsed controller reply.
#[derive(Clone, Debug, PartialEq)]
pub struct Reply {
    /// 0 on success; see [`error_text`].
    pub error_id: i32,
    /// Comma-separated values between the braces, trimmed (empty for `{}`).
    pub values: Vec<String>,
    /// The echoed command text after the braces (without the trailing `;`).
    pub echo: String,
}

impl Reply {
    /// The values parsed as numbers.
    pub fn numbers(&self) -> Result<Vec<f64>, ReplyError> {
        self.values
            .iter()
            .map(|v| {
                v.parse::<f64>()
                    .map_err(|_| ReplyError::Malformed(format!("value {v:?} is not a number")))
            })
            .collect()
    }
}

/// Why a reply could not be parsed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ReplyError {
    #[error("malformed reply: {0}")]
    Malformed(String),
}

/// Parses one reply such as `0,{-473.0,-141.0},GetPose();`. The trailing `;` and surrounding whitespace are
/// optional so the text read up to the terminator can be passed as is.
pub fn parse_reply(text: &str) -> Result<Reply, ReplyError> {
    let body = text.trim();
    let body = body.strip_suffix(';').unwrap_or(body);
    let (code, rest) = body
        .split_once(',')
        .ok_or_else(|| ReplyError::Malformed(format!("no ',' after the error id in {text:?}")))?;
    let error_id = code
        .trim()
        .parse::<i32>()
        .map_err(|_| ReplyError::Malformed(format!("error id {:?} is not an integer", code.trim())))?;
    let rest = rest.trim_start();
    let inner = rest
        .strip_prefix('{')
        .ok_or_else(|| ReplyError::Malformed(format!("no '{{' starting the values in {text:?}")))?;
    // Values may themselves contain braces (vectors); find the brace that closes the first one.
    let mut depth = 1usize;
    let mut close = None;
    for (i, c) in inner.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    close = Some(i);
                    break;
                }
            }
            _ => {}
        }
    }
    let close = close.ok_or_else(|| ReplyError::Malformed(format!("unbalanced braces in {text:?}")))?;
    // `close` comes from `char_indices`, so both cuts are on char boundaries; `get` keeps that checked.
    let values_text = inner.get(..close).unwrap_or_default().trim();
    let values = if values_text.is_empty() {
        Vec::new()
    } else {
        split_top_level(values_text)
            .into_iter()
            .map(|v| v.trim().to_owned())
            .collect()
    };
    let echo = inner
        .get(close + 1..)
        .unwrap_or_default()
        .trim_start_matches(',')
        .trim()
        .to_owned();
    Ok(Reply {
        error_id,
        values,
        echo,
    })
}

/// Splits on commas that are not inside braces, brackets or parentheses (`GetErrorID` answers nested
/// `[[..],[..]]` lists).
pub fn split_top_level(text: &str) -> Vec<&str> {
    let mut parts = Vec::new();
    let mut depth = 0i32;
    let mut start = 0;
    for (i, c) in text.char_indices() {
        match c {
            '{' | '(' | '[' => depth += 1,
            '}' | ')' | ']' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(text.get(start..i).unwrap_or_default());
                start = i + 1;
            }
            _ => {}
        }
    }
    parts.push(text.get(start..).unwrap_or_default());
    parts
}

/// True if `echo`, the command text a reply repeats after its values, is the reply to `sent`.
///
/// The guide (§2.2.1) says a reply ends with "the original command"; its own example answers `GetErrorID()`
/// with `GetErrorId()` (§3.40), so names compare without case. Whitespace is ignored and numbers compare by
/// value, so a controller that reprints `100.000` as `100` still matches, while a reply to any other
/// command (a different name, different parameters, or the empty echo of a stray terminator) does not.
pub fn echo_matches(sent: &str, echo: &str) -> bool {
    let a = echo_tokens(sent);
    let b = echo_tokens(echo);
    a.len() == b.len()
        && a.iter().zip(&b).all(|(x, y)| match (x, y) {
            (EchoToken::Number(x), EchoToken::Number(y)) => (x - y).abs() <= 1e-9 * x.abs().max(1.0),
            (EchoToken::Text(x), EchoToken::Text(y)) => x.eq_ignore_ascii_case(y),
            _ => false,
        })
}

#[derive(Debug)]
enum EchoToken {
    Number(f64),
    Text(String),
}

/// Splits a command into its fields (numbers where they parse as one) and the separators between them,
/// dropping whitespace.
fn echo_tokens(text: &str) -> Vec<EchoToken> {
    let compact: String = text.chars().filter(|c| !c.is_whitespace()).collect();
    let mut tokens = Vec::new();
    let mut field = String::new();
    let flush = |field: &mut String, tokens: &mut Vec<EchoToken>| {
        if !field.is_empty() {
            tokens.push(match field.parse::<f64>() {
                Ok(v) => EchoToken::Number(v),
                Err(_) => EchoToken::Text(std::mem::take(field)),
            });
            field.clear();
        }
    };
    for c in compact.chars() {
        if "(),{}=[]".contains(c) {
            flush(&mut field, &mut tokens);
            tokens.push(EchoToken::Text(c.to_string()));
        } else {
            field.push(c);
        }
    }
    flush(&mut field, &mut tokens);
    tokens
}

/// `GetErrorID()`'s answer: the controller's (and motion planner's) alarm ids, then one list per servo, J1
/// first. Guide §3.40: `ErrorID,{[[id,...,id],[id],[id],[id],[id],[id],[id]]},GetErrorID();`, the ids
/// explained by `alarm_controller.json` and `alarm_servo.json` (shipped with TCP-IP-Python-V4 as
/// `files/alarmController.json`, `files/alarmServo.json`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ErrorIds {
    pub controller: Vec<i64>,
    pub servos: [Vec<i64>; 6],
}

impl ErrorIds {
    /// Parses the reply's value text (`[[..],[..],...]`, seven lists).
    pub fn parse(values: &str) -> Result<Self, ReplyError> {
        let lists: Vec<Vec<i64>> = serde_json::from_str(values.trim())
            .map_err(|e| ReplyError::Malformed(format!("GetErrorID values {values:?}: {e}")))?;
        let [controller, j1, j2, j3, j4, j5, j6]: [Vec<i64>; 7] = lists.try_into().map_err(|l: Vec<_>| {
            ReplyError::Malformed(format!("GetErrorID answered {} lists, not 7", l.len()))
        })?;
        Ok(Self {
            controller,
            servos: [j1, j2, j3, j4, j5, j6],
        })
    }

    pub fn is_empty(&self) -> bool {
        self.controller.is_empty() && self.servos.iter().all(Vec::is_empty)
    }

    /// The wire form, `[[..],[..],...]`.
    pub fn to_values(&self) -> String {
        let list = |ids: &[i64]| {
            format!(
                "[{}]",
                ids.iter().map(i64::to_string).collect::<Vec<_>>().join(",")
            )
        };
        let mut parts = vec![list(&self.controller)];
        parts.extend(self.servos.iter().map(|s| list(s)));
        format!("[{}]", parts.join(","))
    }
}

impl std::fmt::Display for ErrorIds {
    /// "controller alarm 22; J3 servo alarm 4368" (or "no alarm ids").
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut parts = Vec::new();
        if !self.controller.is_empty() {
            parts.push(format!("controller alarm {}", join_ids(&self.controller)));
        }
        for (j, ids) in self.servos.iter().enumerate() {
            if !ids.is_empty() {
                parts.push(format!("J{} servo alarm {}", j + 1, join_ids(ids)));
            }
        }
        if parts.is_empty() {
            f.write_str("no alarm ids")
        } else {
            f.write_str(&parts.join("; "))
        }
    }
}

fn join_ids(ids: &[i64]) -> String {
    ids.iter().map(i64::to_string).collect::<Vec<_>>().join(",")
}

/// Meaning of a controller error id (V4 document §5).
pub fn error_text(code: i32) -> &'static str {
    match code {
        0 => "ok",
        -1 => "command failed",
        -2 => "robot is in an error state",
        -3 => "emergency stop pressed",
        -4 => "robot is powered off",
        -5 => "a script is running",
        -6 => "MoveJog axis does not match the motion type",
        -7 => "script paused",
        -8 => "licence expired",
        -10000 => "unknown command",
        -20000 => "wrong number of parameters",
        -30009..=-30001 => "type error in a required parameter",
        -40009..=-40001 => "range error in a required parameter",
        -50009..=-50001 => "type error in an optional parameter",
        -60009..=-60001 => "range error in an optional parameter",
        _ => "unknown error id",
    }
}

/// Robot mode as reported by `RobotMode()` and the feedback packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RobotMode {
    Init,
    BrakeOpen,
    PowerOff,
    Disabled,
    Enabled,
    Backdrive,
    Running,
    SingleMove,
    Error,
    Pause,
    Collision,
    Unknown(u64),
}

impl RobotMode {
    pub fn from_code(code: u64) -> Self {
        match code {
            1 => Self::Init,
            2 => Self::BrakeOpen,
            3 => Self::PowerOff,
            4 => Self::Disabled,
            5 => Self::Enabled,
            6 => Self::Backdrive,
            7 => Self::Running,
            8 => Self::SingleMove,
            9 => Self::Error,
            10 => Self::Pause,
            11 => Self::Collision,
            other => Self::Unknown(other),
        }
    }

    pub fn code(self) -> u64 {
        match self {
            Self::Init => 1,
            Self::BrakeOpen => 2,
            Self::PowerOff => 3,
            Self::Disabled => 4,
            Self::Enabled => 5,
            Self::Backdrive => 6,
            Self::Running => 7,
            Self::SingleMove => 8,
            Self::Error => 9,
            Self::Pause => 10,
            Self::Collision => 11,
            Self::Unknown(c) => c,
        }
    }

    /// True when the robot accepts motion commands.
    pub fn accepts_motion(self) -> bool {
        matches!(self, Self::Enabled | Self::Running)
    }

    /// True for modes that need operator action (error, collision).
    pub fn is_fault(self) -> bool {
        matches!(self, Self::Error | Self::Collision)
    }
}

/// Optional `ServoP` tuning (V4 only).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ServoParams {
    /// Time to reach the point, seconds ([0.004, 3600] since V4.6.0).
    pub t_s: f64,
    /// Look-ahead (D-like), 20..100.
    pub aheadtime: f64,
    /// Proportional gain, 200..1000.
    pub gain: f64,
}

/// `ServoP(x,y,z,rx,ry,rz[,t=..,aheadtime=..,gain=..])` with the pose in millimetres and degrees.
pub fn servo_p(pose_mm_deg: &[f64; 6], params: Option<ServoParams>) -> String {
    let mut s = String::with_capacity(96);
    let [x, y, z, rx, ry, rz] = *pose_mm_deg;
    let _ = write!(s, "ServoP({x:.3},{y:.3},{z:.3},{rx:.4},{ry:.4},{rz:.4}");
    if let Some(p) = params {
        let _ = write!(s, ",t={},aheadtime={},gain={}", p.t_s, p.aheadtime, p.gain);
    }
    s.push(')');
    s
}

/// `ServoJ(J1,J2,J3,J4,J5,J6[,t=..,aheadtime=..,gain=..])` with the joints in degrees: the same streaming
/// command as `ServoP` in joint space, with the same optional parameters (Dobot V4 TCP protocol, `ServoJ`).
pub fn servo_j(joints_deg: &[f64; 6], params: Option<ServoParams>) -> String {
    let mut s = String::with_capacity(96);
    let [j1, j2, j3, j4, j5, j6] = *joints_deg;
    let _ = write!(s, "ServoJ({j1:.4},{j2:.4},{j3:.4},{j4:.4},{j5:.4},{j6:.4}");
    if let Some(p) = params {
        let _ = write!(s, ",t={},aheadtime={},gain={}", p.t_s, p.aheadtime, p.gain);
    }
    s.push(')');
    s
}

/// Splits a command such as `ServoP(1,2,t=0.1)` into its name and parameters. Returns `None` if it has no
/// parentheses.
pub fn split_command(text: &str) -> Option<(&str, Vec<&str>)> {
    let text = text.trim();
    let open = text.find('(')?;
    let close = text.rfind(')')?;
    if close < open {
        return None;
    }
    let name = text.get(..open)?.trim();
    let inner = text.get(open + 1..close)?.trim();
    let params = if inner.is_empty() {
        Vec::new()
    } else {
        split_top_level(inner).into_iter().map(str::trim).collect()
    };
    Some((name, params))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_documented_replies() {
        let r = parse_reply("0,{1},MovL(pose={-500,100,200,150,0,90});").unwrap();
        assert_eq!(r.error_id, 0);
        assert_eq!(r.values, vec!["1"]);
        assert_eq!(r.echo, "MovL(pose={-500,100,200,150,0,90})");

        let r = parse_reply("-10000,{},Mov(...);").unwrap();
        assert_eq!(r.error_id, -10000);
        assert!(r.values.is_empty());
        assert_eq!(error_text(r.error_id), "unknown command");

        let r =
            parse_reply("0,{-473.0,-141.0,469.0,-180.0,0.0,90.0},GetPose(user = 1, tool = 0);\r\n").unwrap();
        assert_eq!(
            r.numbers().unwrap(),
            vec![-473.0, -141.0, 469.0, -180.0, 0.0, 90.0]
        );
    }

    #[test]
    fn rejects_malformed_replies() {
        for bad in ["", "garbage", "x,{},A();", "0,1,A();", "0,{1,2,A();"] {
            assert!(parse_reply(bad).is_err(), "{bad:?} should not parse");
        }
        let r = parse_reply("0,{a},GetPose();").unwrap();
        assert!(r.numbers().is_err());
    }

    #[test]
    fn formats_servo_p_for_both_firmwares() {
        let pose = [100.0, -20.5, 300.0, 180.0, 0.0, -90.0];
        assert_eq!(
            servo_p(&pose, None),
            "ServoP(100.000,-20.500,300.000,180.0000,0.0000,-90.0000)"
        );
        let s = servo_p(
            &pose,
            Some(ServoParams {
                t_s: 0.008,
                aheadtime: 50.0,
                gain: 500.0,
            }),
        );
        assert!(s.ends_with(",t=0.008,aheadtime=50,gain=500)"), "{s}");
        let (name, params) = split_command(&s).unwrap();
        assert_eq!(name, "ServoP");
        assert_eq!(params.len(), 9);
    }

    #[test]
    fn echoes_match_their_own_command_only() {
        // The guide's own example answers GetErrorID() with GetErrorId().
        assert!(echo_matches("GetErrorID()", "GetErrorId()"));
        assert!(echo_matches(
            "GetPose(user=1,tool=0)",
            "GetPose(user = 1, tool = 0)"
        ));
        assert!(echo_matches(
            "ServoP(100.000,-20.500,t=0.05)",
            "ServoP(100,-20.5,t=0.050)"
        ));
        assert!(echo_matches(
            "MovL(pose={-500,100,200,150,0,90})",
            "MovL(pose={-500,100,200,150,0,90})"
        ));
        for (sent, echo) in [
            ("EnableRobot()", ""),
            ("SpeedFactor(30)", "ClearError()"),
            ("ServoP(1,2,3,4,5,6)", "ServoP(1,2,3,4,5,7)"),
            ("ServoP(1,2,3,4,5,6)", "ServoP(1,2,3,4,5)"),
            ("DO(1,1)", "DO(11)"),
            ("MovJ(joint={1,2,3,4,5,6})", "MovJ(pose={1,2,3,4,5,6})"),
        ] {
            assert!(!echo_matches(sent, echo), "{sent} answered by {echo:?}");
        }
    }

    #[test]
    fn get_error_id_has_seven_lists() {
        let r = parse_reply("0,{[[],[],[],[],[],[],[]]},GetErrorId();").unwrap();
        assert_eq!(r.values.len(), 1, "the nested lists are one value");
        let ids = ErrorIds::parse(&r.values[0]).unwrap();
        assert!(ids.is_empty());
        assert_eq!(ids.to_string(), "no alarm ids");
        let ids = ErrorIds::parse("[[22, 23],[],[],[4368],[],[],[]]").unwrap();
        assert_eq!(ids.controller, vec![22, 23]);
        assert_eq!(ids.servos[2], vec![4368]);
        assert_eq!(ids.to_string(), "controller alarm 22,23; J3 servo alarm 4368");
        assert_eq!(ErrorIds::parse(&ids.to_values()).unwrap(), ids);
        for bad in ["[[22]]", "[[],[],[],[],[],[],[],[]]", "22", "[[x]]"] {
            assert!(ErrorIds::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn formats_servo_j_in_degrees() {
        let joints = [10.0, -20.5, 90.0, 0.0, -45.25, 180.0];
        assert_eq!(
            servo_j(&joints, None),
            "ServoJ(10.0000,-20.5000,90.0000,0.0000,-45.2500,180.0000)"
        );
        let s = servo_j(
            &joints,
            Some(ServoParams {
                t_s: 0.02,
                aheadtime: 50.0,
                gain: 500.0,
            }),
        );
        assert!(s.ends_with(",t=0.02,aheadtime=50,gain=500)"), "{s}");
        let (name, params) = split_command(&s).unwrap();
        assert_eq!(name, "ServoJ");
        assert_eq!(params.len(), 9);
    }

    #[test]
    fn error_ranges_are_named() {
        assert_eq!(error_text(-40003), "range error in a required parameter");
        assert_eq!(error_text(-60001), "range error in an optional parameter");
        assert_eq!(error_text(-2), "robot is in an error state");
        assert_eq!(error_text(12345), "unknown error id");
    }
}

//! Dobot gripper outputs: a controller or tool digital output, or a Modbus-RTU register write tunnelled over the
//! controller's HTTP tool-data endpoint (the route Phone2Act's CR5 uses for a DH-Robotics-style gripper).

use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::time::Duration;

/// How the gripper is driven.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum GripperOutput {
    /// No gripper: the gripper target is ignored and reported back as commanded.
    None,
    /// A controller digital output (`DOInstant` on V4, `DOExecute` on V3).
    Do {
        index: u32,
        /// Output level that closes the gripper.
        #[serde(default = "default_true")]
        closed_high: bool,
    },
    /// A tool (end-effector) digital output (`ToolDOInstant` / `ToolDOExecute`).
    ToolDo {
        index: u32,
        #[serde(default = "default_true")]
        closed_high: bool,
    },
    /// Modbus "write single register" frames posted as JSON to `http://host:port/path`.
    ModbusHttp {
        #[serde(default = "default_http_port")]
        port: u16,
        #[serde(default = "default_http_path")]
        path: String,
        #[serde(default = "default_slave")]
        slave: u8,
        #[serde(default = "default_register")]
        register: u16,
        /// Register value for fully open (1000 on DH-Robotics grippers: position in per mille).
        #[serde(default = "default_open_value")]
        open_value: u16,
        #[serde(default)]
        closed_value: u16,
    },
}

impl Default for GripperOutput {
    fn default() -> Self {
        GripperOutput::ToolDo {
            index: 1,
            closed_high: true,
        }
    }
}

fn default_true() -> bool {
    true
}
fn default_http_port() -> u16 {
    22000
}
fn default_http_path() -> String {
    "/interface/toolDataExchange".to_owned()
}
fn default_slave() -> u8 {
    1
}
fn default_register() -> u16 {
    0x0103
}
fn default_open_value() -> u16 {
    1000
}

/// Modbus CRC-16 (polynomial 0xA001, initial 0xFFFF).
pub fn modbus_crc16(bytes: &[u8]) -> u16 {
    let mut crc = 0xFFFFu16;
    for &b in bytes {
        crc ^= u16::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc
}

/// A Modbus-RTU "write single register" (function 6) frame with its CRC, low byte first.
pub fn modbus_write_register(slave: u8, register: u16, value: u16) -> [u8; 8] {
    let [rh, rl] = register.to_be_bytes();
    let [vh, vl] = value.to_be_bytes();
    let head = [slave, 6, rh, rl, vh, vl];
    let [cl, ch] = modbus_crc16(&head).to_le_bytes();
    [slave, 6, rh, rl, vh, vl, cl, ch]
}

/// Checks a frame's CRC and returns `(slave, register, value)` for a function-6 frame.
pub fn parse_modbus_write_register(frame: &[u8]) -> Option<(u8, u16, u16)> {
    if frame.len() != 8 || frame[1] != 6 {
        return None;
    }
    let crc = u16::from_le_bytes([frame[6], frame[7]]);
    if modbus_crc16(&frame[..6]) != crc {
        return None;
    }
    Some((
        frame[0],
        u16::from_be_bytes([frame[2], frame[3]]),
        u16::from_be_bytes([frame[4], frame[5]]),
    ))
}

/// JSON body the endpoint expects: `{"value":[b0,...,b7]}`.
pub fn modbus_http_body(frame: &[u8]) -> String {
    let values: Vec<String> = frame.iter().map(u8::to_string).collect();
    format!("{{\"value\":[{}]}}", values.join(","))
}

/// Posts a JSON body and returns the HTTP status code. A one-shot HTTP/1.1 request with `Connection: close`:
/// the endpoint is called only when the gripper target changes, so a client library would add nothing.
pub fn http_post_json(
    host: &str,
    port: u16,
    path: &str,
    body: &str,
    timeout: Duration,
) -> std::io::Result<u16> {
    let addr: SocketAddr = (host, port)
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::NotFound, format!("cannot resolve {host}")))?;
    let mut stream = TcpStream::connect_timeout(&addr, timeout)?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    let request = format!(
        "POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes())?;
    let mut response = Vec::with_capacity(256);
    let mut chunk = [0u8; 256];
    // Only the status line is needed; stop once it is complete.
    while !response.windows(2).any(|w| w == b"\r\n") {
        let n = stream.read(&mut chunk)?;
        if n == 0 || response.len() > 8192 {
            break;
        }
        response.extend_from_slice(&chunk[..n]);
    }
    let text = String::from_utf8_lossy(&response);
    let status_line = text.lines().next().unwrap_or_default();
    status_line
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse::<u16>().ok())
        .ok_or_else(|| {
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("bad HTTP status {status_line:?}"),
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_match_phone2act_gripper_bytes() {
        // The exact frames Phone2Act posts to close and open its CR5 gripper.
        assert_eq!(modbus_write_register(1, 0x0103, 0), [1, 6, 1, 3, 0, 0, 120, 54]);
        assert_eq!(
            modbus_write_register(1, 0x0103, 1000),
            [1, 6, 1, 3, 3, 232, 120, 136]
        );
        assert_eq!(
            modbus_http_body(&[1, 6, 1, 3, 0, 0, 120, 54]),
            "{\"value\":[1,6,1,3,0,0,120,54]}"
        );
    }

    #[test]
    fn parse_checks_the_crc() {
        let f = modbus_write_register(1, 0x0103, 500);
        assert_eq!(parse_modbus_write_register(&f), Some((1, 0x0103, 500)));
        let mut bad = f;
        bad[5] ^= 1;
        assert_eq!(parse_modbus_write_register(&bad), None);
        assert_eq!(parse_modbus_write_register(&f[..7]), None);
    }

    #[test]
    fn gripper_config_parses_every_kind() {
        let g: GripperOutput = serde_json::from_str(r#"{"kind":"modbus_http"}"#).unwrap();
        assert!(matches!(
            g,
            GripperOutput::ModbusHttp {
                port: 22000,
                register: 0x0103,
                open_value: 1000,
                ..
            }
        ));
        let g: GripperOutput = serde_json::from_str(r#"{"kind":"do","index":3}"#).unwrap();
        assert_eq!(
            g,
            GripperOutput::Do {
                index: 3,
                closed_high: true
            }
        );
        assert!(serde_json::from_str::<GripperOutput>(r#"{"kind":"do","index":3,"bogus":1}"#).is_err());
    }
}

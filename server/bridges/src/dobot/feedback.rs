//! The 1440-byte real-time feedback packet (ports 30004/30005/30006), its validation and stream framing, and the
//! controller's Euler-angle convention.
//!
//! Offsets follow the packed little-endian layout in the protocol notes (V3 and V4 agree on every field used
//! here). A TCP stream has no message boundaries, so [`FrameReader`] re-synchronises on the size and test-value
//! fields instead of trusting that every read starts a packet.

use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Size of one packet; the first `u16` must say so.
pub const PACKET_LEN: usize = 1440;
/// Fixed value at offset 48 that tells a real packet from misaligned bytes.
pub const TEST_VALUE: u64 = 0x0123_4567_89AB_CDEF;

const OFF_DIGITAL_INPUTS: usize = 8;
const OFF_DIGITAL_OUTPUTS: usize = 16;
const OFF_ROBOT_MODE: usize = 24;
const OFF_TIMESTAMP: usize = 32;
const OFF_TEST_VALUE: usize = 48;
const OFF_SPEED_SCALING: usize = 64;
const OFF_Q_TARGET: usize = 192;
const OFF_Q_ACTUAL: usize = 432;
const OFF_TOOL_VECTOR_ACTUAL: usize = 624;
const OFF_TOOL_VECTOR_TARGET: usize = 768;
const OFF_ENABLE_STATUS: usize = 1026;
const OFF_ERROR_STATUS: usize = 1029;
const OFF_ROBOT_TYPE: usize = 1031;
const OFF_COLLISION_STATE: usize = 1038;
const OFF_CURRENT_COMMAND_ID: usize = 1112;
const OFF_ACTUAL_QUATERNION: usize = 1384;

/// The fields of a feedback packet that the bridge uses.
#[derive(Clone, Debug, PartialEq)]
pub struct FeedbackPacket {
    pub digital_inputs: u64,
    pub digital_outputs: u64,
    /// [`super::protocol::RobotMode`] code.
    pub robot_mode: u64,
    /// Controller Unix time, milliseconds.
    pub timestamp_ms: u64,
    pub speed_scaling: f64,
    pub q_target_deg: [f64; 6],
    pub q_actual_deg: [f64; 6],
    /// x, y, z in millimetres, rx, ry, rz in degrees.
    pub tool_vector_actual: [f64; 6],
    pub tool_vector_target: [f64; 6],
    pub enable_status: u8,
    pub error_status: u8,
    /// 5 = CR5, 115 = CR5A.
    pub robot_type: u8,
    pub collision_state: u8,
    pub current_command_id: u64,
    /// `[qw, qx, qy, qz]` of the tool; all zero on firmware that does not fill it.
    pub actual_quaternion_wxyz: [f64; 4],
}

impl Default for FeedbackPacket {
    fn default() -> Self {
        Self {
            digital_inputs: 0,
            digital_outputs: 0,
            robot_mode: 4,
            timestamp_ms: 0,
            speed_scaling: 1.0,
            q_target_deg: [0.0; 6],
            q_actual_deg: [0.0; 6],
            tool_vector_actual: [0.0; 6],
            tool_vector_target: [0.0; 6],
            enable_status: 0,
            error_status: 0,
            robot_type: 5,
            collision_state: 0,
            current_command_id: 0,
            actual_quaternion_wxyz: [1.0, 0.0, 0.0, 0.0],
        }
    }
}

/// Why a packet was rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PacketError {
    #[error("feedback packet too short: {len} of {PACKET_LEN} bytes")]
    Short { len: usize },
    #[error("feedback packet declares size {declared}, expected {PACKET_LEN}")]
    BadSize { declared: u16 },
    #[error("feedback packet test value {found:#018x}, expected {TEST_VALUE:#018x}")]
    BadTestValue { found: u64 },
    #[error("feedback packet field {field} is not finite")]
    NonFinite { field: &'static str },
}

fn u64_at(b: &[u8], off: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[off..off + 8]);
    u64::from_le_bytes(a)
}

fn f64_at(b: &[u8], off: usize) -> f64 {
    f64::from_bits(u64_at(b, off))
}

fn f64s_at<const N: usize>(b: &[u8], off: usize) -> [f64; N] {
    std::array::from_fn(|i| f64_at(b, off + 8 * i))
}

fn put_u64(b: &mut [u8], off: usize, v: u64) {
    b[off..off + 8].copy_from_slice(&v.to_le_bytes());
}

fn put_f64s(b: &mut [u8], off: usize, v: &[f64]) {
    for (i, x) in v.iter().enumerate() {
        put_u64(b, off + 8 * i, x.to_bits());
    }
}

/// Checks the size and test-value fields of the first [`PACKET_LEN`] bytes.
pub fn validate_header(bytes: &[u8]) -> Result<(), PacketError> {
    if bytes.len() < PACKET_LEN {
        return Err(PacketError::Short { len: bytes.len() });
    }
    let declared = u16::from_le_bytes([bytes[0], bytes[1]]);
    if usize::from(declared) != PACKET_LEN {
        return Err(PacketError::BadSize { declared });
    }
    let found = u64_at(bytes, OFF_TEST_VALUE);
    if found != TEST_VALUE {
        return Err(PacketError::BadTestValue { found });
    }
    Ok(())
}

impl FeedbackPacket {
    /// Parses and validates one packet (exactly the first [`PACKET_LEN`] bytes are read).
    pub fn parse(bytes: &[u8]) -> Result<Self, PacketError> {
        validate_header(bytes)?;
        let p = Self {
            digital_inputs: u64_at(bytes, OFF_DIGITAL_INPUTS),
            digital_outputs: u64_at(bytes, OFF_DIGITAL_OUTPUTS),
            robot_mode: u64_at(bytes, OFF_ROBOT_MODE),
            timestamp_ms: u64_at(bytes, OFF_TIMESTAMP),
            speed_scaling: f64_at(bytes, OFF_SPEED_SCALING),
            q_target_deg: f64s_at(bytes, OFF_Q_TARGET),
            q_actual_deg: f64s_at(bytes, OFF_Q_ACTUAL),
            tool_vector_actual: f64s_at(bytes, OFF_TOOL_VECTOR_ACTUAL),
            tool_vector_target: f64s_at(bytes, OFF_TOOL_VECTOR_TARGET),
            enable_status: bytes[OFF_ENABLE_STATUS],
            error_status: bytes[OFF_ERROR_STATUS],
            robot_type: bytes[OFF_ROBOT_TYPE],
            collision_state: bytes[OFF_COLLISION_STATE],
            current_command_id: u64_at(bytes, OFF_CURRENT_COMMAND_ID),
            actual_quaternion_wxyz: f64s_at(bytes, OFF_ACTUAL_QUATERNION),
        };
        if !p.q_actual_deg.iter().all(|v| v.is_finite()) {
            return Err(PacketError::NonFinite { field: "QActual" });
        }
        if !p.tool_vector_actual.iter().all(|v| v.is_finite()) {
            return Err(PacketError::NonFinite {
                field: "ToolVectorActual",
            });
        }
        if !p.actual_quaternion_wxyz.iter().all(|v| v.is_finite()) {
            return Err(PacketError::NonFinite {
                field: "ActualQuaternion",
            });
        }
        Ok(p)
    }

    /// Serialises the packet as the controller does (used by the emulator).
    pub fn encode(&self) -> Vec<u8> {
        let mut b = vec![0u8; PACKET_LEN];
        b[0..2].copy_from_slice(&(PACKET_LEN as u16).to_le_bytes());
        put_u64(&mut b, OFF_DIGITAL_INPUTS, self.digital_inputs);
        put_u64(&mut b, OFF_DIGITAL_OUTPUTS, self.digital_outputs);
        put_u64(&mut b, OFF_ROBOT_MODE, self.robot_mode);
        put_u64(&mut b, OFF_TIMESTAMP, self.timestamp_ms);
        put_u64(&mut b, OFF_TEST_VALUE, TEST_VALUE);
        put_f64s(&mut b, OFF_SPEED_SCALING, &[self.speed_scaling]);
        put_f64s(&mut b, OFF_Q_TARGET, &self.q_target_deg);
        put_f64s(&mut b, OFF_Q_ACTUAL, &self.q_actual_deg);
        put_f64s(&mut b, OFF_TOOL_VECTOR_ACTUAL, &self.tool_vector_actual);
        put_f64s(&mut b, OFF_TOOL_VECTOR_TARGET, &self.tool_vector_target);
        b[OFF_ENABLE_STATUS] = self.enable_status;
        b[OFF_ERROR_STATUS] = self.error_status;
        b[OFF_ROBOT_TYPE] = self.robot_type;
        b[OFF_COLLISION_STATE] = self.collision_state;
        put_u64(&mut b, OFF_CURRENT_COMMAND_ID, self.current_command_id);
        put_f64s(&mut b, OFF_ACTUAL_QUATERNION, &self.actual_quaternion_wxyz);
        b
    }
}

/// Cuts a TCP byte stream into packets. Bytes that do not start a valid packet are skipped up to the next
/// plausible start, and each skip is reported once, so a corrupt or truncated packet costs one packet, not
/// the stream.
#[derive(Debug, Default)]
pub struct FrameReader {
    buffer: Vec<u8>,
}

impl FrameReader {
    /// Bytes waiting for the rest of their packet.
    pub fn pending(&self) -> usize {
        self.buffer.len()
    }

    pub fn push(&mut self, bytes: &[u8]) {
        self.buffer.extend_from_slice(bytes);
    }

    /// The next result: a packet, a rejection (after which the reader has skipped ahead), or `None` when more
    /// bytes are needed.
    pub fn next_packet(&mut self) -> Option<Result<FeedbackPacket, PacketError>> {
        if self.buffer.len() < PACKET_LEN {
            return None;
        }
        match validate_header(&self.buffer) {
            Ok(()) => {
                let result = FeedbackPacket::parse(&self.buffer[..PACKET_LEN]);
                self.buffer.drain(..PACKET_LEN);
                Some(result)
            }
            Err(error) => {
                // Skip to the next offset whose size and test value both look right; if none is in the buffer
                // yet, keep only a tail that could still be the start of one.
                let next = (1..self.buffer.len()).find(|&i| self.looks_like_start(i));
                let cut = next.unwrap_or_else(|| self.buffer.len().saturating_sub(OFF_TEST_VALUE + 8));
                self.buffer.drain(..cut);
                Some(Err(error))
            }
        }
    }

    fn looks_like_start(&self, i: usize) -> bool {
        let b = &self.buffer[i..];
        if b.len() < 2 || usize::from(u16::from_le_bytes([b[0], b[1]])) != PACKET_LEN {
            return false;
        }
        // Without the test value in view yet, a matching size is enough to wait for more bytes.
        b.len() < OFF_TEST_VALUE + 8 || u64_at(b, OFF_TEST_VALUE) == TEST_VALUE
    }
}

/// How the controller's `rx, ry, rz` angles compose into a rotation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EulerConvention {
    /// Fixed axes X, Y, Z: `R = Rz(rz)·Ry(ry)·Rx(rx)` (what Phone2Act's working CR5 bridge assumes).
    #[default]
    ExtrinsicXyz,
    /// Moving axes X, Y', Z'': `R = Rx(rx)·Ry(ry)·Rz(rz)`.
    IntrinsicXyz,
}

impl EulerConvention {
    /// Rotation from angles in degrees.
    pub fn to_rotation(self, rx_deg: f64, ry_deg: f64, rz_deg: f64) -> UnitQuaternion<f64> {
        let (rx, ry, rz) = (rx_deg.to_radians(), ry_deg.to_radians(), rz_deg.to_radians());
        match self {
            EulerConvention::ExtrinsicXyz => UnitQuaternion::from_euler_angles(rx, ry, rz),
            EulerConvention::IntrinsicXyz => {
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), rx)
                    * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), ry)
                    * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rz)
            }
        }
    }

    /// Angles in degrees `[rx, ry, rz]` for a rotation.
    pub fn to_angles_deg(self, rotation: &UnitQuaternion<f64>) -> [f64; 3] {
        match self {
            EulerConvention::ExtrinsicXyz => {
                let (rx, ry, rz) = rotation.euler_angles();
                [rx.to_degrees(), ry.to_degrees(), rz.to_degrees()]
            }
            EulerConvention::IntrinsicXyz => {
                let m: Rotation3<f64> = rotation.to_rotation_matrix();
                let m = m.matrix();
                let ry = m[(0, 2)].clamp(-1.0, 1.0).asin();
                let rx = (-m[(1, 2)]).atan2(m[(2, 2)]);
                let rz = (-m[(0, 1)]).atan2(m[(0, 0)]);
                [rx.to_degrees(), ry.to_degrees(), rz.to_degrees()]
            }
        }
    }
}

/// Outcome of comparing a packet's Euler angles with its quaternion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ConventionCheck {
    /// The configured convention reproduces the quaternion.
    Confirmed,
    /// The other convention fits and the configured one does not.
    Contradicted { fits: EulerConvention },
    /// The quaternion is missing (all zero) or the pose is symmetric enough that both conventions fit.
    Inconclusive,
    /// Neither convention fits: the packet is inconsistent.
    NeitherFits,
}

/// Angle (radians) within which a convention is taken to reproduce the packet's quaternion.
pub const CONVENTION_TOLERANCE_RAD: f64 = 1e-3;

/// Compares the tool pose angles with the quaternion in the same packet.
pub fn check_convention(packet: &FeedbackPacket, configured: EulerConvention) -> ConventionCheck {
    let [w, x, y, z] = packet.actual_quaternion_wxyz;
    let norm = (w * w + x * x + y * y + z * z).sqrt();
    if !(0.5..=1.5).contains(&norm) {
        return ConventionCheck::Inconclusive;
    }
    let measured = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
    let [_, _, _, rx, ry, rz] = packet.tool_vector_actual;
    let fits = |c: EulerConvention| c.to_rotation(rx, ry, rz).angle_to(&measured) < CONVENTION_TOLERANCE_RAD;
    let other = match configured {
        EulerConvention::ExtrinsicXyz => EulerConvention::IntrinsicXyz,
        EulerConvention::IntrinsicXyz => EulerConvention::ExtrinsicXyz,
    };
    match (fits(configured), fits(other)) {
        (true, true) => ConventionCheck::Inconclusive,
        (true, false) => ConventionCheck::Confirmed,
        (false, true) => ConventionCheck::Contradicted { fits: other },
        (false, false) => ConventionCheck::NeitherFits,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> FeedbackPacket {
        let rotation = EulerConvention::ExtrinsicXyz.to_rotation(170.0, -20.0, 35.0);
        let q = rotation.quaternion();
        FeedbackPacket {
            robot_mode: 5,
            q_actual_deg: [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            tool_vector_actual: [-400.0, 120.0, 300.0, 170.0, -20.0, 35.0],
            actual_quaternion_wxyz: [q.w, q.i, q.j, q.k],
            current_command_id: 42,
            ..FeedbackPacket::default()
        }
    }

    #[test]
    fn encode_parse_round_trip_at_documented_offsets() {
        let p = sample();
        let bytes = p.encode();
        assert_eq!(bytes.len(), PACKET_LEN);
        assert_eq!(u16::from_le_bytes([bytes[0], bytes[1]]), 1440);
        assert_eq!(u64_at(&bytes, 48), TEST_VALUE);
        assert_eq!(u64_at(&bytes, 432), 1.0f64.to_bits());
        assert_eq!(u64_at(&bytes, 624), (-400.0f64).to_bits());
        assert_eq!(u64_at(&bytes, 24), 5);
        assert_eq!(FeedbackPacket::parse(&bytes).unwrap(), p);
    }

    #[test]
    fn rejects_short_wrong_size_wrong_test_value_and_nan() {
        let bytes = sample().encode();
        assert_eq!(
            FeedbackPacket::parse(&bytes[..100]),
            Err(PacketError::Short { len: 100 })
        );
        let mut b = bytes.clone();
        b[0] = 0x00;
        assert!(matches!(
            FeedbackPacket::parse(&b),
            Err(PacketError::BadSize { .. })
        ));
        let mut b = bytes.clone();
        b[50] ^= 0xFF;
        assert!(matches!(
            FeedbackPacket::parse(&b),
            Err(PacketError::BadTestValue { .. })
        ));
        let mut b = bytes;
        b[432..440].copy_from_slice(&f64::NAN.to_bits().to_le_bytes());
        assert_eq!(
            FeedbackPacket::parse(&b),
            Err(PacketError::NonFinite { field: "QActual" })
        );
    }

    #[test]
    fn frame_reader_resyncs_after_a_truncated_packet() {
        let good = sample().encode();
        let mut reader = FrameReader::default();
        // A packet cut short, then two good ones, delivered in awkward chunks.
        let mut stream = good[..700].to_vec();
        stream.extend_from_slice(&good);
        stream.extend_from_slice(&good);
        for chunk in stream.chunks(333) {
            reader.push(chunk);
        }
        let mut results = Vec::new();
        while let Some(r) = reader.next_packet() {
            results.push(r);
        }
        let oks = results.iter().filter(|r| r.is_ok()).count();
        let errs = results.iter().filter(|r| r.is_err()).count();
        assert_eq!(oks, 2, "{results:?}");
        assert_eq!(errs, 1);
        assert_eq!(reader.pending(), 0);
    }

    #[test]
    fn conventions_round_trip_and_differ() {
        for c in [EulerConvention::ExtrinsicXyz, EulerConvention::IntrinsicXyz] {
            let r = c.to_rotation(30.0, -45.0, 120.0);
            let [rx, ry, rz] = c.to_angles_deg(&r);
            assert!((rx - 30.0).abs() < 1e-9 && (ry + 45.0).abs() < 1e-9 && (rz - 120.0).abs() < 1e-9);
        }
        let a = EulerConvention::ExtrinsicXyz.to_rotation(30.0, -45.0, 120.0);
        let b = EulerConvention::IntrinsicXyz.to_rotation(30.0, -45.0, 120.0);
        assert!(a.angle_to(&b) > 0.1);
        // Extrinsic X-Y-Z equals Rz·Ry·Rx.
        let manual = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 120f64.to_radians())
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), (-45f64).to_radians())
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 30f64.to_radians());
        assert!(a.angle_to(&manual) < 1e-12);
    }

    #[test]
    fn convention_check_detects_a_mismatch() {
        let p = sample();
        assert_eq!(
            check_convention(&p, EulerConvention::ExtrinsicXyz),
            ConventionCheck::Confirmed
        );
        assert_eq!(
            check_convention(&p, EulerConvention::IntrinsicXyz),
            ConventionCheck::Contradicted {
                fits: EulerConvention::ExtrinsicXyz
            }
        );
        let missing = FeedbackPacket {
            actual_quaternion_wxyz: [0.0; 4],
            ..sample()
        };
        assert_eq!(
            check_convention(&missing, EulerConvention::ExtrinsicXyz),
            ConventionCheck::Inconclusive
        );
        let wrong = FeedbackPacket {
            actual_quaternion_wxyz: [0.0, 1.0, 0.0, 0.0],
            ..sample()
        };
        assert_eq!(
            check_convention(&wrong, EulerConvention::ExtrinsicXyz),
            ConventionCheck::NeitherFits
        );
    }
}

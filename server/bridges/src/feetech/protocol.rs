//! Feetech "SCS" protocol 0 packets (STS/SMS series): framing, checksum, instructions, the STS3215 control
//! table and sign-magnitude values.
//!
//! Instruction: `FF FF ID LEN INSTR P1..Pn CHK`; status: `FF FF ID LEN ERR P1..Pn CHK`; `LEN = n + 2`,
//! `CHK = !(ID + LEN + INSTR|ERR + ΣP)`. Multi-byte values are little-endian on STS servos.

/// Broadcast id: every servo executes, none replies.
pub const BROADCAST_ID: u8 = 0xFE;
/// Highest addressable servo id.
pub const MAX_ID: u8 = 0xFC;

/// Instruction codes.
pub mod instruction {
    pub const PING: u8 = 0x01;
    pub const READ: u8 = 0x02;
    pub const WRITE: u8 = 0x03;
    pub const REG_WRITE: u8 = 0x04;
    pub const ACTION: u8 = 0x05;
    pub const SYNC_READ: u8 = 0x82;
    pub const SYNC_WRITE: u8 = 0x83;
}

/// STS3215 control table entries as `(address, bytes)` (lerobot `STS_SMS_SERIES_CONTROL_TABLE`).
pub mod register {
    pub type Entry = (u8, u8);
    pub const FIRMWARE_MAJOR_VERSION: Entry = (0, 1);
    pub const FIRMWARE_MINOR_VERSION: Entry = (1, 1);
    pub const MODEL_NUMBER: Entry = (3, 2);
    pub const ID: Entry = (5, 1);
    pub const BAUD_RATE: Entry = (6, 1);
    pub const RETURN_DELAY_TIME: Entry = (7, 1);
    pub const RESPONSE_STATUS_LEVEL: Entry = (8, 1);
    pub const MIN_POSITION_LIMIT: Entry = (9, 2);
    pub const MAX_POSITION_LIMIT: Entry = (11, 2);
    pub const MAX_TEMPERATURE_LIMIT: Entry = (13, 1);
    pub const MAX_VOLTAGE_LIMIT: Entry = (14, 1);
    pub const MIN_VOLTAGE_LIMIT: Entry = (15, 1);
    pub const MAX_TORQUE_LIMIT: Entry = (16, 2);
    pub const PHASE: Entry = (18, 1);
    pub const P_COEFFICIENT: Entry = (21, 1);
    pub const D_COEFFICIENT: Entry = (22, 1);
    pub const I_COEFFICIENT: Entry = (23, 1);
    pub const PROTECTION_CURRENT: Entry = (28, 2);
    pub const HOMING_OFFSET: Entry = (31, 2);
    pub const OPERATING_MODE: Entry = (33, 1);
    pub const OVERLOAD_TORQUE: Entry = (36, 1);
    pub const TORQUE_ENABLE: Entry = (40, 1);
    pub const ACCELERATION: Entry = (41, 1);
    pub const GOAL_POSITION: Entry = (42, 2);
    pub const GOAL_TIME: Entry = (44, 2);
    pub const GOAL_VELOCITY: Entry = (46, 2);
    pub const TORQUE_LIMIT: Entry = (48, 2);
    pub const LOCK: Entry = (55, 1);
    pub const PRESENT_POSITION: Entry = (56, 2);
    pub const PRESENT_VELOCITY: Entry = (58, 2);
    pub const PRESENT_LOAD: Entry = (60, 2);
    pub const PRESENT_VOLTAGE: Entry = (62, 1);
    pub const PRESENT_TEMPERATURE: Entry = (63, 1);
    pub const STATUS: Entry = (65, 1);
    pub const MOVING: Entry = (66, 1);
    pub const PRESENT_CURRENT: Entry = (69, 2);
    pub const MAXIMUM_ACCELERATION: Entry = (85, 1);
    /// First SRAM address: lower addresses are EPROM, writable only with `Lock` = 0.
    pub const FIRST_SRAM: u8 = 40;
}

/// Model number the STS3215 reports at address 3 (lerobot `MODEL_NUMBER_TABLE["sts3215"]`).
pub const STS3215_MODEL: u16 = 777;
/// Firmware version (major, minor) at addresses 0 and 1 of current STS3215s: lerobot's handshake requires every
/// servo of a bus to report the same one, and SO-101 users report "3.10" as current, "3.9" as the version to
/// upgrade from (huggingface/lerobot issues #1010 and #532).
pub const STS3215_FIRMWARE: (u8, u8) = (3, 10);

/// Decodes a `Present_Position` register into a single-turn position (0..4095). In multi-turn feedback mode
/// ([`PHASE_MULTI_TURN_FEEDBACK`]) the servo counts on past the seam (4096 and beyond, or below 0); the same
/// shaft angle in single-turn mode is that count modulo one turn, which is what lerobot reads once the bit is
/// cleared.
pub fn single_turn_position(raw: u16) -> u16 {
    decode_sign_magnitude(raw, POSITION_SIGN_BIT).rem_euclid(i32::from(COUNTS_PER_TURN)) as u16
}
/// Encoder counts per turn.
pub const COUNTS_PER_TURN: u16 = 4096;
/// Sign bit of positions and velocities.
pub const POSITION_SIGN_BIT: u8 = 15;
/// Sign bit of `Homing_Offset` (±2047).
pub const HOMING_OFFSET_SIGN_BIT: u8 = 11;

/// `Phase` (address 18) bit 4, angle feedback mode: 0 reports the single-turn angle (0..4095), 1 the full
/// (multi-turn) angle, which leaves 0..4095 once the shaft passes the encoder's seam. Feetech STS memory table
/// §3.1 "Servo Phase" (wiki.juxitech.com, "Magnetic Encoder STS Servo – Memory Table Analysis"); some STS3215s
/// ship with it set, which is why lerobot clears it in `FeetechMotorsBus.configure_motors` (huggingface/lerobot
/// PR #3373, "fix(feetech): motor position readings overflow").
pub const PHASE_MULTI_TURN_FEEDBACK: u8 = 0x10;

/// Alarm bits of a status packet's error byte, which are also the bits of the `Status` register (65).
/// Feetech SDK `scservo_def`/`protocol_packet_handler` `ERRBIT_*`, and the STS memory table §3.2 "Servo
/// Status" (bit 4 is listed as unused there; bits 6 and 7 are not listed at all).
pub mod alarm {
    /// Input voltage outside `Min_Voltage_Limit`..`Max_Voltage_Limit` (15, 14).
    pub const VOLTAGE: u8 = 0x01;
    /// The magnetic encoder (angle sensor) failed.
    pub const ANGLE_SENSOR: u8 = 0x02;
    /// Temperature above `Max_Temperature_Limit` (13).
    pub const OVERHEAT: u8 = 0x04;
    /// Current above `Protection_Current` (28).
    pub const OVERCURRENT: u8 = 0x08;
    /// Load above `Overload_Torque` (36) for longer than `Protection_Time` (35).
    pub const OVERLOAD: u8 = 0x20;

    /// Each documented bit and its name.
    pub const NAMED: [(u8, &str); 5] = [
        (VOLTAGE, "input voltage"),
        (ANGLE_SENSOR, "angle sensor"),
        (OVERHEAT, "overheat"),
        (OVERCURRENT, "overcurrent"),
        (OVERLOAD, "overload"),
    ];
}

/// Names the alarm bits of a status error byte, e.g. `"input voltage, overheat (0x05)"`.
pub fn status_error_text(error: u8) -> String {
    let mut names: Vec<String> = alarm::NAMED
        .iter()
        .filter(|(b, _)| error & b != 0)
        .map(|(_, n)| (*n).to_owned())
        .collect();
    let known = alarm::NAMED.iter().fold(0u8, |acc, (b, _)| acc | b);
    if error & !known != 0 {
        names.push(format!("undocumented bits {:#04x}", error & !known));
    }
    if names.is_empty() {
        format!("error {error:#04x}")
    } else {
        format!("{} ({error:#04x})", names.join(", "))
    }
}

/// `!(sum of bytes) & 0xFF` over id, length, instruction/error and parameters.
pub fn checksum(body: &[u8]) -> u8 {
    !body.iter().fold(0u8, |acc, b| acc.wrapping_add(*b))
}

/// Encodes an instruction packet. Fails if the parameters do not fit in one packet.
pub fn instruction_packet(id: u8, instruction: u8, params: &[u8]) -> Result<Vec<u8>, PacketError> {
    let len = u8::try_from(params.len() + 2).map_err(|_| PacketError::TooLong(params.len()))?;
    let mut p = Vec::with_capacity(params.len() + 6);
    p.extend_from_slice(&[0xFF, 0xFF, id, len, instruction]);
    p.extend_from_slice(params);
    p.push(checksum(&p[2..]));
    Ok(p)
}

/// Encodes a status packet (what a servo sends back).
pub fn status_packet(id: u8, error: u8, params: &[u8]) -> Vec<u8> {
    // Status payloads come from the emulator's own register reads, which are at most a few hundred bytes; a
    // longer one is clipped rather than mis-framed.
    let params = &params[..params.len().min(250)];
    let mut p = Vec::with_capacity(params.len() + 6);
    p.extend_from_slice(&[0xFF, 0xFF, id, (params.len() + 2) as u8, error]);
    p.extend_from_slice(params);
    p.push(checksum(&p[2..]));
    p
}

/// `SYNC_WRITE` of `len` bytes at `address` to each `(id, data)`.
pub fn sync_write_packet(address: u8, len: u8, items: &[(u8, Vec<u8>)]) -> Result<Vec<u8>, PacketError> {
    let mut params = Vec::with_capacity(2 + items.len() * (usize::from(len) + 1));
    params.extend_from_slice(&[address, len]);
    for (id, data) in items {
        if data.len() != usize::from(len) {
            return Err(PacketError::DataLength {
                id: *id,
                expected: len,
                got: data.len(),
            });
        }
        params.push(*id);
        params.extend_from_slice(data);
    }
    instruction_packet(BROADCAST_ID, instruction::SYNC_WRITE, &params)
}

/// `SYNC_READ` of `len` bytes at `address` from `ids` (each answers in turn).
pub fn sync_read_packet(address: u8, len: u8, ids: &[u8]) -> Result<Vec<u8>, PacketError> {
    let mut params = Vec::with_capacity(2 + ids.len());
    params.extend_from_slice(&[address, len]);
    params.extend_from_slice(ids);
    instruction_packet(BROADCAST_ID, instruction::SYNC_READ, &params)
}

/// A decoded packet: for instructions `code` is the instruction, for status packets the error byte.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Packet {
    pub id: u8,
    pub code: u8,
    pub params: Vec<u8>,
}

/// Packet framing and encoding errors.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PacketError {
    #[error("{0} parameter bytes do not fit in one packet")]
    TooLong(usize),
    #[error("servo {id}: {got} data bytes, expected {expected}")]
    DataLength { id: u8, expected: u8, got: usize },
    #[error("packet from id {id}: checksum {got:#04x}, expected {expected:#04x}")]
    Checksum { id: u8, expected: u8, got: u8 },
    #[error("packet from id {id}: length field {len} is invalid")]
    BadLength { id: u8, len: u8 },
}

/// Outcome of scanning a receive buffer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Decoded {
    /// A packet and the number of bytes it (and any garbage before it) used.
    Packet(Packet, usize),
    /// A framing error; skip `usize` bytes and scan again.
    Error(PacketError, usize),
    /// Not enough bytes yet; `usize` leading bytes are garbage and may be dropped.
    Incomplete(usize),
}

/// Finds the next packet in `buf`, skipping bytes before an `FF FF` header.
pub fn decode(buf: &[u8]) -> Decoded {
    let Some(start) = buf.windows(2).position(|w| w == [0xFF, 0xFF]) else {
        // Keep a trailing 0xFF: it may be the first half of a header.
        let keep = usize::from(buf.last() == Some(&0xFF));
        return Decoded::Incomplete(buf.len() - keep);
    };
    // A third 0xFF means the header started one byte later (0xFF is not a valid id).
    if buf.get(start + 2) == Some(&0xFF) {
        return Decoded::Error(PacketError::BadLength { id: 0xFF, len: 0 }, start + 1);
    }
    let rest = &buf[start..];
    if rest.len() < 4 {
        return Decoded::Incomplete(start);
    }
    let (id, len) = (rest[2], rest[3]);
    if len < 2 {
        return Decoded::Error(PacketError::BadLength { id, len }, start + 2);
    }
    let total = 4 + usize::from(len);
    if rest.len() < total {
        return Decoded::Incomplete(start);
    }
    let expected = checksum(&rest[2..total - 1]);
    let got = rest[total - 1];
    if expected != got {
        return Decoded::Error(PacketError::Checksum { id, expected, got }, start + 2);
    }
    Decoded::Packet(
        Packet {
            id,
            code: rest[4],
            params: rest[5..total - 1].to_vec(),
        },
        start + total,
    )
}

/// Encodes a signed value with the sign in bit `sign_bit` and the magnitude below it.
pub fn encode_sign_magnitude(value: i32, sign_bit: u8) -> u16 {
    let max = (1i32 << sign_bit) - 1;
    let magnitude = value.unsigned_abs().min(max as u32) as u16;
    if value < 0 {
        magnitude | (1 << sign_bit)
    } else {
        magnitude
    }
}

/// Decodes a sign-magnitude value.
pub fn decode_sign_magnitude(raw: u16, sign_bit: u8) -> i32 {
    let magnitude = i32::from(raw & ((1u16 << sign_bit) - 1));
    if raw & (1 << sign_bit) != 0 {
        -magnitude
    } else {
        magnitude
    }
}

/// Little-endian bytes of a 1- or 2-byte register value.
pub fn value_bytes(value: u16, len: u8) -> Vec<u8> {
    match len {
        1 => vec![value as u8],
        _ => value.to_le_bytes().to_vec(),
    }
}

/// Reads a 1- or 2-byte little-endian value.
pub fn bytes_value(bytes: &[u8]) -> u16 {
    match bytes {
        [] => 0,
        [b] => u16::from(*b),
        [lo, hi, ..] => u16::from_le_bytes([*lo, *hi]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ping_and_read_match_the_documented_bytes() {
        // PING id 1: FF FF 01 02 01 FB.
        assert_eq!(
            instruction_packet(1, instruction::PING, &[]).unwrap(),
            vec![0xFF, 0xFF, 1, 2, 1, 0xFB]
        );
        // READ id 1, Present_Position (56, 2): LEN 4, CHK = !(1+4+2+56+2).
        let p = instruction_packet(1, instruction::READ, &[56, 2]).unwrap();
        assert_eq!(p, vec![0xFF, 0xFF, 1, 4, 2, 56, 2, !(1u8 + 4 + 2 + 56 + 2)]);
    }

    #[test]
    fn sync_packets_have_the_documented_length() {
        let items: Vec<(u8, Vec<u8>)> = (1..=6).map(|id| (id, vec![0x00, 0x08])).collect();
        let p = sync_write_packet(42, 2, &items).unwrap();
        // LEN = (L + 1)·N + 4.
        assert_eq!(p[3], 3 * 6 + 4);
        assert_eq!(p[2], BROADCAST_ID);
        let p = sync_read_packet(56, 2, &[1, 2, 3, 4, 5, 6]).unwrap();
        assert_eq!(p[3], 6 + 4);
        assert!(sync_write_packet(42, 2, &[(1, vec![0])]).is_err());
    }

    #[test]
    fn decode_finds_packets_after_garbage_and_rejects_bad_checksums() {
        let good = status_packet(3, 0, &[0x10, 0x20]);
        let mut buf = vec![0x00, 0x13, 0xFF];
        buf.extend_from_slice(&good);
        // The stray 0xFF before the header makes FF FF FF: skipped one byte at a time.
        let mut offset = 0;
        let packet = loop {
            match decode(&buf[offset..]) {
                Decoded::Packet(p, used) => {
                    assert_eq!(offset + used, buf.len());
                    break p;
                }
                Decoded::Error(_, skip) => offset += skip,
                Decoded::Incomplete(_) => panic!("incomplete"),
            }
        };
        assert_eq!(
            packet,
            Packet {
                id: 3,
                code: 0,
                params: vec![0x10, 0x20]
            }
        );

        let mut bad = good.clone();
        *bad.last_mut().unwrap() ^= 0x01;
        assert!(matches!(
            decode(&bad),
            Decoded::Error(PacketError::Checksum { id: 3, .. }, _)
        ));
        assert_eq!(decode(&good[..5]), Decoded::Incomplete(0));
    }

    #[test]
    fn sign_magnitude_round_trips_at_both_sign_bits() {
        for v in [-2047, -1, 0, 1, 1000, 2047] {
            assert_eq!(decode_sign_magnitude(encode_sign_magnitude(v, 11), 11), v);
        }
        assert_eq!(encode_sign_magnitude(-5, 11), 0x0805);
        assert_eq!(encode_sign_magnitude(-5, 15), 0x8005);
        // Clamped to the magnitude range rather than spilling into the sign bit.
        assert_eq!(encode_sign_magnitude(5000, 11), 2047);
        assert_eq!(decode_sign_magnitude(0x8000 | 0x012C, 15), -300);
    }

    #[test]
    fn multi_turn_positions_wrap_to_one_turn() {
        assert_eq!(single_turn_position(2000), 2000);
        // 4200 is 104 counts past the seam; -50 is 50 counts before it.
        assert_eq!(single_turn_position(4200), 104);
        assert_eq!(
            single_turn_position(encode_sign_magnitude(-50, POSITION_SIGN_BIT)),
            4046
        );
        assert_eq!(
            single_turn_position(encode_sign_magnitude(-4096, POSITION_SIGN_BIT)),
            0
        );
    }

    #[test]
    fn error_bits_are_named() {
        assert_eq!(status_error_text(0x20), "overload (0x20)");
        assert_eq!(status_error_text(0x05), "input voltage, overheat (0x05)");
        assert_eq!(status_error_text(0x10), "undocumented bits 0x10 (0x10)");
        assert_eq!(
            status_error_text(0x21 | 0x40),
            "input voltage, overload, undocumented bits 0x40 (0x61)"
        );
    }
}

//! A Feetech servo bus on a serial port: ping, read, write, sync read and sync write with timeouts.
//!
//! Every transaction first drops stale input, so a late answer from a previous, timed-out request cannot be
//! taken for the answer to the next one.

use super::protocol::{
    self, BROADCAST_ID, Decoded, Packet, PacketError, bytes_value, instruction, status_error_text,
    value_bytes,
};
use serialport::{ClearBuffer, SerialPort};
use std::io::{ErrorKind, Read, Write};
use std::time::{Duration, Instant};

/// Bus errors; each names the servo concerned where there is one.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error("serial port {port}: {message}")]
    Open { port: String, message: String },
    #[error("serial I/O: {0}")]
    Io(#[from] std::io::Error),
    #[error("servo {id} did not answer within {timeout_ms} ms")]
    Timeout { id: u8, timeout_ms: u64 },
    #[error("{0}")]
    Packet(#[from] PacketError),
    #[error("servo {id} reports {}", status_error_text(*.error))]
    Servo { id: u8, error: u8 },
    #[error("servo {expected} expected, packet from {got}")]
    WrongId { expected: u8, got: u8 },
    #[error("servo {id}: {got} bytes returned, {expected} requested")]
    ShortData { id: u8, expected: usize, got: usize },
}

impl BusError {
    /// True when the port itself failed (unplugged adapter), as opposed to one servo misbehaving.
    pub fn is_link_failure(&self) -> bool {
        matches!(self, BusError::Io(_) | BusError::Open { .. })
    }
}

/// Bus statistics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BusStats {
    pub transactions: u64,
    pub timeouts: u64,
    pub checksum_errors: u64,
    pub servo_errors: u64,
}

/// An open bus.
pub struct FeetechBus {
    port: Box<dyn SerialPort>,
    path: String,
    timeout: Duration,
    rx: Vec<u8>,
    stats: BusStats,
    /// When true, a status packet whose error byte is non-zero fails the transaction.
    pub strict_status: bool,
}

impl std::fmt::Debug for FeetechBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FeetechBus")
            .field("path", &self.path)
            .field("timeout", &self.timeout)
            .finish_non_exhaustive()
    }
}

impl FeetechBus {
    /// Opens `path` at `baudrate` (8N1). `timeout` bounds each servo's answer.
    pub fn open(path: &str, baudrate: u32, timeout: Duration) -> Result<Self, BusError> {
        let port = serialport::new(path, baudrate)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(Duration::from_millis(2))
            .open()
            .map_err(|e| BusError::Open {
                port: path.to_owned(),
                message: e.to_string(),
            })?;
        Ok(Self {
            port,
            path: path.to_owned(),
            timeout,
            rx: Vec::with_capacity(256),
            stats: BusStats::default(),
            strict_status: true,
        })
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    pub fn stats(&self) -> BusStats {
        self.stats
    }

    fn send(&mut self, packet: &[u8]) -> Result<(), BusError> {
        self.port
            .clear(ClearBuffer::Input)
            .map_err(|e| BusError::Io(e.into()))?;
        self.rx.clear();
        self.stats.transactions += 1;
        self.port.write_all(packet)?;
        self.port.flush()?;
        Ok(())
    }

    /// Reads the next status packet from `expected_id`, or times out at `deadline`.
    fn receive(&mut self, expected_id: u8, deadline: Instant) -> Result<Packet, BusError> {
        let mut chunk = [0u8; 256];
        loop {
            match protocol::decode(&self.rx) {
                Decoded::Packet(p, used) => {
                    self.rx.drain(..used);
                    if p.id != expected_id {
                        return Err(BusError::WrongId {
                            expected: expected_id,
                            got: p.id,
                        });
                    }
                    if p.code != 0 && self.strict_status {
                        self.stats.servo_errors += 1;
                        return Err(BusError::Servo {
                            id: p.id,
                            error: p.code,
                        });
                    }
                    return Ok(p);
                }
                Decoded::Error(e, skip) => {
                    self.rx.drain(..skip);
                    if matches!(e, PacketError::Checksum { .. }) {
                        self.stats.checksum_errors += 1;
                        return Err(e.into());
                    }
                }
                Decoded::Incomplete(garbage) => {
                    self.rx.drain(..garbage);
                }
            }
            if Instant::now() >= deadline {
                self.stats.timeouts += 1;
                return Err(BusError::Timeout {
                    id: expected_id,
                    timeout_ms: self.timeout.as_millis() as u64,
                });
            }
            match self.port.read(&mut chunk) {
                Ok(n) => self.rx.extend_from_slice(&chunk[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(BusError::Io(e)),
            }
        }
    }

    /// Pings a servo; returns its error byte.
    pub fn ping(&mut self, id: u8) -> Result<u8, BusError> {
        self.send(&protocol::instruction_packet(id, instruction::PING, &[])?)?;
        let strict = std::mem::replace(&mut self.strict_status, false);
        let reply = self.receive(id, Instant::now() + self.timeout);
        self.strict_status = strict;
        Ok(reply?.code)
    }

    /// Reads `len` bytes at `address`.
    pub fn read(&mut self, id: u8, address: u8, len: u8) -> Result<Vec<u8>, BusError> {
        self.send(&protocol::instruction_packet(
            id,
            instruction::READ,
            &[address, len],
        )?)?;
        let p = self.receive(id, Instant::now() + self.timeout)?;
        if p.params.len() != usize::from(len) {
            return Err(BusError::ShortData {
                id,
                expected: usize::from(len),
                got: p.params.len(),
            });
        }
        Ok(p.params)
    }

    /// Reads a 1- or 2-byte register.
    pub fn read_value(&mut self, id: u8, entry: (u8, u8)) -> Result<u16, BusError> {
        Ok(bytes_value(&self.read(id, entry.0, entry.1)?))
    }

    /// Writes bytes at `address` and waits for the acknowledgement (none for the broadcast id).
    pub fn write(&mut self, id: u8, address: u8, data: &[u8]) -> Result<(), BusError> {
        let mut params = Vec::with_capacity(data.len() + 1);
        params.push(address);
        params.extend_from_slice(data);
        self.send(&protocol::instruction_packet(id, instruction::WRITE, &params)?)?;
        if id != BROADCAST_ID {
            self.receive(id, Instant::now() + self.timeout)?;
        }
        Ok(())
    }

    /// Writes a 1- or 2-byte register.
    pub fn write_value(&mut self, id: u8, entry: (u8, u8), value: u16) -> Result<(), BusError> {
        self.write(id, entry.0, &value_bytes(value, entry.1))
    }

    /// One packet writing `len` bytes at `address` on several servos; no servo answers.
    pub fn sync_write(&mut self, address: u8, len: u8, items: &[(u8, Vec<u8>)]) -> Result<(), BusError> {
        self.send(&protocol::sync_write_packet(address, len, items)?)
    }

    /// Reads `len` bytes at `address` from each of `ids` with one request. Returns the data in `ids` order, or
    /// the first failure (a servo that does not answer fails the whole read: a partial state is not a state).
    /// With [`Self::strict_status`], a servo reporting an alarm fails it too.
    pub fn sync_read(&mut self, address: u8, len: u8, ids: &[u8]) -> Result<Vec<Vec<u8>>, BusError> {
        Ok(self
            .sync_read_packets(address, len, ids)?
            .into_iter()
            .map(|p| p.params)
            .collect())
    }

    /// As [`Self::sync_read`], but an alarm is data, not a failure: each servo's answer comes with the error
    /// byte of its status packet (alarm bits, [`protocol::alarm`]), whatever [`Self::strict_status`] says.
    /// Servos keep answering while an alarm is latched, so this is how a caller sees an alarm without losing
    /// the positions that came with it.
    pub fn sync_read_with_status(
        &mut self,
        address: u8,
        len: u8,
        ids: &[u8],
    ) -> Result<Vec<ServoReply>, BusError> {
        let strict = std::mem::replace(&mut self.strict_status, false);
        let result = self.sync_read_packets(address, len, ids);
        self.strict_status = strict;
        Ok(result?
            .into_iter()
            .map(|p| ServoReply {
                data: p.params,
                error: p.code,
            })
            .collect())
    }

    fn sync_read_packets(&mut self, address: u8, len: u8, ids: &[u8]) -> Result<Vec<Packet>, BusError> {
        self.send(&protocol::sync_read_packet(address, len, ids)?)?;
        let deadline = Instant::now() + self.timeout;
        let mut out = Vec::with_capacity(ids.len());
        for &id in ids {
            let p = match self.receive(id, deadline) {
                // Servos answer in list order: an answer from a later servo means this one stayed silent.
                Err(BusError::WrongId { expected, got }) if ids.contains(&got) => {
                    self.stats.timeouts += 1;
                    return Err(BusError::Timeout {
                        id: expected,
                        timeout_ms: self.timeout.as_millis() as u64,
                    });
                }
                other => other?,
            };
            if p.params.len() != usize::from(len) {
                return Err(BusError::ShortData {
                    id,
                    expected: usize::from(len),
                    got: p.params.len(),
                });
            }
            out.push(p);
        }
        Ok(out)
    }
}

/// One servo's answer to a sync read: its data and the error byte (alarm bits) of its status packet.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ServoReply {
    pub data: Vec<u8>,
    pub error: u8,
}

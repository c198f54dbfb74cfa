//! The flight recorder's files: one per arm and server run, holding the arbiter's starting point and then every
//! input it was given with its time, the robot state it saw and what it decided ([`phone2act_core::flight`]).
//!
//! A file is `MAGIC`, then MessagePack values: the [`FlightHeader`], then records, each an entry or the end
//! record that says why the log stopped. Records are encoded on the control path (a few microseconds) and
//! handed to a writer thread through a bounded channel, so the disk never holds up a command. A log never
//! grows past its size limit, and a writer that falls behind stops the log rather than the arm: either way
//! the file ends on a whole record, and the end record (when there was room for it) says why.

use crate::config::Config;
pub use phone2act_core::{Divergence, ReplayCounts};
use phone2act_core::{FlightEntry, FlightHeader, ReplayError, Replayer};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError, sync_channel};
use std::thread::JoinHandle;
use std::time::Duration;

/// The first bytes of a flight log.
pub const MAGIC: &[u8; 8] = b"P2AFLT1\n";

/// Records that may wait for the writer thread: several seconds of a 60 Hz phone plus a policy's ticks.
const QUEUE_RECORDS: usize = 4096;

/// How long the writer waits for records before it flushes what it has: what a crash can lose at most.
const FLUSH_AFTER: Duration = Duration::from_millis(200);

#[derive(Debug, Serialize, Deserialize)]
enum Record {
    Entry(Box<FlightEntry>),
    End { reason: String },
}

/// Errors of a flight log file.
#[derive(Debug, thiserror::Error)]
pub enum FlightLogError {
    #[error("flight log {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("flight log {path}: not a phone2act flight log (no {MAGIC:?} at its start)")]
    NotALog { path: PathBuf },
    #[error("flight log {path}: cannot read its header: {message}")]
    Header { path: PathBuf, message: String },
    #[error("flight log: cannot encode a record: {0}")]
    Encode(String),
    #[error("flight log {path}: {source}")]
    Replay {
        path: PathBuf,
        #[source]
        source: ReplayError,
    },
    #[error("flight log {path}: the configuration has no arm {arm:?} (the log's arm)")]
    UnknownArm { path: PathBuf, arm: String },
}

/// Writes one arm's flight log. Owned by the arm's controller and called under its lock, in input order.
#[derive(Debug)]
pub struct FlightLogWriter {
    path: PathBuf,
    tx: Option<SyncSender<Vec<u8>>>,
    writer: Option<JoinHandle<()>>,
    written_bytes: u64,
    max_bytes: u64,
    stopped: Option<String>,
}

impl FlightLogWriter {
    /// Creates a new log for `header.arm` in `dir` (created if missing) with the header written, so that a
    /// directory that cannot be written is an error at start, not a silent gap later. `max_bytes` bounds the
    /// file.
    pub fn create(dir: &Path, header: &FlightHeader, max_bytes: u64) -> Result<Self, FlightLogError> {
        let io = |path: &Path| {
            let path = path.to_owned();
            move |source| FlightLogError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let stamp_s = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let (path, file) = (0..1000)
            .map(|n| {
                let suffix = if n == 0 { String::new() } else { format!("-{n}") };
                dir.join(format!("{}-{stamp_s}{suffix}.flight", header.arm))
            })
            .find_map(|path| match File::create_new(&path) {
                Ok(file) => Some(Ok((path, file))),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => None,
                Err(e) => Some(Err(FlightLogError::Io { path, source: e })),
            })
            .unwrap_or_else(|| {
                Err(FlightLogError::Io {
                    path: dir.to_owned(),
                    source: std::io::Error::other("no free file name"),
                })
            })?;
        let mut out = BufWriter::new(file);
        let head = rmp_serde::to_vec(header).map_err(|e| FlightLogError::Encode(e.to_string()))?;
        out.write_all(MAGIC)
            .and_then(|()| out.write_all(&head))
            .and_then(|()| out.flush())
            .map_err(io(&path))?;
        let (tx, rx) = sync_channel(QUEUE_RECORDS);
        let thread_path = path.clone();
        let writer = std::thread::Builder::new()
            .name(format!("flight-{}", header.arm))
            .spawn(move || write_records(&rx, out, &thread_path))
            .map_err(io(&path))?;
        Ok(Self {
            written_bytes: (MAGIC.len() + head.len()) as u64,
            path,
            tx: Some(tx),
            writer: Some(writer),
            max_bytes,
            stopped: None,
        })
    }

    /// The file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Why the log stopped taking records, if it did.
    pub fn stopped(&self) -> Option<&str> {
        self.stopped.as_deref()
    }

    /// Bytes handed to the writer so far (header included).
    pub fn written_bytes(&self) -> u64 {
        self.written_bytes
    }

    /// Logs one input. Never blocks: a log that is full or whose writer fell behind stops (and says so once
    /// in the server log); the arm goes on.
    pub fn record(&mut self, entry: FlightEntry) {
        if self.stopped.is_some() {
            return;
        }
        let bytes = match rmp_serde::to_vec(&Record::Entry(Box::new(entry))) {
            Ok(bytes) => bytes,
            Err(e) => return self.stop(format!("a record could not be encoded: {e}"), true),
        };
        // Room is kept for the end record, so a full log still says why it ended.
        if self.written_bytes + bytes.len() as u64 + END_RECORD_ROOM > self.max_bytes {
            return self.stop(
                format!("the log reached its size limit of {} bytes", self.max_bytes),
                true,
            );
        }
        let len = bytes.len() as u64;
        match self.tx.as_ref().map(|tx| tx.try_send(bytes)) {
            Some(Ok(())) => self.written_bytes += len,
            Some(Err(TrySendError::Full(_))) => self.stop(
                format!("the writer fell {QUEUE_RECORDS} records behind (the disk is too slow)"),
                false,
            ),
            Some(Err(TrySendError::Disconnected(_))) | None => {
                self.stop("the writer stopped (see the error logged before)".into(), false);
            }
        }
    }

    fn stop(&mut self, reason: String, with_end_record: bool) {
        tracing::warn!(path = %self.path.display(), %reason, "flight log stopped; later inputs are not logged");
        if with_end_record {
            self.send_end(&reason);
        }
        self.stopped = Some(reason);
    }

    fn send_end(&mut self, reason: &str) {
        let Ok(bytes) = rmp_serde::to_vec(&Record::End {
            reason: reason.to_owned(),
        }) else {
            return;
        };
        let len = bytes.len() as u64;
        if self.tx.as_ref().is_some_and(|tx| tx.try_send(bytes).is_ok()) {
            self.written_bytes += len;
        }
    }
}

/// Bytes kept free for the end record (its reason is a short sentence).
const END_RECORD_ROOM: u64 = 512;

impl Drop for FlightLogWriter {
    /// Ends the log with an end record and waits for the writer, so that the file is complete once the arm
    /// is gone.
    fn drop(&mut self) {
        if self.stopped.is_none() {
            self.send_end("the arm was shut down");
        }
        self.tx = None;
        if let Some(writer) = self.writer.take() {
            let _ = writer.join();
        }
    }
}

fn write_records(rx: &Receiver<Vec<u8>>, mut out: BufWriter<File>, path: &Path) {
    loop {
        let result = match rx.recv_timeout(FLUSH_AFTER) {
            Ok(bytes) => out.write_all(&bytes),
            Err(RecvTimeoutError::Timeout) => out.flush(),
            Err(RecvTimeoutError::Disconnected) => break,
        };
        if let Err(e) = result {
            tracing::error!(path = %path.display(), error = %e, "flight log write failed; the log stops here");
            return;
        }
    }
    if let Err(e) = out.flush().and_then(|()| out.get_ref().sync_all()) {
        tracing::error!(path = %path.display(), error = %e, "flight log final flush failed");
    }
}

/// How a log ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Ending {
    /// Not read to its end yet.
    NotYet,
    /// With an end record giving the reason.
    Recorded(String),
    /// Without one: the server was killed, or the writer fell behind.
    NoEndRecord,
    /// With a partial record (the server was killed mid-write) or bytes that are no record.
    Damaged(String),
}

/// Reads a flight log: its header, then its entries in order.
#[derive(Debug)]
pub struct FlightLogReader<R> {
    input: BufReader<R>,
    header: FlightHeader,
    ending: Ending,
}

impl FlightLogReader<File> {
    /// Opens `path` and reads its header.
    pub fn open(path: &Path) -> Result<Self, FlightLogError> {
        let file = File::open(path).map_err(|source| FlightLogError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::new(file, path)
    }
}

impl<R: Read> FlightLogReader<R> {
    /// Reads the header from `input`; `path` names it in errors.
    pub fn new(input: R, path: &Path) -> Result<Self, FlightLogError> {
        let mut input = BufReader::new(input);
        let mut magic = [0u8; MAGIC.len()];
        if input.read_exact(&mut magic).is_err() || &magic != MAGIC {
            return Err(FlightLogError::NotALog {
                path: path.to_owned(),
            });
        }
        let header: FlightHeader = rmp_serde::from_read(&mut input).map_err(|e| FlightLogError::Header {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
        Ok(Self {
            input,
            header,
            ending: Ending::NotYet,
        })
    }

    /// What the arbiter started from.
    pub fn header(&self) -> &FlightHeader {
        &self.header
    }

    /// How the log ended, once the entries have been read to their end.
    pub fn ending(&self) -> &Ending {
        &self.ending
    }
}

impl<R: Read> Iterator for FlightLogReader<R> {
    type Item = FlightEntry;

    fn next(&mut self) -> Option<FlightEntry> {
        if self.ending != Ending::NotYet {
            return None;
        }
        match self.input.fill_buf() {
            Ok([]) => {
                self.ending = Ending::NoEndRecord;
                return None;
            }
            Ok(_) => {}
            Err(e) => {
                self.ending = Ending::Damaged(e.to_string());
                return None;
            }
        }
        match rmp_serde::from_read::<_, Record>(&mut self.input) {
            Ok(Record::Entry(entry)) => Some(*entry),
            Ok(Record::End { reason }) => {
                self.ending = Ending::Recorded(reason);
                None
            }
            Err(e) => {
                self.ending = Ending::Damaged(e.to_string());
                None
            }
        }
    }
}

/// What one log's replay found.
#[derive(Debug)]
pub enum Verdict {
    Identical(ReplayCounts),
    Differs(Divergence),
}

/// Replays the log at `path` on a fresh arbiter: under `config`'s teleop and chunk settings for the log's arm
/// when given (the same inputs decided by other settings), else under the settings it recorded. Returns the verdict and, when identical, a sentence saying how the log ended.
pub fn replay_file(path: &Path, config: Option<&Config>) -> Result<(Verdict, String), FlightLogError> {
    let mut reader = FlightLogReader::open(path)?;
    let mut header = reader.header().clone();
    if let Some(config) = config {
        let arm =
            config
                .arms
                .iter()
                .find(|a| a.name == header.arm)
                .ok_or_else(|| FlightLogError::UnknownArm {
                    path: path.to_owned(),
                    arm: header.arm.clone(),
                })?;
        header.teleop = arm.teleop.clone();
        header.chunk = arm.chunk.clone();
    }
    let mut replayer = Replayer::new(&header).map_err(|source| FlightLogError::Replay {
        path: path.to_owned(),
        source,
    })?;
    for entry in reader.by_ref() {
        if let Err(d) = replayer.step(&entry) {
            return Ok((Verdict::Differs(d), String::new()));
        }
    }
    let ending = match reader.ending() {
        Ending::Recorded(reason) => format!("the log ends: {reason}"),
        Ending::NoEndRecord => {
            "the log ends without an end record (the server was killed, or its writer fell behind)".to_owned()
        }
        Ending::Damaged(message) => {
            format!("the log ends in a damaged record ({message}); the entries before it were replayed")
        }
        Ending::NotYet => String::new(),
    };
    Ok((Verdict::Identical(replayer.counts()), ending))
}

#[cfg(test)]
mod tests {
    use super::*;
    use phone2act_core::{BridgeHealth, ChunkConfig, Effects, Input, Outcome, Robot, TeleopConfig};

    fn header() -> FlightHeader {
        FlightHeader::new(
            "main",
            &TeleopConfig::default(),
            &ChunkConfig::default(),
            nalgebra::Isometry3::translation(0.25, 0.0, 0.2),
            0.5,
        )
    }

    fn entry(now_s: f64) -> FlightEntry {
        FlightEntry {
            now_s,
            input: Input::Tick,
            robot: Robot {
                health: BridgeHealth::Disconnected("x".into()),
                feedback: None,
            },
            outcome: Outcome::Applied(Effects::default()),
        }
    }

    fn read_all(path: &Path) -> (FlightHeader, Vec<FlightEntry>, Ending) {
        let mut reader = FlightLogReader::open(path).unwrap();
        let entries: Vec<_> = reader.by_ref().collect();
        (reader.header().clone(), entries, reader.ending().clone())
    }

    fn only_file(dir: &Path) -> PathBuf {
        let files: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(files.len(), 1, "{files:?}");
        files[0].clone()
    }

    #[test]
    fn a_log_reads_back_bit_for_bit_with_its_end() {
        let dir = tempfile::tempdir().unwrap();
        let mut log = FlightLogWriter::create(dir.path(), &header(), 1 << 20).unwrap();
        // A time that is not a short decimal: the log keeps every bit.
        let times: Vec<f64> = (0..100).map(|i| 1.0 / 3.0 + f64::from(i) * 0.1).collect();
        for &t in &times {
            log.record(entry(t));
        }
        assert!(log.stopped().is_none());
        let path = log.path().to_owned();
        drop(log);
        let (h, entries, ending) = read_all(&path);
        assert_eq!(h, header());
        assert_eq!(entries, times.iter().map(|&t| entry(t)).collect::<Vec<_>>());
        assert_eq!(ending, Ending::Recorded("the arm was shut down".into()));
    }

    #[test]
    fn a_log_stops_at_its_size_limit_and_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let max_bytes = 4096;
        let mut log = FlightLogWriter::create(dir.path(), &header(), max_bytes).unwrap();
        for i in 0..10_000 {
            log.record(entry(f64::from(i)));
        }
        assert!(log.stopped().unwrap().contains("size limit of 4096 bytes"));
        assert!(log.written_bytes() <= max_bytes, "{}", log.written_bytes());
        let path = log.path().to_owned();
        drop(log);
        assert!(std::fs::metadata(&path).unwrap().len() <= max_bytes);
        let (_, entries, ending) = read_all(&path);
        assert!(entries.len() > 10, "{}", entries.len());
        assert_eq!(entries.last().unwrap(), &entry((entries.len() - 1) as f64));
        assert_eq!(
            ending,
            Ending::Recorded("the log reached its size limit of 4096 bytes".into())
        );
    }

    #[test]
    fn a_killed_writer_leaves_a_log_whose_whole_records_read() {
        let dir = tempfile::tempdir().unwrap();
        let mut log = FlightLogWriter::create(dir.path(), &header(), 1 << 20).unwrap();
        for i in 0..5 {
            log.record(entry(f64::from(i)));
        }
        let path = log.path().to_owned();
        drop(log);
        // As a kill -9 leaves it: no end record, and half of a record at the end.
        let full = std::fs::read(&path).unwrap();
        let end = rmp_serde::to_vec(&Record::End {
            reason: "the arm was shut down".into(),
        })
        .unwrap();
        let without_end = &full[..full.len() - end.len()];
        std::fs::write(&path, without_end).unwrap();
        let (_, entries, ending) = read_all(&path);
        assert_eq!((entries.len(), ending), (5, Ending::NoEndRecord));
        let half = rmp_serde::to_vec(&Record::Entry(Box::new(entry(9.0)))).unwrap();
        let mut damaged = without_end.to_vec();
        damaged.extend_from_slice(&half[..half.len() / 2]);
        std::fs::write(&path, damaged).unwrap();
        let (_, entries, ending) = read_all(&path);
        assert_eq!(entries.len(), 5);
        assert!(matches!(ending, Ending::Damaged(_)), "{ending:?}");
    }

    #[test]
    fn two_logs_of_one_arm_in_one_second_get_two_files_and_a_bad_file_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let a = FlightLogWriter::create(dir.path(), &header(), 1 << 20).unwrap();
        let b = FlightLogWriter::create(dir.path(), &header(), 1 << 20).unwrap();
        assert_ne!(a.path(), b.path());
        drop((a, b));
        let other = dir.path().join("other.flight");
        std::fs::write(&other, b"not a log").unwrap();
        let err = FlightLogReader::open(&other).unwrap_err();
        assert!(err.to_string().contains("not a phone2act flight log"), "{err}");
        let sub = tempfile::tempdir().unwrap();
        let log = FlightLogWriter::create(&sub.path().join("new/dir"), &header(), 1 << 20).unwrap();
        drop(log);
        only_file(&sub.path().join("new/dir"));
    }
}

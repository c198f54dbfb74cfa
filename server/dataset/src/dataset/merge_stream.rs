//! The streaming pieces of a merge, which keep its memory independent of how many episodes the inputs hold:
//! the inputs' file lists walked chunk by chunk, their episode metadata read a record batch (or a line) at a
//! time, each input's provenance entries parsed as they are needed, and the merged provenance spooled to a
//! file in the output directory and spliced into `meta/phone2act_provenance.json` at the end.

use super::{EpisodeSummary, Provenance, meta::pretty};
use crate::error::RecorderError;
use crate::stats::Aggregate;
use arrow_array::RecordBatch;
use parquet::arrow::arrow_reader::{ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder};
use serde::Deserialize;
use serde::de::{self, DeserializeSeed, Deserializer, IgnoredAny, MapAccess, SeqAccess, Visitor};
use serde_json::Value;
use std::collections::BTreeMap;
use std::fs::{self, File};
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

/// The `.parquet` files of a `data/` or `meta/episodes/` tree in path order, listed one chunk directory at a
/// time: what is held is the list of chunk directories and one chunk's files (lerobot puts at most
/// `chunks_size` files in a chunk), not every file of the dataset.
pub(super) fn parquet_files(dir: &Path) -> impl Iterator<Item = PathBuf> + use<> {
    let mut chunks: Vec<PathBuf> = fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|c| c.path())
        .collect();
    chunks.sort();
    chunks.into_iter().flat_map(|chunk| {
        let mut files: Vec<PathBuf> = fs::read_dir(&chunk)
            .into_iter()
            .flatten()
            .flatten()
            .map(|f| f.path())
            .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
            .collect();
        files.sort();
        files
    })
}

/// The rows of a sequence of parquet files, in order, one record batch held at a time (the reader's default
/// batch of up to 1,024 rows, the batches `parquet_io::read_batches` returns).
pub(super) struct ParquetRows<I> {
    files: I,
    reader: Option<(PathBuf, ParquetRecordBatchReader)>,
    batch: Option<RecordBatch>,
    row: usize,
}

impl<I: Iterator<Item = PathBuf>> ParquetRows<I> {
    pub(super) fn new(files: I) -> Self {
        ParquetRows {
            files,
            reader: None,
            batch: None,
            row: 0,
        }
    }

    /// The next row: its batch (shared, not copied) and its position there.
    pub(super) fn next_row(&mut self) -> Result<Option<(RecordBatch, usize)>, RecorderError> {
        loop {
            if let Some(b) = &self.batch
                && self.row < b.num_rows()
            {
                self.row += 1;
                return Ok(Some((b.clone(), self.row - 1)));
            }
            self.batch = None;
            self.row = 0;
            if let Some((path, reader)) = &mut self.reader {
                match reader.next() {
                    Some(b) => {
                        self.batch = Some(b.map_err(|e| RecorderError::Parquet {
                            path: path.clone(),
                            detail: e.to_string(),
                        })?);
                        continue;
                    }
                    None => self.reader = None,
                }
            }
            let Some(path) = self.files.next() else {
                return Ok(None);
            };
            let file = File::open(&path).map_err(|e| RecorderError::io(&path, e))?;
            let reader = ParquetRecordBatchReaderBuilder::try_new(file)
                .and_then(ParquetRecordBatchReaderBuilder::build)
                .map_err(|e| RecorderError::parquet(&path, &e))?;
            self.reader = Some((path, reader));
        }
    }
}

/// The non-blank lines of a JSON-lines file, parsed one at a time.
pub(super) struct JsonLines {
    path: PathBuf,
    lines: std::io::Lines<BufReader<File>>,
}

impl JsonLines {
    pub(super) fn open(path: &Path) -> Result<Self, RecorderError> {
        let file = File::open(path).map_err(|e| RecorderError::io(path, e))?;
        Ok(JsonLines {
            path: path.to_owned(),
            lines: BufReader::new(file).lines(),
        })
    }

    /// The next value; `Err(text)` for a line that is not JSON (the parser's message), an I/O error as an
    /// error of the outer result.
    pub(super) fn next_value(&mut self) -> Result<Option<Result<Value, String>>, RecorderError> {
        for line in self.lines.by_ref() {
            let line = line.map_err(|e| RecorderError::io(&self.path, e))?;
            if line.trim().is_empty() {
                continue;
            }
            return Ok(Some(serde_json::from_str(&line).map_err(|e| e.to_string())));
        }
        Ok(None)
    }
}

/// What a merge takes from an input's provenance sidecar besides its episodes.
#[derive(Clone, Debug, Default)]
pub(super) struct ProvenanceHead {
    pub(super) video: Value,
    pub(super) config: Value,
    pub(super) sync: Value,
}

/// An input's provenance sidecar, read the way [`Provenance`] is (a file that does not parse as one is no
/// provenance at all), with its episode entries parsed when they are asked for.
pub(super) struct InputProvenance {
    pub(super) head: ProvenanceHead,
    path: PathBuf,
    /// The entries, read whole, when the list is not one entry per episode in index order (no sidecar
    /// phone2act writes is like that): only then does the merge hold an input's entries.
    unordered: Option<Vec<EpisodeSummary>>,
    stream: Option<EpisodeStream>,
    /// Position in the list of the next entry `stream` yields.
    next_position: u64,
}

/// The checks of a sidecar's `episodes` list: every entry must parse as an [`EpisodeSummary`]; none is kept.
struct EpisodeOrder {
    /// Entry `k` is episode `k`, for every `k`.
    positional: bool,
}

impl<'de> Deserialize<'de> for EpisodeOrder {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = EpisodeOrder;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a list of episodes")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<EpisodeOrder, A::Error> {
                let mut positional = true;
                let mut position = 0u64;
                while let Some(e) = seq.next_element::<EpisodeSummary>()? {
                    positional &= e.index == position;
                    position += 1;
                }
                Ok(EpisodeOrder { positional })
            }
        }
        d.deserialize_seq(V)
    }
}

/// [`Provenance`]'s fields with the same types (so the same files parse), the episodes checked, not kept.
#[derive(Deserialize)]
#[allow(dead_code)] // parsed to accept exactly the files `Provenance` accepts
struct ProvenanceCheck {
    software: String,
    version: String,
    format: String,
    video: Value,
    config: Value,
    sync: Value,
    episodes: EpisodeOrder,
    stats: BTreeMap<String, Aggregate>,
}

impl InputProvenance {
    /// The sidecar at `path`, or None when there is none or it does not parse as a [`Provenance`].
    pub(super) fn open(path: &Path) -> Option<Self> {
        let file = File::open(path).ok()?;
        let check: ProvenanceCheck = serde_json::from_reader(BufReader::new(file)).ok()?;
        let unordered = if check.episodes.positional {
            None
        } else {
            let p: Provenance = serde_json::from_slice(&fs::read(path).ok()?).ok()?;
            Some(p.episodes)
        };
        Some(InputProvenance {
            head: ProvenanceHead {
                video: check.video,
                config: check.config,
                sync: check.sync,
            },
            path: path.to_owned(),
            unordered,
            stream: None,
            next_position: 0,
        })
    }

    /// The station the sidecar's configuration names, empty when none.
    pub(super) fn station(&self) -> &str {
        self.head.config["station_id"].as_str().unwrap_or_default()
    }

    /// The entry of episode `index` if its length is `length`. Episodes are asked for in index order, so a
    /// list in index order is read once, front to back.
    pub(super) fn episode(
        &mut self,
        index: u64,
        length: u64,
    ) -> Result<Option<EpisodeSummary>, RecorderError> {
        let same = |e: &&EpisodeSummary| e.index == index && e.length_frames == length;
        if let Some(list) = &self.unordered {
            return Ok(usize::try_from(index)
                .ok()
                .and_then(|i| list.get(i))
                .filter(same)
                .or_else(|| list.iter().find(same))
                .cloned());
        }
        if index < self.next_position {
            // Asked out of order (never, in a merge): start the list again.
            self.stream = None;
            self.next_position = 0;
        }
        if self.stream.is_none() {
            self.stream = Some(EpisodeStream::spawn(&self.path)?);
        }
        let stream = self.stream.as_mut().expect("just started");
        while self.next_position < index {
            stream.next(&self.path)?;
            self.next_position += 1;
        }
        let found = stream.next(&self.path)?;
        self.next_position += 1;
        Ok(found.filter(|e| same(&e)))
    }
}

/// A sidecar's episode entries, parsed by a thread of their own and handed over through a bounded channel:
/// serde pushes a list's elements, the merge pulls them one episode at a time.
struct EpisodeStream {
    rx: Option<Receiver<Result<EpisodeSummary, String>>>,
    thread: Option<JoinHandle<()>>,
}

/// Entries parsed ahead of the merge.
const STREAM_AHEAD: usize = 64;

impl EpisodeStream {
    fn spawn(path: &Path) -> Result<Self, RecorderError> {
        let file = File::open(path).map_err(|e| RecorderError::io(path, e))?;
        let (tx, rx) = sync_channel(STREAM_AHEAD);
        let thread = std::thread::Builder::new()
            .name("merge-provenance".into())
            .spawn(move || {
                let mut de = serde_json::Deserializer::from_reader(BufReader::new(file));
                if let Err(e) = SendEpisodes(&tx).deserialize(&mut de) {
                    // A closed channel (the merge stopped asking) is not worth reporting.
                    let _ = tx.send(Err(e.to_string()));
                }
            })
            .map_err(|e| RecorderError::io(path, e))?;
        Ok(EpisodeStream {
            rx: Some(rx),
            thread: Some(thread),
        })
    }

    /// The next entry, None past the end.
    fn next(&mut self, path: &Path) -> Result<Option<EpisodeSummary>, RecorderError> {
        match self.rx.as_ref().map(Receiver::recv) {
            Some(Ok(Ok(e))) => Ok(Some(e)),
            Some(Ok(Err(detail))) => Err(RecorderError::CorruptDataset {
                root: path.to_owned(),
                detail: format!("provenance changed during the merge: {detail}"),
            }),
            _ => Ok(None),
        }
    }
}

impl Drop for EpisodeStream {
    fn drop(&mut self) {
        // Closing the channel makes the parser's next send fail, which ends its thread.
        self.rx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Parses a provenance file, sending each element of its `episodes` list and skipping every other field.
struct SendEpisodes<'a>(&'a SyncSender<Result<EpisodeSummary, String>>);

impl<'de> DeserializeSeed<'de> for SendEpisodes<'_> {
    type Value = ();
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de> Visitor<'de> for SendEpisodes<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a provenance object")
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(key) = map.next_key::<String>()? {
            if key == "episodes" {
                map.next_value_seed(SendList(self.0))?;
            } else {
                map.next_value::<IgnoredAny>()?;
            }
        }
        Ok(())
    }
}

struct SendList<'a>(&'a SyncSender<Result<EpisodeSummary, String>>);

impl<'de> DeserializeSeed<'de> for SendList<'_> {
    type Value = ();
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for SendList<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a list of episodes")
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        while let Some(e) = seq.next_element::<EpisodeSummary>()? {
            self.0
                .send(Ok(e))
                .map_err(|_| de::Error::custom("the merge stopped reading"))?;
        }
        Ok(())
    }
}

/// The merged dataset's provenance entries, written to a file in the output directory as they are made, in
/// the exact text they take inside `meta/phone2act_provenance.json`; [`ProvenanceSpool::finish`] splices them
/// into the sidecar.
pub(super) struct ProvenanceSpool {
    path: PathBuf,
    out: BufWriter<File>,
    entries: u64,
}

/// The spool's name in the output directory (removed before the output is renamed into place).
const SPOOL_FILE: &str = ".provenance-episodes.spool";

/// Four-space indent of an entry of the sidecar's `episodes` list (depth 2 in the file).
const ENTRY_INDENT: &str = "        ";

impl ProvenanceSpool {
    pub(super) fn create(dst: &Path) -> Result<Self, RecorderError> {
        let path = dst.join(SPOOL_FILE);
        let file = File::create(&path).map_err(|e| RecorderError::io(&path, e))?;
        Ok(ProvenanceSpool {
            path,
            out: BufWriter::new(file),
            entries: 0,
        })
    }

    /// Appends `e` as the pretty printer writes an element of a list at depth 2: after a newline (and a
    /// comma past the first), each of its lines indented by two levels (JSON strings hold no raw newline, so
    /// every newline in the text is the printer's).
    pub(super) fn push(&mut self, e: &EpisodeSummary) -> Result<(), RecorderError> {
        let text = String::from_utf8(pretty(e)).expect("serde_json writes UTF-8");
        let sep = if self.entries == 0 { "\n" } else { ",\n" };
        let mut chunk = String::with_capacity(text.len() * 2);
        chunk.push_str(sep);
        chunk.push_str(ENTRY_INDENT);
        chunk.push_str(&text.replace('\n', &format!("\n{ENTRY_INDENT}")));
        self.out
            .write_all(chunk.as_bytes())
            .map_err(|err| RecorderError::io(&self.path, err))?;
        self.entries += 1;
        Ok(())
    }

    /// Writes `provenance` (whose `episodes` are empty) to `to` pretty-printed, with the spooled entries as
    /// its `episodes`, the same bytes as printing it with every entry in its list; removes the spool.
    pub(super) fn finish(self, provenance: &Provenance, to: &Path) -> Result<(), RecorderError> {
        let ProvenanceSpool { path, out, entries } = self;
        drop(
            out.into_inner()
                .map_err(|e| RecorderError::io(&path, e.into_error()))?,
        );
        debug_assert!(provenance.episodes.is_empty());
        let text = pretty(provenance);
        // Top-level keys are the only ones after a newline and exactly four spaces.
        let key = b"\n    \"episodes\": []";
        let at = text
            .windows(key.len())
            .position(|w| w == key)
            .expect("provenance prints its episodes list")
            + key.len()
            - 1;
        let write = || -> std::io::Result<()> {
            let mut w = BufWriter::new(File::create(to)?);
            w.write_all(&text[..at])?;
            if entries > 0 {
                std::io::copy(&mut File::open(&path)?, &mut w)?;
                w.write_all(b"\n    ")?;
            }
            w.write_all(&text[at..])?;
            w.flush()
        };
        write().map_err(|e| RecorderError::io(to, e))?;
        fs::remove_file(&path).map_err(|e| RecorderError::io(&path, e))
    }
}

/// A value as the pretty printer writes it, for tests comparing a spliced sidecar with it.
#[cfg(test)]
pub(super) fn pretty_string<T: serde::Serialize>(v: &T) -> String {
    String::from_utf8(pretty(v)).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::MergedFrom;

    fn entry(i: u64) -> EpisodeSummary {
        EpisodeSummary {
            index: i,
            task: format!("task \"{i}\"\nwith a newline"),
            length_frames: 10 + i,
            duration_s: 0.1 * i as f64 + 1.0 / 3.0,
            policies: if i.is_multiple_of(2) {
                vec!["pi0".into(), "act".into()]
            } else {
                Vec::new()
            },
            success: i.is_multiple_of(3).then_some(true),
            merged_from: Some(MergedFrom {
                dataset: "s3://b/station-1".into(),
                episode_index: i,
            }),
            station_id: "st".into(),
            ..EpisodeSummary::default()
        }
    }

    fn provenance(episodes: Vec<EpisodeSummary>) -> Provenance {
        let mut stats = BTreeMap::new();
        stats.insert("action".to_owned(), Aggregate::default());
        Provenance {
            software: "phone2act-recorder".into(),
            version: "1".into(),
            format: "v3.0".into(),
            video: serde_json::json!({"codec": "av1"}),
            config: serde_json::json!({"merged_from": [{"dataset": "a", "episodes": 3}]}),
            sync: Value::Null,
            episodes,
            stats,
        }
    }

    /// The spliced sidecar is byte for byte the pretty printing of the whole provenance, with no entry, one,
    /// and several (entries with nested lists, objects, escapes).
    #[test]
    fn spooled_provenance_is_the_same_bytes_as_printing_it_whole() {
        let dir = tempfile::tempdir().unwrap();
        for n in [0, 1, 5] {
            let entries: Vec<EpisodeSummary> = (0..n).map(entry).collect();
            let mut spool = ProvenanceSpool::create(dir.path()).unwrap();
            for e in &entries {
                spool.push(e).unwrap();
            }
            let to = dir.path().join("prov.json");
            spool.finish(&provenance(Vec::new()), &to).unwrap();
            assert_eq!(
                fs::read_to_string(&to).unwrap(),
                pretty_string(&provenance(entries)),
                "{n} entries"
            );
            assert!(!dir.path().join(SPOOL_FILE).exists());
        }
    }

    /// Entries come back one by one as the whole list would give them, in order and asked with gaps, from a
    /// list in index order and from one that is not.
    #[test]
    fn input_provenance_finds_the_entries_the_whole_list_would() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.json");
        let ordered: Vec<EpisodeSummary> = (0..200).map(entry).collect();
        let mut shuffled = ordered.clone();
        shuffled.swap(3, 150);
        shuffled.remove(7);
        for list in [ordered, shuffled] {
            let text = pretty_string(&provenance(list));
            fs::write(&path, &text).unwrap();
            // What the whole list gives is the list as parsed from the file.
            let list = serde_json::from_str::<Provenance>(&text).unwrap().episodes;
            let mut p = InputProvenance::open(&path).unwrap();
            assert_eq!(p.station(), "");
            for i in (0..210u64).filter(|i| !(i + 1).is_multiple_of(5)) {
                let want = list.iter().find(|e| e.index == i).cloned();
                let length = want.as_ref().map_or(10 + i, |e| e.length_frames);
                assert_eq!(p.episode(i, length).unwrap(), want, "episode {i}");
            }
            assert_eq!(p.episode(2, 999).unwrap(), None, "a length that differs");
        }
        fs::write(&path, "{\"software\": 1}").unwrap();
        assert!(
            InputProvenance::open(&path).is_none(),
            "a file Provenance does not parse is none"
        );
    }
}

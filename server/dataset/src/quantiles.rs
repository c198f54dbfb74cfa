//! Dataset-wide quantiles of the numeric parquet columns, kept as one [`QuantileSketch`] per dimension and
//! persisted beside the dataset (`meta/phone2act_quantiles.bin`, ignored by lerobot and GR00T), so that a
//! save merges one episode instead of re-reading every earlier one.
//!
//! The file is written into staging and renamed by the same commit journal as the episode, so it always
//! describes the committed episodes; it records how many episodes and frames it covers, and a dataset
//! whose file is missing, damaged or out of step (another writer, a copy without it) gets it rebuilt from
//! the parquet data at open.

use crate::error::RecorderError;
use crate::parquet_io;
use crate::stats::{ColumnStats, FeatureStats, QUANTILES, QuantileSketch};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Where the sketches live, relative to the dataset root.
pub const QUANTILES_FILE: &str = "meta/phone2act_quantiles.bin";
const MAGIC: &[u8; 8] = b"P2AQNT01";

/// Sketches of every numeric column over a number of committed episodes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct QuantileState {
    pub episodes: u64,
    pub frames: u64,
    /// Feature name → one sketch per dimension.
    pub columns: BTreeMap<String, Vec<QuantileSketch>>,
}

impl QuantileState {
    fn add(&mut self, frames: u64, columns: &[(&str, &ColumnStats)]) {
        for (name, c) in columns {
            let new = c.sketches();
            let dims = self.columns.entry((*name).to_owned()).or_default();
            if dims.is_empty() {
                dims.resize(new.len(), QuantileSketch::default());
            }
            for (d, s) in dims.iter_mut().zip(&new) {
                d.merge(s);
            }
        }
        self.episodes += 1;
        self.frames += frames;
    }
}

/// The dataset's quantile state.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct QuantileStore {
    pub current: QuantileState,
}

impl QuantileStore {
    /// Adds one episode's columns (each holding that episode's values).
    pub fn add_episode(&mut self, frames: u64, columns: &[(&str, &ColumnStats)]) {
        self.current.add(frames, columns);
    }

    /// Replaces the quantiles of `stats` (feature `name`) with the dataset's, if this store sketches it.
    pub fn apply(&self, name: &str, stats: &mut FeatureStats) {
        let Some(dims) = self.current.columns.get(name) else {
            return;
        };
        if dims.len() != stats.mean.len() || dims.iter().any(|d| d.count() != stats.count) {
            return;
        }
        let qs: Vec<f64> = QUANTILES.iter().map(|(q, _)| *q).collect();
        let per_dim: Vec<Vec<f64>> = dims.iter().map(|d| d.quantiles(&qs)).collect();
        stats.quantiles = (0..qs.len())
            .map(|qi| per_dim.iter().map(|v| v[qi]).collect())
            .collect();
    }

    /// The file's bytes: magic, then the current state, little-endian, closed by a 64-bit FNV-1a checksum
    /// of everything before it.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        encode_state(&mut out, &self.current);
        let sum = fnv1a(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// Parses [`QuantileStore::encode`]'s bytes; `None` if they are not exactly that.
    pub fn decode(bytes: &[u8]) -> Option<Self> {
        let (body, sum) = bytes.split_at_checked(bytes.len().checked_sub(8)?)?;
        if fnv1a(body) != u64::from_le_bytes(sum.try_into().ok()?) {
            return None;
        }
        let mut r = Reader(body.strip_prefix(MAGIC.as_slice())?);
        let current = decode_state(&mut r)?;
        r.0.is_empty().then_some(QuantileStore { current })
    }

    /// The persisted store of `root` if it covers exactly `episodes` episodes and `frames` frames.
    pub fn load(root: &Path, episodes: u64, frames: u64) -> Option<Self> {
        let store = Self::decode(&std::fs::read(root.join(QUANTILES_FILE)).ok()?)?;
        (store.current.episodes == episodes && store.current.frames == frames).then_some(store)
    }

    /// Rebuilds the store from the data files of the first `episodes` episodes (every `*.parquet` under
    /// `data/`, whatever the layout; rows of later episodes are left out).
    pub fn rebuild(root: &Path, episodes: u64) -> Result<Self, RecorderError> {
        let mut files = Vec::new();
        collect_parquet(&root.join("data"), &mut files);
        files.sort();
        let mut by_episode: BTreeMap<i64, Vec<parquet_io::Row>> = BTreeMap::new();
        for f in &files {
            for row in parquet_io::read_rows(f)? {
                if u64::try_from(row.episode_index).is_ok_and(|e| e < episodes) {
                    by_episode.entry(row.episode_index).or_default().push(row);
                }
            }
        }
        let mut store = QuantileStore::default();
        for rows in by_episode.into_values() {
            let cols = EpisodeColumns::from_rows(&rows);
            store.add_episode(rows.len() as u64, &cols.as_refs());
        }
        Ok(store)
    }
}

/// One episode's numeric columns, in the parquet's names.
pub struct EpisodeColumns(pub Vec<(&'static str, ColumnStats)>);

impl EpisodeColumns {
    fn from_rows(rows: &[parquet_io::Row]) -> Self {
        use crate::stats::StatKind::{Bool, Float, Int};
        let (sd, ad) = rows.first().map_or((0, 0), |r| (r.state.len(), r.action.len()));
        // The bool columns the rows carry (`next.success`, `intervention`), in the parquet's order.
        let mut flags: Vec<_> = [
            crate::parquet_io::SUCCESS_FEATURE,
            crate::parquet_io::INTERVENTION_FEATURE,
        ]
        .into_iter()
        .filter(|name| rows.first().is_some_and(|r| r.flag(name).is_some()))
        .map(|name| (name, ColumnStats::new(Bool, 1)))
        .collect();
        let mut c = [
            ("observation.state", ColumnStats::new(Float, sd)),
            ("action", ColumnStats::new(Float, ad)),
            ("timestamp", ColumnStats::new(Float, 1)),
            ("frame_index", ColumnStats::new(Int, 1)),
            ("episode_index", ColumnStats::new(Int, 1)),
            ("index", ColumnStats::new(Int, 1)),
            ("task_index", ColumnStats::new(Int, 1)),
        ];
        for r in rows {
            c[0].1.push_f32(&r.state);
            c[1].1.push_f32(&r.action);
            c[2].1.push_f32(&[r.timestamp]);
            for (i, v) in [r.frame_index, r.episode_index, r.index, r.task_index]
                .into_iter()
                .enumerate()
            {
                c[3 + i].1.push(&[v as f64]);
            }
            for (name, s) in &mut flags {
                s.push(&[f64::from(u8::from(r.flag(name).unwrap_or(false)))]);
            }
        }
        let mut columns: Vec<_> = c.into();
        columns.extend(flags);
        EpisodeColumns(columns)
    }

    pub fn as_refs(&self) -> Vec<(&str, &ColumnStats)> {
        self.0.iter().map(|(n, c)| (*n, c)).collect()
    }
}

fn collect_parquet(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(rd) = std::fs::read_dir(dir) else { return };
    for e in rd.flatten() {
        let p = e.path();
        if p.is_dir() {
            collect_parquet(&p, out);
        } else if p.extension().is_some_and(|x| x == "parquet") {
            out.push(p);
        }
    }
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn encode_state(out: &mut Vec<u8>, s: &QuantileState) {
    let u64s = |out: &mut Vec<u8>, v: u64| out.extend_from_slice(&v.to_le_bytes());
    u64s(out, s.episodes);
    u64s(out, s.frames);
    u64s(out, s.columns.len() as u64);
    for (name, dims) in &s.columns {
        u64s(out, name.len() as u64);
        out.extend_from_slice(name.as_bytes());
        u64s(out, dims.len() as u64);
        for d in dims {
            let (levels, count, bound, parity) = d.parts();
            for v in [count, bound, parity, levels.len() as u64] {
                u64s(out, v);
            }
            for l in levels {
                // Recorded values are float32 (state, action, timestamp) or small integers: stored in 4
                // bytes when that is exact, which halves the file.
                #[allow(clippy::float_cmp)] // exactness is the point
                let narrow = l.iter().all(|v| f64::from(*v as f32) == *v);
                u64s(out, l.len() as u64);
                out.push(if narrow { 4 } else { 8 });
                for v in l {
                    if narrow {
                        out.extend_from_slice(&(*v as f32).to_le_bytes());
                    } else {
                        out.extend_from_slice(&v.to_le_bytes());
                    }
                }
            }
        }
    }
}

struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Option<&[u8]> {
        let (head, rest) = self.0.split_at_checked(n)?;
        self.0 = rest;
        Some(head)
    }
    fn u8(&mut self) -> Option<u8> {
        self.take(1).map(|b| b[0])
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    /// A length that must fit in what is left (at `unit` bytes each), so a damaged file cannot make
    /// the reader allocate more than the file holds.
    fn len(&mut self, unit: usize) -> Option<usize> {
        let n = usize::try_from(self.u64()?).ok()?;
        (n.checked_mul(unit)? <= self.0.len()).then_some(n)
    }
}

fn decode_state(r: &mut Reader) -> Option<QuantileState> {
    let episodes = r.u64()?;
    let frames = r.u64()?;
    let mut columns = BTreeMap::new();
    for _ in 0..r.len(1)? {
        let n = r.len(1)?;
        let name = String::from_utf8(r.take(n)?.to_vec()).ok()?;
        let mut dims = Vec::new();
        for _ in 0..r.len(1)? {
            let (count, bound, parity) = (r.u64()?, r.u64()?, r.u64()?);
            let mut levels = Vec::new();
            for _ in 0..r.len(8)? {
                let n = r.len(4)?;
                let level = match r.u8()? {
                    4 => r
                        .take(n.checked_mul(4)?)?
                        .chunks_exact(4)
                        .map(|b| f64::from(f32::from_le_bytes(b.try_into().unwrap_or_default())))
                        .collect(),
                    8 => r
                        .take(n.checked_mul(8)?)?
                        .chunks_exact(8)
                        .map(|b| f64::from_le_bytes(b.try_into().unwrap_or_default()))
                        .collect(),
                    _ => return None,
                };
                levels.push(level);
            }
            dims.push(QuantileSketch::from_parts(levels, count, bound, parity)?);
        }
        columns.insert(name, dims);
    }
    Some(QuantileState {
        episodes,
        frames,
        columns,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::StatKind;

    fn episode(offset: usize, len: usize) -> ColumnStats {
        let mut c = ColumnStats::new(StatKind::Float, 2);
        for i in 0..len {
            let x = (offset + i) as f64;
            c.push(&[x, (x * 0.37).sin()]);
        }
        c
    }

    #[test]
    fn store_round_trips_and_rejects_damage() {
        let mut store = QuantileStore::default();
        store.add_episode(3000, &[("action", &episode(0, 3000))]);
        store.add_episode(2500, &[("action", &episode(3000, 2500))]);
        let bytes = store.encode();
        let back = QuantileStore::decode(&bytes).unwrap();
        assert_eq!(back.current, store.current);
        for cut in [0, 8, bytes.len() / 2, bytes.len() - 1] {
            assert_eq!(QuantileStore::decode(&bytes[..cut]), None, "truncated at {cut}");
        }
        let mut flipped = bytes.clone();
        flipped[bytes.len() / 3] ^= 0x10;
        assert_eq!(QuantileStore::decode(&flipped), None);
    }
}

//! Feature statistics the way lerobot computes them: per episode min, max, mean, population std, count and
//! the 1/10/50/90/99 % quantiles; across episodes min of mins, max of maxes, count-weighted mean and pooled
//! variance. Images are per channel in 0..1 with shape (3,1,1), over frames sampled once per second and
//! strided to about 150 px, from 256-bin histograms (exact for 8-bit pixels); their dataset quantiles are
//! the count-weighted mean of the episodes' (what lerobot's `aggregate_stats` does).
//!
//! Dataset quantiles of numeric features are not averaged: an average of per-episode quantiles is not a
//! quantile of the dataset (4 episodes gave `index` q01 112 where the data's is 3). They come from a
//! [`QuantileSketch`] per dimension, merged episode by episode: exact (numpy's default linear interpolation)
//! while a column holds at most [`SKETCH_LEVEL_CAPACITY`] values, and beyond that within a rank error the
//! sketch tracks and that stays below 0.5 % of the count for any dataset under 2^32 frames.

use crate::frame::Frame;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// Quantiles lerobot (>= 0.4) stores, with their key names.
pub const QUANTILES: [(f64, &str); 5] = [
    (0.01, "q01"),
    (0.10, "q10"),
    (0.50, "q50"),
    (0.90, "q90"),
    (0.99, "q99"),
];

/// How a feature's stats are serialised.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum StatKind {
    /// float32 vectors and scalars: everything as floats.
    Float,
    /// int64 scalars: min and max as integers.
    Int,
    /// bool scalars (`next.success`, `intervention`): min and max as booleans in v2.1 (lerobot 0.3) and as
    /// floats of 0/1 in v3.0 (lerobot 0.6, see [`FeatureStats::to_json_v30`]), the rest as floats of 0/1.
    Bool,
    /// Video/image: every entry shaped (3,1,1).
    Image,
}

/// Stats of one feature (one episode, or aggregated).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureStats {
    pub kind: StatKind,
    pub min: Vec<f64>,
    pub max: Vec<f64>,
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
    pub count: u64,
    /// One vector per entry of [`QUANTILES`].
    pub quantiles: Vec<Vec<f64>>,
}

fn wrap(kind: StatKind, v: &[f64]) -> Value {
    match kind {
        StatKind::Float => json!(v),
        StatKind::Int => json!(v.iter().map(|x| x.round() as i64).collect::<Vec<_>>()),
        StatKind::Bool => json!(v.iter().map(|x| *x >= 0.5).collect::<Vec<_>>()),
        StatKind::Image => Value::Array(v.iter().map(|x| json!([[x]])).collect()),
    }
}

impl FeatureStats {
    /// lerobot v3.0 `stats.json` entry: min, max, mean, std, count, q01..q99.
    pub fn to_json_v30(&self) -> Value {
        let mut m = serde_json::Map::new();
        // lerobot 0.6 computes a bool column's stats on it cast to float (`RunningQuantileStats.update`), so
        // its min and max are 0.0 / 1.0; lerobot 0.3 (v2.1) keeps numpy's bool min and max.
        let extremes = if self.kind == StatKind::Bool {
            StatKind::Float
        } else {
            self.kind
        };
        m.insert("min".into(), wrap(extremes, &self.min));
        m.insert("max".into(), wrap(extremes, &self.max));
        let k = if self.kind == StatKind::Image {
            StatKind::Image
        } else {
            StatKind::Float
        };
        m.insert("mean".into(), wrap(k, &self.mean));
        m.insert("std".into(), wrap(k, &self.std));
        m.insert("count".into(), json!([self.count]));
        for ((_, name), q) in QUANTILES.iter().zip(&self.quantiles) {
            m.insert((*name).into(), wrap(k, q));
        }
        Value::Object(m)
    }

    /// lerobot v2.1 `episodes_stats.jsonl` entry: min, max, mean, std, count.
    pub fn to_json_v21(&self) -> Value {
        let k = if self.kind == StatKind::Image {
            StatKind::Image
        } else {
            StatKind::Float
        };
        json!({
            "min": wrap(self.kind, &self.min),
            "max": wrap(self.kind, &self.max),
            "mean": wrap(k, &self.mean),
            "std": wrap(k, &self.std),
            "count": [self.count],
        })
    }

    /// GR00T `stats.json` entry: exactly mean, std, min, max, q01, q99 (plain float lists).
    pub fn to_json_gr00t(&self) -> Value {
        json!({
            "mean": self.mean, "std": self.std, "min": self.min, "max": self.max,
            "q01": self.quantiles[0], "q99": self.quantiles[4],
        })
    }
}

/// Linear-interpolated quantile of sorted data (numpy's default method).
fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// Values a sketch level holds before it is compacted. The worst-case rank error is at most
/// `levels · count / SKETCH_LEVEL_CAPACITY` with `levels ≤ log2(count / capacity) + 1`, i.e. ≤ 20/4096 < 0.5 %
/// up to 2^32 values; the persisted size is at most `levels · capacity` values per dimension.
pub const SKETCH_LEVEL_CAPACITY: usize = 4096;

/// A deterministic, mergeable quantile summary of one dimension (a multi-level compactor: level `h` holds
/// values of weight `2^h`, sorted above level 0). Until a level overflows nothing is dropped and quantiles are exact. A
/// compaction sorts a full level and promotes every other value (alternating which half, so that the
/// errors of successive compactions tend to cancel); it moves any rank by at most the level's weight, and
/// [`QuantileSketch::rank_error_bound`] is the sum of those weights: a proven bound, not an estimate.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct QuantileSketch {
    levels: Vec<Vec<f64>>,
    count: u64,
    rank_error_bound: u64,
    /// Bit `h`: which half the next compaction of level `h` keeps.
    parity: u64,
}

impl QuantileSketch {
    /// An exact sketch of `values` (one episode's column).
    pub fn from_values(values: &[f64]) -> Self {
        let mut s = QuantileSketch {
            levels: vec![values.to_vec()],
            count: values.len() as u64,
            rank_error_bound: 0,
            parity: 0,
        };
        s.compact();
        s
    }

    /// Rebuilds a sketch from its parts (see [`QuantileSketch::parts`]); `None` if they are inconsistent.
    pub fn from_parts(
        mut levels: Vec<Vec<f64>>,
        count: u64,
        rank_error_bound: u64,
        parity: u64,
    ) -> Option<Self> {
        for l in levels.iter_mut().skip(1) {
            if !l.is_sorted_by(|a, b| a.total_cmp(b).is_le()) {
                l.sort_by(f64::total_cmp);
            }
        }
        let weight: u128 = levels
            .iter()
            .enumerate()
            .map(|(h, l)| (l.len() as u128) << h)
            .sum();
        (levels.len() < 64 && weight == u128::from(count)).then_some(QuantileSketch {
            levels,
            count,
            rank_error_bound,
            parity,
        })
    }

    /// The levels, count, rank error bound and parity bits, for persisting.
    pub fn parts(&self) -> (&[Vec<f64>], u64, u64, u64) {
        (&self.levels, self.count, self.rank_error_bound, self.parity)
    }

    /// Number of values summarised.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Worst-case distance, in ranks, between a value this sketch returns for rank `r` and the true
    /// order statistic `r` (0 while the sketch is exact).
    pub fn rank_error_bound(&self) -> u64 {
        self.rank_error_bound
    }

    /// Adds everything `other` summarises.
    pub fn merge(&mut self, other: &QuantileSketch) {
        if self.levels.len() < other.levels.len() {
            self.levels.resize(other.levels.len(), Vec::new());
        }
        for (h, (mine, theirs)) in self.levels.iter_mut().zip(&other.levels).enumerate() {
            if h == 0 {
                mine.extend_from_slice(theirs);
            } else {
                merge_sorted(mine, theirs);
            }
        }
        self.count += other.count;
        self.rank_error_bound += other.rank_error_bound;
        self.compact();
    }

    fn compact(&mut self) {
        let mut h = 0;
        while h < self.levels.len() {
            if self.levels[h].len() > SKETCH_LEVEL_CAPACITY {
                let level = &mut self.levels[h];
                if h == 0 {
                    level.sort_by(f64::total_cmp);
                }
                // An odd value out stays at this level; the rest pair up.
                let keep = level.len() % 2;
                let offset = usize::from(self.parity >> h & 1 == 1);
                self.parity ^= 1 << h;
                let promoted: Vec<f64> = level[keep..].iter().skip(offset).step_by(2).copied().collect();
                level.truncate(keep);
                if self.levels.len() == h + 1 {
                    self.levels.push(Vec::new());
                }
                merge_sorted(&mut self.levels[h + 1], &promoted);
                self.rank_error_bound += 1 << h;
            }
            h += 1;
        }
    }

    /// The summarised values with their weights, sorted by value (the levels above 0 are sorted already,
    /// so this is a sort of at most one level and a merge: a few ms per save for a long dataset).
    fn weighted(&self) -> Vec<(f64, u64)> {
        let mut items: Vec<(f64, u64)> = Vec::new();
        for (h, level) in self.levels.iter().enumerate() {
            let mut run: Vec<(f64, u64)> = level.iter().map(|v| (*v, 1u64 << h)).collect();
            if h == 0 {
                run.sort_by(|a, b| a.0.total_cmp(&b.0));
            }
            merge_sorted_by(&mut items, &run, |x| x.0);
        }
        items
    }

    /// Quantiles by numpy's default method (linear interpolation between order statistics `⌊q(n−1)⌋` and
    /// `⌈q(n−1)⌉`), each order statistic read from the sketch. 0 for an empty sketch.
    pub fn quantiles(&self, qs: &[f64]) -> Vec<f64> {
        let items = self.weighted();
        let mut cumulative = Vec::with_capacity(items.len());
        let mut acc = 0u64;
        for (_, w) in &items {
            acc += w;
            cumulative.push(acc);
        }
        let at_rank = |r: u64| -> f64 {
            let i = cumulative.partition_point(|c| *c <= r).min(items.len() - 1);
            items[i].0
        };
        qs.iter()
            .map(|q| {
                if self.count == 0 {
                    return 0.0;
                }
                let pos = q.clamp(0.0, 1.0) * (self.count - 1) as f64;
                let (lo, hi) = (pos.floor(), pos.ceil());
                let (a, b) = (at_rank(lo as u64), at_rank(hi as u64));
                a + (b - a) * (pos - lo)
            })
            .collect()
    }
}

/// Merges the sorted `run` into the sorted `into`.
fn merge_sorted(into: &mut Vec<f64>, run: &[f64]) {
    merge_sorted_by(into, run, |x| *x);
}

/// Merges `run` into `into`, both sorted by `key`.
fn merge_sorted_by<T: Copy>(into: &mut Vec<T>, run: &[T], key: impl Fn(&T) -> f64) {
    if run.is_empty() {
        return;
    }
    let mut out = Vec::with_capacity(into.len() + run.len());
    let (mut i, mut j) = (0, 0);
    while i < into.len() && j < run.len() {
        if key(&into[i]).total_cmp(&key(&run[j])).is_le() {
            out.push(into[i]);
            i += 1;
        } else {
            out.push(run[j]);
            j += 1;
        }
    }
    out.extend_from_slice(&into[i..]);
    out.extend_from_slice(&run[j..]);
    *into = out;
}

/// Collects the values of one numeric feature over one episode (bounded by the episode length).
#[derive(Clone, Debug)]
pub struct ColumnStats {
    kind: StatKind,
    columns: Vec<Vec<f64>>,
}

impl ColumnStats {
    pub fn new(kind: StatKind, dims: usize) -> Self {
        ColumnStats {
            kind,
            columns: vec![Vec::new(); dims],
        }
    }

    pub fn dims(&self) -> usize {
        self.columns.len()
    }

    pub fn push(&mut self, row: &[f64]) {
        for (c, v) in self.columns.iter_mut().zip(row) {
            c.push(*v);
        }
    }

    pub fn push_f32(&mut self, row: &[f32]) {
        for (c, v) in self.columns.iter_mut().zip(row) {
            c.push(f64::from(*v));
        }
    }

    pub fn clear(&mut self) {
        for c in &mut self.columns {
            c.clear();
        }
    }

    /// An exact sketch of each dimension's values.
    pub fn sketches(&self) -> Vec<QuantileSketch> {
        self.columns
            .iter()
            .map(|c| QuantileSketch::from_values(c))
            .collect()
    }

    pub fn finish(&self) -> FeatureStats {
        let count = self.columns.first().map_or(0, Vec::len) as u64;
        let mut s = FeatureStats {
            kind: self.kind,
            min: Vec::new(),
            max: Vec::new(),
            mean: Vec::new(),
            std: Vec::new(),
            count,
            quantiles: vec![Vec::new(); QUANTILES.len()],
        };
        for col in &self.columns {
            let mut sorted = col.clone();
            sorted.sort_by(f64::total_cmp);
            let n = sorted.len().max(1) as f64;
            let mean = sorted.iter().sum::<f64>() / n;
            let var = sorted.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
            s.min.push(sorted.first().copied().unwrap_or(0.0));
            s.max.push(sorted.last().copied().unwrap_or(0.0));
            s.mean.push(mean);
            s.std.push(var.sqrt());
            for (i, (q, _)) in QUANTILES.iter().enumerate() {
                s.quantiles[i].push(quantile_sorted(&sorted, *q));
            }
        }
        s
    }
}

/// Per-channel pixel histograms over sampled frames of one episode.
#[derive(Clone, Debug)]
pub struct ImageStats {
    sample_every: u64,
    hist: [[u64; 256]; 3],
    frames: u64,
}

impl ImageStats {
    /// Samples one frame per second at `fps`.
    pub fn new(fps: u32) -> Self {
        ImageStats {
            sample_every: u64::from(fps.max(1)),
            hist: [[0; 256]; 3],
            frames: 0,
        }
    }

    /// Adds frame `index` if it is a sampled one.
    pub fn observe(&mut self, index: u64, frame: &Frame) {
        if !index.is_multiple_of(self.sample_every) {
            return;
        }
        let (w, h) = (frame.width as usize, frame.height as usize);
        if frame.rgb.len() < w * h * 3 {
            return;
        }
        let step = (w.max(h) / 150).max(1);
        for y in (0..h).step_by(step) {
            for x in (0..w).step_by(step) {
                let i = (y * w + x) * 3;
                for c in 0..3 {
                    self.hist[c][frame.rgb[i + c] as usize] += 1;
                }
            }
        }
        self.frames += 1;
    }

    /// Adds the frames `other` sampled.
    pub fn merge(&mut self, other: &ImageStats) {
        for (mine, theirs) in self.hist.iter_mut().zip(&other.hist) {
            for (m, t) in mine.iter_mut().zip(theirs) {
                *m += t;
            }
        }
        self.frames += other.frames;
    }

    /// Stats in 0..1, `count` = sampled frames.
    pub fn finish(&self) -> FeatureStats {
        let mut s = FeatureStats {
            kind: StatKind::Image,
            min: Vec::new(),
            max: Vec::new(),
            mean: Vec::new(),
            std: Vec::new(),
            count: self.frames,
            quantiles: vec![Vec::new(); QUANTILES.len()],
        };
        for h in &self.hist {
            let n: u64 = h.iter().sum();
            let nf = n.max(1) as f64;
            let val = |i: usize| i as f64 / 255.0;
            let mean = h.iter().enumerate().map(|(i, c)| val(i) * *c as f64).sum::<f64>() / nf;
            let var = h
                .iter()
                .enumerate()
                .map(|(i, c)| (val(i) - mean).powi(2) * *c as f64)
                .sum::<f64>()
                / nf;
            s.min.push(h.iter().position(|c| *c > 0).map_or(0.0, val));
            s.max.push(h.iter().rposition(|c| *c > 0).map_or(0.0, val));
            s.mean.push(mean);
            s.std.push(var.sqrt());
            for (qi, (q, _)) in QUANTILES.iter().enumerate() {
                // Nearest rank on the histogram: pixel values are 8-bit, so this is exact up to a bin.
                let target = (q * n as f64).ceil().max(1.0) as u64;
                let mut acc = 0;
                let mut v = 0.0;
                for (i, c) in h.iter().enumerate() {
                    acc += c;
                    if acc >= target {
                        v = val(i);
                        break;
                    }
                }
                s.quantiles[qi].push(v);
            }
        }
        s
    }
}

/// Running aggregate of per-episode stats (what lerobot's `aggregate_stats` computes), small and
/// serialisable so that resuming a dataset does not need to reread every episode. Its quantiles are
/// lerobot's count-weighted mean: kept for images; numeric columns take theirs from a [`QuantileSketch`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Aggregate {
    pub kind: Option<StatKind>,
    pub count: u64,
    pub min: Vec<f64>,
    pub max: Vec<f64>,
    /// Σ n·mean
    pub sum_mean: Vec<f64>,
    /// Σ n·(var + mean²)
    pub sum_sq: Vec<f64>,
    /// Σ n·q per quantile (lerobot's aggregate, not a quantile of the data)
    pub sum_q: Vec<Vec<f64>>,
}

impl Aggregate {
    pub fn add(&mut self, s: &FeatureStats) {
        if s.count == 0 {
            return;
        }
        let n = s.count as f64;
        if self.count == 0 {
            self.kind = Some(s.kind);
            self.min.clone_from(&s.min);
            self.max.clone_from(&s.max);
            self.sum_mean = vec![0.0; s.mean.len()];
            self.sum_sq = vec![0.0; s.mean.len()];
            self.sum_q = vec![vec![0.0; s.mean.len()]; QUANTILES.len()];
        }
        for i in 0..s.mean.len().min(self.sum_mean.len()) {
            self.min[i] = self.min[i].min(s.min[i]);
            self.max[i] = self.max[i].max(s.max[i]);
            self.sum_mean[i] += n * s.mean[i];
            self.sum_sq[i] += n * (s.std[i] * s.std[i] + s.mean[i] * s.mean[i]);
            for (acc, q) in self.sum_q.iter_mut().zip(&s.quantiles) {
                acc[i] += n * q[i];
            }
        }
        self.count += s.count;
    }

    pub fn finish(&self) -> Option<FeatureStats> {
        let kind = self.kind?;
        let n = self.count.max(1) as f64;
        let mean: Vec<f64> = self.sum_mean.iter().map(|s| s / n).collect();
        let std = self
            .sum_sq
            .iter()
            .zip(&mean)
            .map(|(s, m)| (s / n - m * m).max(0.0).sqrt())
            .collect();
        Some(FeatureStats {
            kind,
            min: self.min.clone(),
            max: self.max.clone(),
            mean,
            std,
            count: self.count,
            quantiles: self
                .sum_q
                .iter()
                .map(|q| q.iter().map(|v| v / n).collect())
                .collect(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::sync::Arc;

    /// numpy.quantile(data, q) (method "linear") over sorted data.
    fn numpy_quantile(sorted: &[f64], q: f64) -> f64 {
        quantile_sorted(sorted, q)
    }

    /// Checks every order statistic the sketch is asked for against the sorted data: the value returned for
    /// rank r lies between the true order statistics r − bound and r + bound.
    fn check_ranks(sketch: &QuantileSketch, sorted: &[f64]) {
        let n = sorted.len();
        let b = usize::try_from(sketch.rank_error_bound()).unwrap();
        let qs: Vec<f64> = (0..=200).map(|i| f64::from(i) / 200.0).collect();
        for (q, got) in qs.iter().copied().zip(sketch.quantiles(&qs)) {
            let pos = q * (n - 1) as f64;
            let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
            let (min_ok, max_ok) = (sorted[lo.saturating_sub(b)], sorted[(hi + b).min(n - 1)]);
            assert!(
                min_ok <= got && got <= max_ok,
                "q={q}: {got} outside [{min_ok}, {max_ok}] (rank error bound {b} of {n})"
            );
            if b == 0 {
                assert!((got - numpy_quantile(sorted, q)).abs() <= 1e-12 * got.abs().max(1.0));
            }
        }
    }

    /// Episodes of a few kinds of column: smooth, discrete (a gripper), heavy-tailed, constant, integer ramp.
    fn column(kind: u8, seed: u64, len: usize, offset: usize) -> Vec<f64> {
        let mut x = seed | 1;
        (0..len)
            .map(|i| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let u = (x >> 11) as f64 / (1u64 << 53) as f64;
                match kind % 5 {
                    0 => (i as f64 * 0.05).sin() * 0.2 + u * 0.01,
                    1 => [0.0, 0.5, 1.0][(x % 3) as usize],
                    2 => (u.max(1e-9)).ln().powi(3),
                    3 => 0.25,
                    _ => (offset + i) as f64,
                }
            })
            .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        /// Merging episodes one by one (as saves do) keeps every quantile within the tracked bound of the
        /// dataset's true order statistics, exactly numpy's while the column fits a level, and the bound
        /// under 0.5 %.
        #[test]
        fn merged_sketch_stays_within_its_rank_bound(
            kind in 0u8..5,
            lens in proptest::collection::vec(1usize..6000, 1..12),
            seed in any::<u64>(),
        ) {
            let mut sketch = QuantileSketch::default();
            let mut all = Vec::new();
            for (e, len) in lens.iter().enumerate() {
                let values = column(kind, seed.wrapping_add(e as u64), *len, all.len());
                sketch.merge(&QuantileSketch::from_values(&values));
                all.extend(values);
            }
            all.sort_by(f64::total_cmp);
            prop_assert_eq!(sketch.count(), all.len() as u64);
            if all.len() <= SKETCH_LEVEL_CAPACITY {
                prop_assert_eq!(sketch.rank_error_bound(), 0);
            }
            prop_assert!(sketch.rank_error_bound() as f64 <= 0.005 * all.len() as f64);
            check_ranks(&sketch, &all);
        }
    }

    #[test]
    fn a_long_dataset_stays_under_half_a_percent() {
        // 1 M values (9 h at 30 fps) in 500 episodes of 2 000 frames: 9 levels.
        let mut sketch = QuantileSketch::default();
        let mut all = Vec::new();
        for e in 0..500u64 {
            let values = column(2, e * 7919 + 1, 2000, all.len());
            sketch.merge(&QuantileSketch::from_values(&values));
            all.extend(values);
        }
        all.sort_by(f64::total_cmp);
        let bound = sketch.rank_error_bound() as f64 / all.len() as f64;
        assert!(bound <= 0.005, "rank error bound {bound}");
        check_ranks(&sketch, &all);
        let retained: usize = sketch.parts().0.iter().map(Vec::len).sum();
        assert!(retained <= 10 * SKETCH_LEVEL_CAPACITY, "{retained} values kept");
    }

    #[test]
    fn sketch_parts_round_trip_and_reject_inconsistent_counts() {
        let s = QuantileSketch::from_values(&column(0, 3, 9000, 0));
        let (levels, count, bound, parity) = s.parts();
        let back = QuantileSketch::from_parts(levels.to_vec(), count, bound, parity).unwrap();
        assert_eq!(back, s);
        assert!(QuantileSketch::from_parts(levels.to_vec(), count + 1, bound, parity).is_none());
    }

    #[test]
    fn dataset_quantiles_are_not_an_average_of_episode_quantiles() {
        // The case: `index` over 4 episodes. numpy over all frames gives q01 = 3.08 for 4 x 77 rows.
        let mut sketch = QuantileSketch::default();
        for e in 0..4 {
            let idx: Vec<f64> = (e * 77..(e + 1) * 77).map(f64::from).collect();
            sketch.merge(&QuantileSketch::from_values(&idx));
        }
        let q = sketch.quantiles(&[0.01, 0.99]);
        assert!(
            (q[0] - 3.07).abs() < 1e-9 && (q[1] - 303.93).abs() < 1e-9,
            "{q:?}"
        );
    }

    #[test]
    fn column_stats_match_numpy() {
        let mut c = ColumnStats::new(StatKind::Float, 2);
        for i in 0..=100 {
            c.push(&[f64::from(i), -f64::from(i)]);
        }
        let s = c.finish();
        assert_eq!(s.count, 101);
        assert_eq!((s.min[0], s.max[0], s.mean[0]), (0.0, 100.0, 50.0));
        assert!((s.std[0] - 29.154_759_474_226_5).abs() < 1e-9);
        assert!((s.quantiles[0][0] - 1.0).abs() < 1e-12 && (s.quantiles[4][0] - 99.0).abs() < 1e-12);
        assert!((s.quantiles[2][1] + 50.0).abs() < 1e-12);
    }

    #[test]
    fn aggregate_pools_variance_like_lerobot() {
        let mut a = ColumnStats::new(StatKind::Float, 1);
        let mut b = ColumnStats::new(StatKind::Float, 1);
        let mut all = ColumnStats::new(StatKind::Float, 1);
        for i in 0..10 {
            a.push(&[f64::from(i)]);
            all.push(&[f64::from(i)]);
        }
        for i in 20..50 {
            b.push(&[f64::from(i)]);
            all.push(&[f64::from(i)]);
        }
        let mut agg = Aggregate::default();
        agg.add(&a.finish());
        agg.add(&b.finish());
        let (got, want) = (agg.finish().unwrap(), all.finish());
        assert_eq!(got.count, 40);
        assert!((got.mean[0] - want.mean[0]).abs() < 1e-9);
        assert!((got.std[0] - want.std[0]).abs() < 1e-9);
        assert_eq!((got.min[0], got.max[0]), (0.0, 49.0));
    }

    #[test]
    fn image_stats_are_per_channel_in_unit_range() {
        let mut s = ImageStats::new(10);
        let rgb: Vec<u8> = (0..16 * 16).flat_map(|_| [255u8, 0, 51]).collect();
        let f = Frame {
            width: 16,
            height: 16,
            rgb: Arc::new(rgb),
            capture_time_ns: 0,
            seq: 0,
        };
        for i in 0..25 {
            s.observe(i, &f);
        }
        let st = s.finish();
        assert_eq!(st.count, 3, "frames 0, 10, 20 are sampled");
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9);
        assert!(close(&st.mean, &[1.0, 0.0, 0.2]), "{:?}", st.mean);
        assert!(close(&st.std, &[0.0, 0.0, 0.0]));
        assert!(close(&st.quantiles[2], &[1.0, 0.0, 0.2]));
        let j = st.to_json_v30();
        assert_eq!(j["mean"][0], json!([[1.0]]));
        assert_eq!(j["mean"].as_array().unwrap().len(), 3);
        assert_eq!(j["count"], json!([3]));
    }
}

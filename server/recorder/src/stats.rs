//! Feature statistics the way lerobot computes them: per episode min, max, mean, population std, count and
//! the 1/10/50/90/99 % quantiles; across episodes min of mins, max of maxes, count-weighted mean, pooled
//! variance and count-weighted quantiles. Images are per channel in 0..1 with shape (3,1,1), over frames
//! sampled once per second and strided to about 150 px, from 256-bin histograms (exact for 8-bit pixels).

use crate::camera::Frame;
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
        StatKind::Image => Value::Array(v.iter().map(|x| json!([[x]])).collect()),
    }
}

impl FeatureStats {
    /// lerobot v3.0 `stats.json` entry: min, max, mean, std, count, q01..q99.
    pub fn to_json_v30(&self) -> Value {
        let mut m = serde_json::Map::new();
        m.insert("min".into(), wrap(self.kind, &self.min));
        m.insert("max".into(), wrap(self.kind, &self.max));
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
/// serialisable so that resuming a dataset does not need to reread every episode.
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
    /// Σ n·q per quantile
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
    use std::sync::Arc;

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

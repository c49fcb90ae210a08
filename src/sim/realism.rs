//! Realism statistics of range images, for comparing simulated scans with real
//! ones (KITTI HDL-64E): keep rate per row and per column, drop rate against the
//! range of the pixel's surroundings, the range histogram of returns, and the
//! share of returns per semantic class. The same estimators run on both sides,
//! so real dropped rays (which have no range) and simulated ones are treated alike.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::lidar::{RangeImage, SensorProfile, Strategy, kitti, project};

/// Width of a range bin, meters, and the number of bins (0-80 m).
pub const RANGE_BIN_M: f32 = 4.0;
pub const RANGE_BINS: usize = 20;

/// Groups a SemanticKITTI label (class in the low 16 bits; moving classes folded
/// onto their static class) into the classes the simulator produces.
pub fn class_group(label: u32) -> &'static str {
    match label & 0xffff {
        10 | 252 => "car",
        11 => "bicycle",
        30 | 254 => "person",
        31 | 253 => "bicyclist",
        40 | 60 => "road",
        48 => "sidewalk",
        44 | 49 => "parking/other-ground",
        50 => "building",
        51 => "fence",
        70 => "vegetation",
        71 => "trunk",
        72 => "terrain",
        80 => "pole",
        81 => "traffic-sign",
        13 | 15 | 16 | 18 | 20 | 255..=259 => "other-vehicle",
        _ => "other",
    }
}

/// Accumulated statistics over a set of range images of one size.
#[derive(Debug, Clone, PartialEq)]
pub struct RealismStats {
    pub name: String,
    pub height: usize,
    pub width: usize,
    pub scans: usize,
    row_kept: Vec<u64>,
    col_kept: Vec<u64>,
    pixel_kept: Vec<u32>,
    /// Per context-range bin: (pixels, dropped); the last bin holds pixels with no
    /// return anywhere around them (sky).
    context: Vec<(u64, u64)>,
    range_hist: Vec<u64>,
    classes: BTreeMap<&'static str, u64>,
    labelled_returns: u64,
    returns: u64,
}

impl RealismStats {
    pub fn new(name: &str, height: usize, width: usize) -> Self {
        RealismStats {
            name: name.into(),
            height,
            width,
            scans: 0,
            row_kept: vec![0; height],
            col_kept: vec![0; width],
            pixel_kept: vec![0; height * width],
            context: vec![(0, 0); RANGE_BINS + 1],
            range_hist: vec![0; RANGE_BINS],
            classes: BTreeMap::new(),
            labelled_returns: 0,
            returns: 0,
        }
    }

    /// Adds one range image (same size as the others). `labelled`: whether its
    /// labels are real SemanticKITTI labels (else the class share skips it).
    pub fn add(&mut self, image: &RangeImage, labelled: bool) {
        if image.height != self.height || image.width != self.width {
            return;
        }
        let (h, w) = (self.height, self.width);
        self.scans += 1;
        for k in 0..h * w {
            let (row, col) = (k / w, k % w);
            let kept = image.is_valid(k);
            let bin = match context_range(image, row, col) {
                Some(r) => ((r / RANGE_BIN_M) as usize).min(RANGE_BINS - 1),
                None => RANGE_BINS,
            };
            self.context[bin].0 += 1;
            if !kept {
                self.context[bin].1 += 1;
                continue;
            }
            self.row_kept[row] += 1;
            self.col_kept[col] += 1;
            self.pixel_kept[k] += 1;
            self.returns += 1;
            self.range_hist[((image.range_m[k] / RANGE_BIN_M) as usize).min(RANGE_BINS - 1)] += 1;
            if labelled {
                *self.classes.entry(class_group(image.label[k])).or_default() += 1;
                self.labelled_returns += 1;
            }
        }
    }

    /// Kept share of all pixels.
    pub fn keep_rate(&self) -> f64 {
        self.returns as f64 / (self.scans * self.height * self.width).max(1) as f64
    }

    /// Keep rate of each row (top first).
    pub fn row_keep(&self) -> Vec<f64> {
        let n = (self.scans * self.width).max(1) as f64;
        self.row_kept.iter().map(|&c| c as f64 / n).collect()
    }

    /// Keep rate of each column, averaged over `group` adjacent columns.
    pub fn column_keep(&self, group: usize) -> Vec<f64> {
        let n = (self.scans * self.height * group).max(1) as f64;
        self.col_kept
            .chunks(group.max(1))
            .map(|c| c.iter().sum::<u64>() as f64 / n)
            .collect()
    }

    /// Keep frequency of every pixel (row-major), the paper's per-pixel ray-drop prior.
    pub fn pixel_keep(&self) -> Vec<f64> {
        let n = self.scans.max(1) as f64;
        self.pixel_kept.iter().map(|&c| c as f64 / n).collect()
    }

    /// Mean keep rate of rows `rows`.
    pub fn rows_keep(&self, rows: std::ops::Range<usize>) -> f64 {
        let r = self.row_keep();
        let sel = &r[rows.start.min(r.len())..rows.end.min(r.len())];
        sel.iter().sum::<f64>() / sel.len().max(1) as f64
    }

    /// Drop rate per context-range bin (NaN where a bin is empty), then the sky bin.
    pub fn drop_vs_range(&self) -> Vec<f64> {
        self.context
            .iter()
            .map(|&(n, d)| {
                if n == 0 {
                    f64::NAN
                } else {
                    d as f64 / n as f64
                }
            })
            .collect()
    }

    /// Share of pixels per context-range bin (how often each range occurs).
    pub fn context_share(&self) -> Vec<f64> {
        let total = self.context.iter().map(|c| c.0).sum::<u64>().max(1) as f64;
        self.context.iter().map(|c| c.0 as f64 / total).collect()
    }

    /// Share of returns per range bin.
    pub fn range_histogram(&self) -> Vec<f64> {
        let n = self.returns.max(1) as f64;
        self.range_hist.iter().map(|&c| c as f64 / n).collect()
    }

    /// Share of labelled returns per class group (empty without labels).
    pub fn class_share(&self) -> BTreeMap<&'static str, f64> {
        let n = self.labelled_returns.max(1) as f64;
        self.classes
            .iter()
            .map(|(k, &v)| (*k, v as f64 / n))
            .collect()
    }
}

/// Median range of the valid pixels in the 3 x 9 window around (row, col), the
/// pixel itself excluded (so a dropped pixel is judged by its surroundings).
pub fn context_range(image: &RangeImage, row: usize, col: usize) -> Option<f32> {
    let (h, w) = (image.height, image.width);
    let mut v = [0f32; 27];
    let mut n = 0;
    for dr in -1i32..=1 {
        let r = row as i32 + dr;
        if r < 0 || r >= h as i32 {
            continue;
        }
        for dc in -4i32..=4 {
            if dr == 0 && dc == 0 {
                continue;
            }
            let c = (col as i32 + dc).rem_euclid(w as i32) as usize;
            let d = image.range_m[r as usize * w + c];
            if d > 0.0 {
                v[n] = d;
                n += 1;
            }
        }
    }
    if n == 0 {
        return None;
    }
    let s = &mut v[..n];
    s.sort_by(f32::total_cmp);
    Some(s[n / 2])
}

/// Real KITTI scans found under `dir` (any depth): every `velodyne/*.bin`, with
/// `labels/*.label` beside it when present. Sorted for reproducibility.
pub fn find_kitti_scans(dir: &Path) -> Vec<(PathBuf, Option<PathBuf>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "bin") {
                let label = p
                    .parent()
                    .and_then(|v| v.parent())
                    .zip(p.file_stem())
                    .map(|(seq, stem)| seq.join("labels").join(stem).with_extension("label"))
                    .filter(|l| l.exists());
                out.push((p, label));
            }
        }
    }
    out.sort();
    out
}

/// Reads and projects one real KITTI scan onto `profile` (KITTI ring order).
pub fn real_range_image(
    bin: &Path,
    labels: Option<&Path>,
    profile: &SensorProfile,
) -> Result<RangeImage, String> {
    let scan = kitti::read_scan(bin, labels).map_err(|e| e.to_string())?;
    project(&scan, profile, Strategy::Auto).map_err(|e| format!("{}: {e}", bin.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::AngleGrid;

    #[test]
    fn stats_count_rows_ranges_and_classes() {
        let angles = AngleGrid::regular_columns(2, 10, |i| -(i as f32) * 0.1);
        let mut img = RangeImage::empty(angles);
        for col in 0..10 {
            img.range_m[10 + col] = 6.0; // bottom row full, at 6 m
            img.label[10 + col] = if col < 5 { 40 } else { 252 };
        }
        img.range_m[3] = 30.0; // one return in the top row
        img.label[3] = 50;
        let mut s = RealismStats::new("t", 2, 10);
        s.add(&img, true);
        assert_eq!(s.row_keep(), vec![0.1, 1.0]);
        assert!((s.keep_rate() - 0.55).abs() < 1e-9);
        let hist = s.range_histogram();
        assert!((hist[1] - 10.0 / 11.0).abs() < 1e-9 && (hist[7] - 1.0 / 11.0).abs() < 1e-9);
        let classes = s.class_share();
        assert!(
            (classes["road"] - 5.0 / 11.0).abs() < 1e-9
                && (classes["car"] - 5.0 / 11.0).abs() < 1e-9
        );
        // Top-row pixels see the 6 m row below them: they count as dropped at 4-8 m.
        let d = s.drop_vs_range();
        assert!(d[1] > 0.4 && d[1] < 0.6, "{d:?}");
        // A wrong-sized image is ignored.
        s.add(
            &RangeImage::empty(AngleGrid::regular_columns(3, 10, |_| 0.0)),
            true,
        );
        assert_eq!(s.scans, 1);
    }

    /// Stats of every `step`-th real SemanticKITTI scan at 64 x 512; `None` (with a skip
    /// message) where the real data is absent.
    fn real_kitti_stats(step: usize) -> Option<RealismStats> {
        let dir = Path::new("../shared/real_lidar/semantickitti_mini");
        if !dir.exists() {
            eprintln!(
                "skipped: {} is absent (real data lives beside the repo)",
                dir.display()
            );
            return None;
        }
        let profile = SensorProfile::kitti_hdl64e().with_columns(512);
        let mut s = RealismStats::new("real", 64, 512);
        for (bin, labels) in find_kitti_scans(dir).into_iter().step_by(step) {
            s.add(
                &real_range_image(&bin, labels.as_deref(), &profile).unwrap(),
                labels.is_some(),
            );
        }
        Some(s)
    }

    #[test]
    fn real_kitti_scans_keep_most_rays_and_lose_the_top_rows() {
        let Some(s) = real_kitti_stats(10) else {
            return;
        };
        assert!(s.scans >= 5);
        assert!(
            s.keep_rate() > 0.7 && s.keep_rate() < 0.95,
            "{}",
            s.keep_rate()
        );
        assert!(s.rows_keep(0..4) < s.rows_keep(20..40));
        assert!(s.class_share().get("road").copied().unwrap_or(0.0) > 0.05);
    }

    #[test]
    fn realistic_physics_brings_the_keep_pattern_close_to_real_kitti() {
        let Some(real) = real_kitti_stats(5) else {
            return;
        };
        let profile = SensorProfile::kitti_hdl64e().with_columns(512);
        let physics = crate::physics::Preset::Realistic.config().effects();
        let (mut ideal, mut realistic) = (
            RealismStats::new("ideal", 64, 512),
            RealismStats::new("realistic", 64, 512),
        );
        for seed in 1..=4 {
            let sim = crate::sim::Simulator::new(
                crate::sim::SceneConfig {
                    seed,
                    duration_s: 2.0,
                    ..Default::default()
                },
                profile.clone(),
            );
            for index in [0, 10] {
                let mut scan = sim.scan(index);
                ideal.add(&scan.image, true);
                physics.apply(&mut scan, seed);
                realistic.add(&scan.image, true);
            }
        }
        let mad = |s: &RealismStats| {
            s.row_keep()
                .iter()
                .zip(real.row_keep())
                .map(|(a, b)| (a - b).abs())
                .sum::<f64>()
                / 64.0
        };
        assert!(
            mad(&realistic) < 0.5 * mad(&ideal),
            "row keep: realistic {} vs ideal {}",
            mad(&realistic),
            mad(&ideal)
        );
        assert!(
            (realistic.keep_rate() - real.keep_rate()).abs() < 0.04,
            "{} vs {}",
            realistic.keep_rate(),
            real.keep_rate()
        );
        // The ego vehicle's blind spots: the bottom rows lose a third of their rays in both.
        assert!((realistic.rows_keep(56..64) - real.rows_keep(56..64)).abs() < 0.1);
        assert!(ideal.rows_keep(56..64) > 0.95);
    }
}

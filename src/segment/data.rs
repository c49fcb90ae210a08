//! Network inputs and targets from range images: the paper's "C R M" input (point
//! coordinates x, y, z, range and the return mask; no intensity, which a simulator does not
//! reproduce), per-pixel class targets, whole recordings as datasets, and training batches
//! with the augmentations that keep a range image a range image (azimuth roll, mirror,
//! scale, random ray drop) and class-balanced crops.

use std::path::PathBuf;

use anyhow::{Result, bail};

use super::classes::{IGNORE, NUM_CLASSES, SCORED, class_of};
use crate::lidar::{RangeImage, SensorProfile};
use crate::recording::{self, Grid};
use crate::util::rng::Rng;

/// Input channels: x, y, z, range, return mask.
pub const CHANNELS: usize = 5;

/// Metres per input unit for x/y, z and range: every channel near unit scale.
const XY_SCALE: f32 = 20.0;
const Z_SCALE: f32 = 2.0;
const RANGE_SCALE: f32 = 20.0;

/// The grid every scan is projected on: the HDL-64E's 64 beams, 512 columns (the paper's
/// resolution, one full revolution).
pub fn benchmark_profile() -> SensorProfile {
    SensorProfile::kitti_hdl64e().with_columns(512)
}

/// One scan as network input and target.
#[derive(Debug, Clone)]
pub struct SegScan {
    /// `[CHANNELS, H, W]`; all zero where no return.
    pub input: Vec<f32>,
    /// `[H, W]` class per pixel; [`IGNORE`] where no return or no label.
    pub target: Vec<u8>,
}

impl SegScan {
    pub fn from_image(image: &RangeImage) -> Self {
        let n = image.len();
        let mut input = vec![0.0f32; CHANNELS * n];
        let mut target = vec![IGNORE; n];
        for k in (0..n).filter(|&k| image.is_valid(k)) {
            let [x, y, z] = image.xyz[k];
            input[k] = x / XY_SCALE;
            input[n + k] = y / XY_SCALE;
            input[2 * n + k] = z / Z_SCALE;
            input[3 * n + k] = image.range_m[k] / RANGE_SCALE;
            input[4 * n + k] = 1.0;
            target[k] = class_of(image.label[k]);
        }
        SegScan { input, target }
    }

    /// Whether pixel `k` holds a return.
    pub fn is_return(&self, k: usize) -> bool {
        self.input[4 * self.target.len() + k] > 0.0
    }
}

/// Labelled scans on one grid.
#[derive(Debug, Clone)]
pub struct SegDataset {
    pub height: usize,
    pub width: usize,
    pub scans: Vec<SegScan>,
    /// The recordings, in order.
    pub files: Vec<PathBuf>,
}

impl SegDataset {
    /// Every scan of the first (or the named) point-cloud topic of each recording, projected
    /// on `profile`. Fails, naming the file, on a recording without labelled returns.
    pub fn from_recordings(
        paths: &[PathBuf],
        topic: Option<&str>,
        profile: &SensorProfile,
    ) -> Result<Self> {
        if paths.is_empty() {
            bail!("no recordings given");
        }
        let grid = Grid::Fixed(profile.clone());
        let mut scans = Vec::new();
        for path in paths {
            let rec = recording::read(path, topic, &grid)?;
            let first = scans.len();
            scans.extend(rec.images.iter().map(SegScan::from_image));
            let labelled = scans[first..]
                .iter()
                .any(|s| s.target.iter().any(|&t| t != IGNORE));
            if !labelled {
                bail!(
                    "{}: topic {}: no labelled returns in {} scans: segmentation needs clouds \
                     with a SemanticKITTI `label` field (written by `simulate`, or by `import` \
                     from a folder with labels/*.label)",
                    path.display(),
                    rec.topic,
                    rec.images.len()
                );
            }
        }
        Ok(SegDataset {
            height: profile.beams(),
            width: profile.columns,
            scans,
            files: paths.to_vec(),
        })
    }

    pub fn len(&self) -> usize {
        self.scans.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scans.is_empty()
    }

    /// Labelled returns per class.
    pub fn class_counts(&self) -> [u64; NUM_CLASSES] {
        let mut counts = [0u64; NUM_CLASSES];
        for t in self.scans.iter().flat_map(|s| &s.target) {
            if let Some(c) = counts.get_mut(*t as usize) {
                *c += 1;
            }
        }
        counts
    }

    /// Loss weight per class, 1/sqrt(frequency) normalised to a mean of 1 over labelled
    /// returns, so small classes (person, pole) are not drowned by road and buildings.
    /// Classes without returns get 0.
    pub fn class_weights(&self) -> [f32; NUM_CLASSES] {
        let counts = self.class_counts();
        let total: u64 = counts.iter().sum();
        let mut w = [0.0f32; NUM_CLASSES];
        if total == 0 {
            return w;
        }
        for (w, &c) in w.iter_mut().zip(&counts) {
            if c > 0 {
                *w = (total as f32 / c as f32).sqrt();
            }
        }
        let mean: f32 = w
            .iter()
            .zip(&counts)
            .map(|(w, &c)| w * c as f32)
            .sum::<f32>()
            / total as f32;
        w.map(|w| w / mean)
    }
}

/// How training crops are drawn and perturbed.
#[derive(Debug, Clone, Copy)]
pub struct CropPlan {
    /// Crops per batch.
    pub size: usize,
    pub crop_width: usize,
    /// Share of crops centred on a column that holds a class drawn uniformly among the
    /// scored classes present, so person and pole are seen about as often as road.
    pub balanced: f32,
    /// Scale jitter and random ray drop, for small real training sets.
    pub augment: bool,
}

/// Largest point-cloud scale change of an augmented crop.
const SCALE_JITTER: f32 = 0.05;
/// Largest share of returns an augmented crop loses to random ray drop.
const MAX_AUGMENT_DROP: f32 = 0.1;

/// For each class, every (scan, column) that holds at least one labelled return of it: the
/// index class-balanced crops draw from.
#[derive(Debug, Clone)]
pub struct ClassColumns {
    by_class: Vec<Vec<(u32, u16)>>,
}

impl ClassColumns {
    pub fn new(data: &SegDataset) -> Self {
        let (h, w) = (data.height, data.width);
        let mut by_class = vec![Vec::new(); NUM_CLASSES];
        let mut seen = [false; NUM_CLASSES];
        for (s, scan) in data.scans.iter().enumerate() {
            for j in 0..w {
                seen.fill(false);
                for i in 0..h {
                    if let Some(f) = seen.get_mut(scan.target[i * w + j] as usize) {
                        *f = true;
                    }
                }
                for c in (0..NUM_CLASSES).filter(|&c| seen[c]) {
                    by_class[c].push((s as u32, j as u16));
                }
            }
        }
        ClassColumns { by_class }
    }

    /// A (scan, column) holding a scored class drawn uniformly among those present.
    fn draw(&self, rng: &mut Rng) -> Option<(usize, usize)> {
        let present: Vec<usize> = SCORED.filter(|&c| !self.by_class[c].is_empty()).collect();
        if present.is_empty() {
            return None;
        }
        let list = &self.by_class[present[rng.below(present.len())]];
        let (s, j) = list[rng.below(list.len())];
        Some((s as usize, j as usize))
    }
}

/// A training batch: `plan.size` crops of `plan.crop_width` columns, each from a scan
/// rolled to a random azimuth (or centred on a drawn class, see [`CropPlan::balanced`]) and
/// mirrored (columns reversed, y negated) with probability 1/2; augmented crops are scaled
/// and lose random returns. Returns the inputs `[size, CHANNELS, H, crop_width]` and the
/// targets `[size, H, crop_width]`.
pub fn batch(
    data: &SegDataset,
    plan: &CropPlan,
    columns: &ClassColumns,
    rng: &mut Rng,
) -> (Vec<f32>, Vec<u8>) {
    let (h, w) = (data.height, data.width);
    let cw = plan.crop_width.min(w);
    let mut input = Vec::with_capacity(plan.size * CHANNELS * h * cw);
    let mut target = Vec::with_capacity(plan.size * h * cw);
    for _ in 0..plan.size {
        let centred = (plan.balanced > 0.0 && rng.chance(plan.balanced))
            .then(|| columns.draw(rng))
            .flatten();
        let (scan, shift) = match centred {
            Some((s, j)) => (&data.scans[s], (j + w - cw / 2) % w),
            None => (&data.scans[rng.below(data.len())], rng.below(w)),
        };
        let mirror = rng.uniform() < 0.5;
        let column = |j: usize| {
            let j = if mirror { cw - 1 - j } else { j };
            (j + shift) % w
        };
        let crop_start = input.len();
        for c in 0..CHANNELS {
            let sign = if mirror && c == 1 { -1.0 } else { 1.0 };
            let plane = &scan.input[c * h * w..(c + 1) * h * w];
            for i in 0..h {
                input.extend((0..cw).map(|j| sign * plane[i * w + column(j)]));
            }
        }
        let target_start = target.len();
        for i in 0..h {
            target.extend((0..cw).map(|j| scan.target[i * w + column(j)]));
        }
        if plan.augment {
            augment(&mut input[crop_start..], &mut target[target_start..], rng);
        }
    }
    (input, target)
}

/// Scales one crop's point cloud (x, y, z and range together) and drops a random share of
/// its returns (input zeroed, target ignored), as a sensor would.
fn augment(input: &mut [f32], target: &mut [u8], rng: &mut Rng) {
    let n = target.len();
    let scale = rng.range(1.0 - SCALE_JITTER, 1.0 + SCALE_JITTER);
    input[..4 * n].iter_mut().for_each(|v| *v *= scale);
    let drop = rng.range(0.0, MAX_AUGMENT_DROP);
    for k in 0..n {
        if input[4 * n + k] > 0.0 && rng.chance(drop) {
            (0..CHANNELS).for_each(|c| input[c * n + k] = 0.0);
            target[k] = IGNORE;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::AngleGrid;

    fn tiny_image() -> RangeImage {
        let angles = AngleGrid::regular_columns(2, 4, |i| -0.1 * i as f32);
        let mut image = RangeImage::empty(angles);
        for k in [0, 1, 5] {
            image.range_m[k] = 10.0;
            image.xyz[k] = [6.0, 8.0, -1.0];
            image.point_index[k] = k as u32;
        }
        image.label[0] = 40;
        image.label[1] = 0;
        image.label[5] = 10;
        image
    }

    #[test]
    fn scan_has_crm_channels_and_ignores_drops_and_unlabelled() {
        let s = SegScan::from_image(&tiny_image());
        let n = 8;
        assert_eq!(s.input.len(), CHANNELS * n);
        assert_eq!(
            s.target,
            vec![2, IGNORE, IGNORE, IGNORE, IGNORE, 0, IGNORE, IGNORE]
        );
        assert!(s.is_return(1) && !s.is_return(2));
        assert_eq!(s.input[3 * n], 0.5);
        assert_eq!(s.input[2 * n + 5], -0.5);
        assert!((0..CHANNELS).all(|c| s.input[c * n + 2] == 0.0));
    }

    #[test]
    fn class_weights_favour_rare_classes_with_unit_mean() {
        let mut s = SegScan::from_image(&tiny_image());
        s.target = vec![2, 2, 2, 2, 2, 2, 2, 0];
        let data = SegDataset {
            height: 2,
            width: 4,
            scans: vec![s],
            files: vec![],
        };
        let w = data.class_weights();
        assert!(w[0] > w[2] && w[1] == 0.0);
        assert!(((7.0 * w[2] + w[0]) / 8.0 - 1.0).abs() < 1e-5);
    }

    #[test]
    fn batch_rolls_and_mirrors_consistently() {
        let mut image = tiny_image();
        image.label[1] = 50;
        let data = SegDataset {
            height: 2,
            width: 4,
            scans: vec![SegScan::from_image(&image)],
            files: vec![],
        };
        let mut rng = Rng::new(3);
        for _ in 0..20 {
            let plan = CropPlan {
                size: 1,
                crop_width: 4,
                balanced: 0.0,
                augment: false,
            };
            let (input, target) = batch(&data, &plan, &ClassColumns::new(&data), &mut rng);
            // The mask channel and the target move together.
            for k in 0..8 {
                assert_eq!(input[4 * 8 + k] > 0.0, target[k] != IGNORE);
            }
            // Row 0 holds road then building; mirrored, building comes first and y flips.
            let road = (0..4).find(|&j| target[j] == 2).unwrap();
            let building = (0..4).find(|&j| target[j] == 4).unwrap();
            let y = input[8 + road];
            if (road + 1) % 4 == building {
                assert_eq!(y, 0.4);
            } else {
                assert_eq!(((building + 1) % 4, y), (road, -0.4));
            }
        }
    }

    /// 16 columns, one row: road everywhere but one person pixel in column 11.
    fn road_with_one_person() -> SegDataset {
        let angles = AngleGrid::regular_columns(1, 16, |_| 0.0);
        let mut image = RangeImage::empty(angles);
        for k in 0..16 {
            image.range_m[k] = 10.0;
            image.xyz[k] = [10.0, 0.0, -1.0];
            image.point_index[k] = k as u32;
            image.label[k] = if k == 11 { 30 } else { 40 };
        }
        SegDataset {
            height: 1,
            width: 16,
            scans: vec![SegScan::from_image(&image)],
            files: vec![],
        }
    }

    fn person_share(data: &SegDataset, plan: &CropPlan) -> f64 {
        let columns = ClassColumns::new(data);
        let mut rng = Rng::new(5);
        let crops = 2000;
        let with_person = (0..crops)
            .filter(|_| batch(data, plan, &columns, &mut rng).1.contains(&1))
            .count();
        with_person as f64 / crops as f64
    }

    #[test]
    fn balanced_crops_show_a_rare_class_as_often_as_a_common_one() {
        let data = road_with_one_person();
        let plan = |balanced| CropPlan {
            size: 1,
            crop_width: 4,
            balanced,
            augment: false,
        };
        // A random 4-of-16 crop holds the person a quarter of the time. Fully balanced crops
        // pick person or road with equal odds, and a crop centred on one of the 15 road
        // columns holds the person for 3 of them: 1/2 + 1/2 * 3/15.
        let random = person_share(&data, &plan(0.0));
        let balanced = person_share(&data, &plan(1.0));
        assert!((random - 0.25).abs() < 0.04, "{random}");
        assert!((balanced - 0.6).abs() < 0.04, "{balanced}");
    }

    #[test]
    fn augmentation_scales_the_cloud_and_drops_returns_with_their_labels() {
        let data = road_with_one_person();
        let plan = CropPlan {
            size: 200,
            crop_width: 16,
            balanced: 0.0,
            augment: true,
        };
        let (input, target) = batch(&data, &plan, &ClassColumns::new(&data), &mut Rng::new(9));
        let n = 16;
        let (mut dropped, mut scales) = (0, Vec::new());
        for (crop, t) in input.chunks(CHANNELS * n).zip(target.chunks(n)) {
            for k in 0..n {
                let kept = crop[4 * n + k] > 0.0;
                assert_eq!(kept, t[k] != IGNORE);
                if kept {
                    scales.push(crop[3 * n + k] / 0.5);
                } else {
                    dropped += 1;
                    assert!((0..CHANNELS).all(|c| crop[c * n + k] == 0.0));
                }
            }
        }
        let share = dropped as f64 / (200 * n) as f64;
        assert!(share > 0.02 && share < 0.08, "{share}");
        let (lo, hi) = scales
            .iter()
            .fold((f32::MAX, f32::MIN), |(lo, hi), &s| (lo.min(s), hi.max(s)));
        assert!(
            lo >= 0.95 - 1e-6 && hi <= 1.05 + 1e-6 && hi - lo > 0.05,
            "{lo} {hi}"
        );
    }
}

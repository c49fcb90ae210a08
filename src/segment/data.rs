//! Network inputs and targets from range images: the paper's "C R M" input (point
//! coordinates x, y, z, range and the return mask; no intensity, which a simulator does not
//! reproduce), per-pixel class targets, whole recordings as datasets, and training batches
//! with the augmentations that keep a range image a range image (azimuth roll, mirror).

use std::path::PathBuf;

use anyhow::{Result, bail};

use super::classes::{IGNORE, NUM_CLASSES, class_of};
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

/// A training batch: `size` scans drawn at random, each rolled to a random azimuth, cut to
/// its first `crop_width` columns and mirrored (columns reversed, y negated) with
/// probability 1/2. Returns the inputs `[size, CHANNELS, H, crop_width]` and the targets
/// `[size, H, crop_width]`.
pub fn batch(
    data: &SegDataset,
    size: usize,
    crop_width: usize,
    rng: &mut Rng,
) -> (Vec<f32>, Vec<u8>) {
    let (h, w) = (data.height, data.width);
    let cw = crop_width.min(w);
    let mut input = Vec::with_capacity(size * CHANNELS * h * cw);
    let mut target = Vec::with_capacity(size * h * cw);
    for _ in 0..size {
        let scan = &data.scans[rng.below(data.len())];
        let shift = rng.below(w);
        let mirror = rng.uniform() < 0.5;
        let column = |j: usize| {
            let j = if mirror { cw - 1 - j } else { j };
            (j + shift) % w
        };
        for c in 0..CHANNELS {
            let sign = if mirror && c == 1 { -1.0 } else { 1.0 };
            let plane = &scan.input[c * h * w..(c + 1) * h * w];
            for i in 0..h {
                input.extend((0..cw).map(|j| sign * plane[i * w + column(j)]));
            }
        }
        for i in 0..h {
            target.extend((0..cw).map(|j| scan.target[i * w + column(j)]));
        }
    }
    (input, target)
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
            let (input, target) = batch(&data, 1, 4, &mut rng);
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
}

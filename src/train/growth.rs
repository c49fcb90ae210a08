//! Coarse-to-fine training of the implicit generator (progressive growing, as in ProGAN).
//!
//! The DUSty v2 generator synthesises on a pyramid of angle grids, coarsest first, and adds
//! each block's head to the upsampled heads below it, so its first `k` blocks alone render a
//! whole scan at level `k`'s resolution: the low-pass part of what all blocks render. A stage
//! trains those `k` blocks against a discriminator of that resolution, which is far cheaper
//! per image than the full grid; the next stage adds a block (and a fresh discriminator),
//! until every block renders the full grid.
//!
//! Real scans reach a stage point-sampled: one pixel of every `f x f` block, at a phase drawn
//! per image, as a sensor with `1/f` of the beams and columns would see the scene. Ray drop
//! keeps its per-pixel statistics that way, where averaging would invent returns.

use burn::config::Config;

use crate::model::generator::GridCache;
use crate::util::rng::Rng;

/// One stage of coarse-to-fine training.
#[derive(Config, Debug, PartialEq)]
pub struct Stage {
    /// Synthesis blocks that render in this stage (the finest of them sets the resolution).
    pub blocks: usize,
    /// Real images shown to the discriminator in this stage.
    pub images: u64,
}

/// The resolution a stage trains at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Level {
    /// Synthesis blocks rendering.
    pub blocks: usize,
    /// Pixels per side of the full grid that one pixel of this level stands for.
    pub factor: usize,
    pub height: usize,
    pub width: usize,
    /// Columns of the windows of the turn this level trains on (full resolution only);
    /// `width` stays the whole turn's.
    pub window: Option<usize>,
}

impl Level {
    /// Stage `stage` of `stages` for a generator of `total_blocks` on a `height x width`
    /// grid; past the last stage, every block at full resolution.
    pub fn of(
        stages: &[Stage],
        stage: usize,
        total_blocks: usize,
        height: usize,
        width: usize,
    ) -> Level {
        let blocks = stages
            .get(stage)
            .map_or(total_blocks, |s| s.blocks.clamp(1, total_blocks));
        let factor = 1 << (total_blocks - blocks);
        Level {
            blocks,
            factor,
            height: height / factor,
            width: width / factor,
            window: None,
        }
    }

    /// This level trained on windows of `window` columns where it is at full resolution.
    pub fn with_window(self, window: Option<usize>) -> Level {
        Level {
            window: window.filter(|_| self.factor == 1),
            ..self
        }
    }

    /// The width of what the discriminator sees: a window or the whole turn.
    pub fn trained_width(&self) -> usize {
        self.window.unwrap_or(self.width)
    }

    /// Columns `start..start + window` (circular) of `image` (`[H, W]` row-major, full
    /// resolution).
    pub fn crop(&self, image: &[f32], start: usize) -> Vec<f32> {
        let (w, window) = (self.width, self.trained_width());
        let mut out = Vec::with_capacity(self.height * window);
        for row in image.chunks_exact(w) {
            out.extend((0..window).map(|j| row[(start + j) % w]));
        }
        out
    }

    /// The generator's grid cache cut to this level's blocks.
    pub fn grid(&self, full: &GridCache) -> GridCache {
        full.first_blocks(self.blocks)
    }

    /// `image` (`[H, W]` row-major, full resolution) sampled at this level: the pixel at
    /// `(phase.0, phase.1)` of every `factor x factor` block.
    pub fn sample(&self, image: &[f32], full_width: usize, phase: (usize, usize)) -> Vec<f32> {
        let f = self.factor;
        let mut out = Vec::with_capacity(self.height * self.width);
        for r in 0..self.height {
            let row = &image[(r * f + phase.0) * full_width..][..full_width];
            out.extend((0..self.width).map(|c| row[c * f + phase.1]));
        }
        out
    }

    /// The R1 weight at this level for `full_gamma` at full resolution: scaled with the
    /// pixel count, as StyleGAN2 scales gamma with resolution squared. A full-resolution
    /// gamma on a 32 x 256 grid kept a fresh discriminator near chance (loss 1.19 after
    /// 10 000 images alone against a fixed generator, 0.76 at a sixteenth of it).
    pub fn r1_gamma(&self, full_gamma: f32) -> f32 {
        full_gamma / (self.factor * self.factor) as f32
    }

    /// A random sampling phase.
    pub fn random_phase(&self, rng: &mut Rng) -> (usize, usize) {
        if self.factor == 1 {
            return (0, 0);
        }
        (rng.below(self.factor), rng.below(self.factor))
    }
}

/// Refuses stages that cannot run: blocks out of order or beyond the generator's, or a
/// level whose grid stage `i`'s discriminator (which needs multiples of `fold(i)`) cannot
/// take.
pub fn check_stages(
    stages: &[Stage],
    total_blocks: usize,
    (height, width): (usize, usize),
    fold: impl Fn(usize) -> usize,
) -> anyhow::Result<()> {
    let mut previous = 0;
    for (i, stage) in stages.iter().enumerate() {
        anyhow::ensure!(
            stage.blocks > previous && stage.blocks < total_blocks,
            "stage {i}: {} blocks; stages need increasing block counts below the generator's {total_blocks}",
            stage.blocks
        );
        previous = stage.blocks;
        let level = Level::of(stages, i, total_blocks, height, width);
        let fold = fold(i);
        anyhow::ensure!(
            level.height.is_multiple_of(fold)
                && level.width.is_multiple_of(fold)
                && level.height > 0,
            "stage {i}: a {}x{} grid is too coarse for the discriminator, which needs multiples of {fold}",
            level.height,
            level.width
        );
    }
    Ok(())
}

/// The stage that `images` seen falls in: the index of the first stage not yet complete, or
/// `stages.len()` (full resolution) once all are.
pub fn stage_at(stages: &[Stage], images: u64) -> usize {
    let mut end = 0u64;
    for (i, s) in stages.iter().enumerate() {
        end = end.saturating_add(s.images);
        if images < end {
            return i;
        }
    }
    stages.len()
}

/// Parses `BLOCKS:IMAGES` (e.g. `3:200000` or `3:200k`), as the CLI takes a stage.
pub fn parse_stage(text: &str) -> Result<Stage, String> {
    let (blocks, images) = text
        .split_once(':')
        .ok_or_else(|| format!("stage {text:?}: expected BLOCKS:IMAGES, e.g. 3:200k"))?;
    let blocks: usize = blocks
        .trim()
        .parse()
        .map_err(|_| format!("stage {text:?}: BLOCKS must be a whole number"))?;
    let images = images.trim().to_ascii_lowercase();
    let (digits, scale) = match images.strip_suffix('k') {
        Some(d) => (d, 1_000),
        None => match images.strip_suffix('m') {
            Some(d) => (d, 1_000_000),
            None => (images.as_str(), 1),
        },
    };
    let images = digits
        .parse::<u64>()
        .ok()
        .and_then(|n| n.checked_mul(scale))
        .ok_or_else(|| format!("stage {text:?}: IMAGES must be a count such as 200000 or 200k"))?;
    if blocks == 0 || images == 0 {
        return Err(format!("stage {text:?}: BLOCKS and IMAGES must be > 0"));
    }
    Ok(Stage::new(blocks, images))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::generator::{Generator, GeneratorConfig};
    use crate::model::layers::{AngleGridExt, kitti_like_grid};
    use burn::tensor::Device;

    #[test]
    fn stages_follow_the_images_seen() {
        let stages = [Stage::new(3, 100), Stage::new(4, 50)];
        assert_eq!(stage_at(&stages, 0), 0);
        assert_eq!(stage_at(&stages, 99), 0);
        assert_eq!(stage_at(&stages, 100), 1);
        assert_eq!(stage_at(&stages, 149), 1);
        assert_eq!(stage_at(&stages, 150), 2);
        assert_eq!(stage_at(&[], 7), 0);
        let level = Level::of(&stages, 0, 5, 64, 512);
        assert_eq!((level.factor, level.height, level.width), (4, 16, 128));
        let full = Level::of(&stages, 2, 5, 64, 512);
        assert_eq!((full.blocks, full.factor, full.height), (5, 1, 64));
        // R1 weighs by pixel count: a sixteenth on the 16 x 128 grid, all of it at full size.
        assert_eq!(level.r1_gamma(1.0), 1.0 / 16.0);
        assert_eq!(full.r1_gamma(0.5), 0.5);
        let fold = |_| 16;
        assert!(check_stages(&stages, 5, (64, 512), fold).is_ok());
        assert!(check_stages(&[Stage::new(2, 10)], 5, (64, 512), fold).is_err());
        assert!(check_stages(&[Stage::new(4, 10), Stage::new(3, 10)], 5, (64, 512), fold).is_err());
        assert!(check_stages(&[Stage::new(5, 10)], 5, (64, 512), fold).is_err());
        // A finer discriminator for the first stage only.
        let per_stage = |i| if i == 0 { 32 } else { 16 };
        assert!(check_stages(&stages, 5, (64, 512), per_stage).is_err());
    }

    #[test]
    fn stage_text_parses_and_bad_text_is_refused() {
        assert_eq!(parse_stage("3:200k"), Ok(Stage::new(3, 200_000)));
        assert_eq!(parse_stage("4:1M"), Ok(Stage::new(4, 1_000_000)));
        assert_eq!(parse_stage("2:37"), Ok(Stage::new(2, 37)));
        for bad in ["3", "x:10", "3:", "0:10", "3:0", "3:99999999999999999999k"] {
            assert!(parse_stage(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn sampling_takes_one_pixel_per_block_at_the_phase() {
        let (h, w) = (4, 8);
        let image: Vec<f32> = (0..h * w).map(|i| i as f32).collect();
        let level = Level {
            blocks: 1,
            factor: 2,
            height: 2,
            width: 4,
            window: None,
        };
        assert_eq!(
            level.sample(&image, w, (1, 0)),
            vec![8., 10., 12., 14., 24., 26., 28., 30.]
        );
        assert_eq!(level.sample(&image, w, (0, 1))[..2], [1., 3.]);
    }

    #[test]
    fn windows_are_cut_across_the_seam_at_full_resolution_only() {
        let image: Vec<f32> = (0..2 * 8).map(|i| i as f32).collect();
        let level = Level::of(&[], 0, 3, 2, 8).with_window(Some(4));
        assert_eq!(level.trained_width(), 4);
        assert_eq!(
            level.crop(&image, 6),
            vec![6., 7., 0., 1., 14., 15., 8., 9.]
        );
        let coarse = Level::of(&[Stage::new(2, 10)], 0, 3, 2, 8).with_window(Some(4));
        assert_eq!((coarse.window, coarse.trained_width()), (None, 4));
    }

    /// The first k blocks render exactly the sum of their heads: the coarse image a stage
    /// trains is the one that the full generator upsamples and adds detail to.
    #[test]
    fn a_cut_grid_renders_the_coarse_levels_of_the_full_one() {
        let device = Device::flex();
        let config = GeneratorConfig::cpu()
            .with_channels(vec![16, 8, 8])
            .with_n_freq(vec![4, 4, 4]);
        let config = config.with_lh(vec![3, 4, 5]).with_lw(vec![3, 4, 5]);
        let g = config.init(&device);
        let full = g.prepare(&kitti_like_grid(16, 64), &device);
        let level = Level::of(&[Stage::new(2, 10)], 0, 3, 16, 64);
        let cut = level.grid(&full);
        assert_eq!((cut.height, cut.width), (8, 32));
        let z = Rng::new(3).normal_tensor([2, g.d_z()], &device);
        let out = g.forward(z, &cut);
        assert_eq!(out.x_d.dims(), [2, 1, 8, 32]);
        // A generator of just the first two blocks, on the full grid's second level.
        let small = Generator {
            mapping: g.mapping.clone(),
            blocks: g.blocks[..2].to_vec(),
            output_gain: g.output_gain,
        };
        let grid = small.prepare(&kitti_like_grid(16, 64).downsample2x(), &device);
        let again = small.forward(Rng::new(3).normal_tensor([2, g.d_z()], &device), &grid);
        let diff = (out.x_d - again.x_d).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-5, "{diff}");
    }
}

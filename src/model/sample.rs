//! Drawing scans from a trained generator (the EMA weights of a run directory): inverse depth,
//! drop probability, a sampled ray-drop mask and the resulting range image, on the training
//! grid or on any other grid (e.g. 2x denser) for the implicit generator.

use anyhow::{Result, bail};
use burn::tensor::Device;
use burn::tensor::activation::sigmoid;

use super::AnyGenerator;
use super::data::RangeDataset;
use super::weights::Model;
use crate::lidar::AngleGrid;
use crate::util::rng::Rng;
use crate::util::tensor::tensor_to_vec;

/// One generated scan, row-major `[H, W]`.
#[derive(Debug, Clone)]
pub struct SampledScan {
    pub angles: AngleGrid,
    /// Inverse depth x_d = min / depth in (0, 1] (min: the nearest depth of the model's
    /// sensor, 1.45 m for KITTI's), before ray drop.
    pub x_d: Vec<f32>,
    /// The depth x_d stands for, meters.
    pub depth_m: Vec<f32>,
    /// x_n: probability that the ray is dropped (all 0 for vanilla).
    pub drop_prob: Vec<f32>,
    /// Sampled returns (true = the ray came back).
    pub mask: Vec<bool>,
    /// Measured range in meters after ray drop; 0 = no return.
    pub range_m: Vec<f32>,
}

impl SampledScan {
    /// Points (sensor frame) of the returns.
    pub fn points(&self) -> Vec<[f32; 3]> {
        (0..self.range_m.len())
            .filter(|&k| self.range_m[k] > 0.0)
            .map(|k| {
                let d = self.angles.direction(k);
                let r = self.range_m[k];
                [d[0] * r, d[1] * r, d[2] * r]
            })
            .collect()
    }
}

/// Options of [`sample`].
#[derive(Debug, Clone)]
pub struct SampleOptions {
    pub n: usize,
    pub seed: u64,
    /// Truncation psi towards w_avg (1 = none; implicit generator only).
    pub truncation: f32,
    /// Grid to render on (implicit generator); default: the model grid.
    pub grid: Option<AngleGrid>,
}

/// Draw `opts.n` scans from a trained generator.
pub fn sample(model: &Model, opts: &SampleOptions, device: &Device) -> Result<Vec<SampledScan>> {
    let (g, config) = (&model.generator, &model.config);
    let grid = opts.grid.clone().unwrap_or_else(|| config.grid());
    let units = config.depth_range();
    let mut rng = Rng::new(opts.seed);
    let mut out = Vec::with_capacity(opts.n);
    let batch = 4;
    let mut done = 0;
    while done < opts.n {
        let b = batch.min(opts.n - done);
        let z = rng.normal_tensor([b, g.d_z()], device);
        let (x_d, keep_logit, angles) = match g {
            AnyGenerator::Implicit(generator) => {
                if !grid.height.is_multiple_of(generator.resolution_step())
                    || !grid.width.is_multiple_of(generator.resolution_step())
                {
                    bail!(
                        "grid {}x{} must divide by {}",
                        grid.height,
                        grid.width,
                        generator.resolution_step()
                    );
                }
                let cache = generator.prepare(&grid, device);
                let w = generator
                    .mapping
                    .truncate(generator.mapping.forward(z), opts.truncation);
                let o = generator.render(w, &cache, None);
                (o.x_d, Some(o.keep_logit), grid.clone())
            }
            AnyGenerator::Conv(generator) => {
                let (h, w) = generator.resolution();
                let y = generator.forward(z);
                let c = y.dims()[1];
                let x_d = y.clone().narrow(1, 0, 1);
                let logit = (c > 1).then(|| y.narrow(1, 1, 1));
                let angles = config.sensor.clone().with_columns(w).angle_grid();
                if angles.height != h {
                    bail!(
                        "conv generator renders {h} rows, its sensor has {}",
                        angles.height
                    );
                }
                (x_d, logit, angles)
            }
        };
        let n = angles.height * angles.width;
        let x_d_net = tensor_to_vec(x_d.clone());
        let (drop_prob, mask) = match keep_logit {
            Some(logit) => {
                let keep = tensor_to_vec(sigmoid(logit.clone()));
                let m = config.measurement.measure(x_d, logit, &mut rng);
                (
                    keep.iter().map(|k| 1.0 - k).collect::<Vec<f32>>(),
                    tensor_to_vec(m.mask)
                        .iter()
                        .map(|v| *v > 0.5)
                        .collect::<Vec<bool>>(),
                )
            }
            // vanilla: the image itself says where the returns are
            None => (
                vec![0.0; b * n],
                x_d_net.iter().map(|v| *v > -0.99).collect(),
            ),
        };
        for i in 0..b {
            let xs = &x_d_net[i * n..(i + 1) * n];
            let x_d: Vec<f32> = xs
                .iter()
                .map(|v| ((v + 1.0) * 0.5).clamp(units.x_d_floor(), 1.0))
                .collect();
            let depth_m: Vec<f32> = x_d.iter().map(|x| units.min_m / x).collect();
            let mask_i = mask[i * n..(i + 1) * n].to_vec();
            let range_m = depth_m
                .iter()
                .zip(&mask_i)
                .map(|(d, &keep)| if keep { *d } else { 0.0 })
                .collect();
            out.push(SampledScan {
                angles: angles.clone(),
                x_d,
                depth_m,
                drop_prob: drop_prob[i * n..(i + 1) * n].to_vec(),
                mask: mask_i,
                range_m,
            });
        }
        done += b;
    }
    Ok(out)
}

/// Real scans of a dataset cache in the same form (for side-by-side pictures and metrics).
pub fn dataset_scan(ds: &RangeDataset, i: usize) -> SampledScan {
    let img = ds.image(i);
    let units = ds.depth_range();
    let x_d: Vec<f32> = img.iter().map(|v| ((v + 1.0) * 0.5).max(0.0)).collect();
    let mask: Vec<bool> = img.iter().map(|v| *v > -1.0 + 1e-6).collect();
    // A real scan has no depth where its ray was dropped.
    let depth_m: Vec<f32> = units.to_range(img);
    SampledScan {
        angles: ds.angles.clone(),
        range_m: depth_m.clone(),
        depth_m,
        drop_prob: mask.iter().map(|&m| if m { 0.0 } else { 1.0 }).collect(),
        x_d,
        mask,
    }
}

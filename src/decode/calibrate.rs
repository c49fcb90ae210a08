//! Fitting a generator's per-beam x_n calibration ([`crate::model::calibration`]): decode
//! training scans the way `convert` does and pair each model-grid pixel's keep logit with
//! whether the ray actually returned, beam by beam.

use anyhow::Result;
use rayon::prelude::*;

use super::{Decoder, scan_seed};
use crate::lidar::RangeImage;
use crate::model::calibration::BeamSamples;

/// Decode `scans` (in parallel; seeds from their index) and collect, per beam of the model
/// grid, the uncalibrated keep logits and the observed returns.
pub fn raydrop_samples(decoder: &Decoder, scans: &[RangeImage]) -> Result<Vec<BeamSamples>> {
    let grid = decoder.model_grid();
    let (h, w) = (grid.height, grid.width);
    let per_scan: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = scans
        .par_iter()
        .enumerate()
        .map(|(i, scan)| -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
            let decoded = decoder.decode(scan, scan_seed("calibration", i as u64))?;
            let (depth, logits) = decoded.depth_and_keep_logits(decoder);
            // A ray returned where the decoder saw it or held it out (restoration).
            let returned = (decoded.observed_m.iter().zip(&decoded.held_out_m))
                .map(|(seen, held)| if *seen > 0.0 || *held > 0.0 { 1.0 } else { 0.0 })
                .collect();
            Ok((logits, depth, returned))
        })
        .collect::<Result<_>>()?;
    let elevations = grid.row_elevations();
    let mut beams: Vec<BeamSamples> = elevations
        .iter()
        .map(|e| BeamSamples {
            elevation_rad: *e,
            ..Default::default()
        })
        .collect();
    for (logits, depth, returned) in &per_scan {
        for r in 0..h {
            let beam = &mut beams[r];
            beam.logits.extend_from_slice(&logits[r * w..(r + 1) * w]);
            beam.depth_m.extend_from_slice(&depth[r * w..(r + 1) * w]);
            beam.kept
                .extend(returned[r * w..(r + 1) * w].iter().map(|m| *m > 0.0));
        }
    }
    Ok(beams)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decode::{DecodeOptions, Quality, model_grid};
    use crate::model::calibration::RaydropCalibration;
    use crate::model::weights::Model;

    /// A flat ground scan whose top 16 rows never return: the fitted calibration must learn that
    /// those beams drop and the others do not, whatever the generator's logits said.
    #[test]
    fn calibration_learns_the_drop_pattern_of_the_scans() {
        let device = burn::tensor::Device::flex();
        let mut opts = DecodeOptions::new(Quality::Paper);
        opts.schedule.w_steps = 0;
        opts.schedule.set_tune_steps(0);
        let decoder = Decoder::new(Model::shipped(&device).unwrap(), opts).unwrap();
        let grid = model_grid();
        let scans: Vec<RangeImage> = (0..2)
            .map(|s| {
                let mut img = RangeImage::empty(grid.clone());
                for (k, r) in img.range_m.iter_mut().enumerate() {
                    if k / grid.width >= 16 {
                        *r = 10.0 + (k % 7) as f32 + s as f32;
                    }
                }
                img
            })
            .collect();
        let samples = raydrop_samples(&decoder, &scans).unwrap();
        assert_eq!(samples.len(), 64);
        assert!(samples.iter().all(|b| b.logits.len() == 2 * grid.width));
        let rows = grid.row_elevations();
        assert!(samples[0].kept.iter().all(|k| !k) && samples[40].kept.iter().all(|k| *k));
        let c = RaydropCalibration::fit(&samples, "test".into()).unwrap();
        for (r, beam) in samples.iter().enumerate() {
            let drop: f32 = (0..beam.logits.len())
                .map(|i| 1.0 / (1.0 + c.keep_logit(beam.logits[i], beam.depth_m[i], rows[r]).exp()))
                .sum::<f32>()
                / beam.logits.len() as f32;
            if r < 15 {
                assert!(drop > 0.9, "row {r}: x_n {drop}");
            } else if r > 16 {
                assert!(drop < 0.1, "row {r}: x_n {drop}");
            }
        }
    }
}

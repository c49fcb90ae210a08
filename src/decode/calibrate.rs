//! Fitting a generator's per-beam x_n calibration ([`crate::model::calibration`]): decode
//! training scans the way `convert` does and pair each model-grid pixel's keep logit with
//! whether the ray actually returned, beam by beam.

use anyhow::Result;
use rayon::prelude::*;

use super::{Decoder, scan_seed};
use crate::lidar::RangeImage;
use crate::lidar::edges::edge_strength;
use crate::model::calibration::BeamSamples;

/// One decoded scan's model-grid pixels: keep logit, completed depth, its edge strength and
/// whether the ray returned.
struct ScanPixels {
    logits: Vec<f32>,
    depth: Vec<f32>,
    edge: Vec<f32>,
    returned: Vec<bool>,
}

/// Decode `scans` (in parallel; seeds from their index) and collect, per beam of the model
/// grid, the uncalibrated keep logits, the completed depth and its edges, and the observed
/// returns.
pub fn raydrop_samples(decoder: &Decoder, scans: &[RangeImage]) -> Result<Vec<BeamSamples>> {
    let grid = decoder.model_grid();
    let w = grid.width;
    let per_scan: Vec<ScanPixels> = scans
        .par_iter()
        .enumerate()
        .map(|(i, scan)| -> Result<ScanPixels> {
            let decoded = decoder.decode(scan, scan_seed("calibration", i as u64))?;
            let (depth, logits) = decoded.depth_and_keep_logits(decoder);
            // A ray returned where the decoder saw it or held it out (restoration).
            let returned = (decoded.observed_m.iter().zip(&decoded.held_out_m))
                .map(|(seen, held)| *seen > 0.0 || *held > 0.0)
                .collect();
            Ok(ScanPixels {
                edge: edge_strength(&depth, w),
                logits,
                depth,
                returned,
            })
        })
        .collect::<Result<_>>()?;
    let mut beams: Vec<BeamSamples> = grid
        .row_elevations()
        .iter()
        .map(|e| BeamSamples {
            elevation_rad: *e,
            ..Default::default()
        })
        .collect();
    for scan in &per_scan {
        for (r, beam) in beams.iter_mut().enumerate() {
            let row = r * w..(r + 1) * w;
            beam.logits.extend_from_slice(&scan.logits[row.clone()]);
            beam.depth_m.extend_from_slice(&scan.depth[row.clone()]);
            beam.edge.extend_from_slice(&scan.edge[row.clone()]);
            beam.kept.extend_from_slice(&scan.returned[row]);
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
                .map(|i| {
                    1.0 / (1.0
                        + c.keep_logit(beam.logits[i], beam.depth_m[i], beam.edge[i], rows[r])
                            .exp())
                })
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

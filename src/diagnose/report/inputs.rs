//! What the inputs allow: their check (scans on both sides, one grid), and which
//! candidates they can test (semantic labels, a grazing contrast).

use super::DiagnoseError;
use crate::diagnose::features::ScanFeatures;
use crate::diagnose::stats::{BinTest, Comparison, Feature};

/// The first real scan, once both sides are usable: scans on both, two real ones at least
/// (one to fit on, one to test on), and the same grid.
pub(super) fn check_inputs<'a>(
    sim: &[ScanFeatures],
    real: &'a [ScanFeatures],
) -> Result<&'a ScanFeatures, DiagnoseError> {
    let (Some(s0), Some(r0)) = (sim.first(), real.first()) else {
        return Err(if sim.is_empty() {
            DiagnoseError::NoSimScans
        } else {
            DiagnoseError::NoRealScans
        });
    };
    if (s0.height, s0.width) != (r0.height, r0.width) {
        return Err(DiagnoseError::GridMismatch {
            sim_h: s0.height,
            sim_w: s0.width,
            real_h: r0.height,
            real_w: r0.width,
        });
    }
    Ok(r0)
}

/// Whether a recording carries semantic labels: at least 5 % of its returns
/// have a class.
pub(super) fn labelled(scans: &[ScanFeatures]) -> bool {
    let (mut kept, mut classed) = (0usize, 0usize);
    for f in scans {
        for k in 0..f.len() {
            if f.kept[k] {
                kept += 1;
                classed += usize::from(f.class[k] != 0);
            }
        }
    }
    classed as f64 >= 0.05 * kept.max(1) as f64
}

/// Smallest grazing contrast ([`grazing_contrast`]) for which `incidence_dropout` is a
/// candidate.
pub(super) const MIN_GRAZING_CONTRAST: f64 = 0.05;

/// How much more of the rays the real recording loses beyond the sim at grazing
/// incidence (the largest real-minus-sim drop rate of the bins from 70 deg) than at
/// other incidences (the median of the bins below 70 deg); None without bins on
/// both sides.
pub(super) fn grazing_contrast(comparison: &Comparison, step_deg: f32) -> Option<f64> {
    let grazing_from = (70.0 / step_deg.max(1e-3)).ceil() as i64;
    let tests = comparison
        .tests
        .iter()
        .filter(|t| t.feature == Feature::Incidence && t.bin >= 0);
    let grazing = tests
        .clone()
        .filter(|t| t.bin >= grazing_from)
        .map(BinTest::rate_diff)
        .reduce(f64::max)?;
    let mut rest: Vec<f64> = tests
        .filter(|t| t.bin < grazing_from)
        .map(BinTest::rate_diff)
        .collect();
    if rest.is_empty() {
        return None;
    }
    rest.sort_by(f64::total_cmp);
    Some(grazing - rest[rest.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn incidence_bins(real_minus_sim: &[f64]) -> Comparison {
        let tests = real_minus_sim
            .iter()
            .enumerate()
            .map(|(bin, &d)| BinTest {
                feature: Feature::Incidence,
                bin: bin as i64,
                description: String::new(),
                pixels_sim: 1000,
                dropped_sim: 200,
                pixels_real: 1000,
                dropped_real: (1000.0 * (0.2 + d)) as u64,
                rate_sim: 0.2,
                rate_real: 0.2 + d,
                z: 0.0,
                p_value: 1.0,
                q_value: 1.0,
                significant: false,
            })
            .collect();
        Comparison {
            rate_sim: 0.2,
            rate_real: 0.2,
            tests,
        }
    }

    #[test]
    fn grazing_contrast_is_the_grazing_excess_over_the_median_elsewhere() {
        // A concealed grazing effect: real loses fewer rays everywhere but at 80-90 deg.
        let concealed =
            incidence_bins(&[-0.05, -0.04, -0.05, -0.06, -0.05, -0.05, -0.04, -0.05, 0.2]);
        let c = grazing_contrast(&concealed, 10.0).unwrap();
        assert!((c - 0.25).abs() < 1e-9, "{c}");
        // A scene difference that only shifts every bin a little.
        let shifted = incidence_bins(&[
            -0.03, -0.03, -0.02, -0.03, -0.03, -0.02, -0.03, -0.01, -0.02,
        ]);
        assert!(grazing_contrast(&shifted, 10.0).unwrap() < MIN_GRAZING_CONTRAST);
        // No grazing bins tested: nothing to say.
        assert_eq!(grazing_contrast(&incidence_bins(&[0.1, 0.1]), 10.0), None);
    }
}

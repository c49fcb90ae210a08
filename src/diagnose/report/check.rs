//! The posterior-predictive check of the fitted model along each plotted feature:
//! where it is close to the real drop rate, and where it is worse than the raw sim.

use serde::Serialize;

use super::plots::Curve;

/// A posterior-predictive check along one plotted feature: in each bin with enough
/// held-out real pixels, is the sim with the fitted effects as close to the real drop rate
/// as the raw sim, and within [`CLOSE`] of it? A fit that lowers the total NLL can still be
/// worse than the raw simulator along one feature; this says where.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FeatureCheck {
    pub feature: String,
    pub unit: String,
    /// Bins with at least [`CHECK_MIN_PIXELS`] held-out real pixels.
    pub bins: usize,
    /// Of those, bins where the fitted drop rate is within [`CLOSE`] of the real one.
    pub close: usize,
    /// Bins where the fitted rate is farther from the real one than the raw sim's is
    /// (by more than [`CLOSE`] / 5), worst first.
    pub worse_than_sim: Vec<MisfitBin>,
}

/// One bin of a feature where the fitted model misses the real drop rate.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MisfitBin {
    /// Bin centre, in the feature's unit.
    pub at: f64,
    pub real: f64,
    pub sim: f64,
    pub fitted: f64,
}

/// Fitted and real drop rates this close count as agreeing.
pub const CLOSE: f64 = 0.05;
/// Held-out real pixels a bin needs before it is checked.
pub const CHECK_MIN_PIXELS: f64 = 200.0;

/// The posterior-predictive check of every curve.
pub fn check_curves(curves: &[Curve]) -> Vec<FeatureCheck> {
    curves
        .iter()
        .map(|c| {
            let mut check = FeatureCheck {
                feature: c.feature.into(),
                unit: c.unit.into(),
                bins: 0,
                close: 0,
                worse_than_sim: Vec::new(),
            };
            for b in 0..c.x.len() {
                let (real, sim, fitted) = (c.real[b], c.sim[b], c.fitted[b]);
                if c.real_pixels[b] < CHECK_MIN_PIXELS || !(real.is_finite() && fitted.is_finite())
                {
                    continue;
                }
                check.bins += 1;
                check.close += usize::from((fitted - real).abs() <= CLOSE);
                if sim.is_finite() && (fitted - real).abs() > (sim - real).abs() + CLOSE / 5.0 {
                    check.worse_than_sim.push(MisfitBin {
                        at: c.x[b],
                        real,
                        sim,
                        fitted,
                    });
                }
            }
            let miss = |m: &MisfitBin| (m.fitted - m.real).abs() - (m.sim - m.real).abs();
            check
                .worse_than_sim
                .sort_by(|a, b| miss(b).total_cmp(&miss(a)));
            check
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_check_names_bins_where_the_fit_is_worse_than_the_raw_sim() {
        let curve = Curve {
            feature: "range",
            unit: "m",
            x: vec![1.25, 3.75, 6.25, 8.75],
            real: vec![0.10, 0.20, 0.12, 0.50],
            sim: vec![0.08, 0.05, 0.04, 0.10],
            // Bin 0 close, bin 1 closer than the sim but not close, bin 2 worse than the
            // sim (the far-drop overprediction), bin 3 too few pixels to judge.
            fitted: vec![0.11, 0.14, 0.38, 0.0],
            real_pixels: vec![5000.0, 5000.0, 900.0, 50.0],
        };
        let [check] = check_curves(&[curve]).try_into().unwrap();
        assert_eq!((check.bins, check.close), (3, 1));
        assert_eq!(check.worse_than_sim.len(), 1);
        assert_eq!(check.worse_than_sim[0].at, 6.25);
        assert_eq!(check.worse_than_sim[0].fitted, 0.38);
    }
}

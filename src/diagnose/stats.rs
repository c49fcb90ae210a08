//! Conditional drop-rate comparisons between a simulated and a real recording
//!: where, in feature space, do the two drop rays at different rates?
//!
//! This module owns the binning of [`ScanFeatures`] by one feature at a time (row,
//! azimuth, range, incidence, depth-edge proximity, class), the per-bin counts,
//! a two-proportion z-test per bin, and the Benjamini-Hochberg correction over all
//! bins of all features. The largest significant divergence locates the mismatch.
//! It does not fit physics models (that is the maximum-likelihood step).
//!
//! Pixels of one scan are not independent, so a per-pixel test overstates the
//! evidence; a bin is called significant only when its corrected q-value is below
//! `alpha` *and* its drop rates differ by at least `min_rate_diff`.

use std::collections::BTreeMap;
use std::f64::consts::{PI, SQRT_2};

use super::features::ScanFeatures;

/// A feature a drop rate can be conditioned on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Feature {
    Row,
    Azimuth,
    Range,
    Incidence,
    EdgeProximity,
    Class,
}

impl Feature {
    pub const ALL: [Feature; 6] = [
        Feature::Row,
        Feature::Azimuth,
        Feature::Range,
        Feature::Incidence,
        Feature::EdgeProximity,
        Feature::Class,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Feature::Row => "row",
            Feature::Azimuth => "azimuth",
            Feature::Range => "range",
            Feature::Incidence => "incidence",
            Feature::EdgeProximity => "edge_proximity",
            Feature::Class => "class",
        }
    }
}

/// Bin key for a pixel whose feature is undefined (no geometry to complete).
pub const UNKNOWN_BIN: i64 = -1;

/// How features are cut into bins.
#[derive(Debug, Clone, PartialEq)]
pub struct BinOptions {
    /// Equal azimuth sectors over the full turn.
    pub azimuth_bins: usize,
    /// Increasing range bin edges, meters; bin `b` is `[edges[b], edges[b + 1])`,
    /// the last one open-ended.
    pub range_edges_m: Vec<f32>,
    /// Incidence bin width, degrees.
    pub incidence_step_deg: f32,
    /// Pixels completed to beyond this range are left out: near the sensor's
    /// reach "no surface" and "dropped" look alike and their share is a scene
    /// property (see [`super::fit::reach_m`]). Infinity keeps all.
    pub reach_m: f32,
}

impl Default for BinOptions {
    fn default() -> Self {
        BinOptions {
            azimuth_bins: 16,
            range_edges_m: vec![0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0, 80.0],
            incidence_step_deg: 10.0,
            reach_m: f32::INFINITY,
        }
    }
}

impl BinOptions {
    /// The bin of pixel `k` for `feature`, or [`UNKNOWN_BIN`].
    pub fn bin(&self, feature: Feature, f: &ScanFeatures, k: usize) -> i64 {
        match feature {
            Feature::Row => i64::from(f.row[k]),
            Feature::Azimuth => {
                let a = f.azimuth_rad[k] as f64;
                if !a.is_finite() || self.azimuth_bins == 0 {
                    return UNKNOWN_BIN;
                }
                let u = (a + PI).rem_euclid(2.0 * PI) / (2.0 * PI);
                ((u * self.azimuth_bins as f64) as i64).min(self.azimuth_bins as i64 - 1)
            }
            Feature::Range => {
                let r = f.range_m[k];
                if !r.is_finite() {
                    return UNKNOWN_BIN;
                }
                self.range_edges_m.iter().filter(|e| **e <= r).count() as i64 - 1
            }
            Feature::Incidence => {
                let deg = f.incidence_rad[k].to_degrees();
                if !deg.is_finite() || self.incidence_step_deg <= 0.0 {
                    return UNKNOWN_BIN;
                }
                (deg / self.incidence_step_deg) as i64
            }
            Feature::EdgeProximity => i64::from(f.edge_px[k]),
            Feature::Class => i64::from(f.class[k]),
        }
    }

    /// Words for a bin, for reports ("range [20, 30) m").
    pub fn describe(&self, feature: Feature, bin: i64) -> String {
        if bin == UNKNOWN_BIN {
            return format!("{} unknown (no geometry)", feature.name());
        }
        match feature {
            Feature::Row => format!("row {bin}"),
            Feature::Azimuth => {
                let step = 360.0 / self.azimuth_bins.max(1) as f64;
                let lo = -180.0 + step * bin as f64;
                format!("azimuth [{lo:.1}, {:.1}) deg", lo + step)
            }
            Feature::Range => {
                let b = bin as usize;
                match (self.range_edges_m.get(b), self.range_edges_m.get(b + 1)) {
                    (Some(lo), Some(hi)) => format!("range [{lo}, {hi}) m"),
                    (Some(lo), None) => format!("range >= {lo} m"),
                    _ => format!("range below {} m", self.range_edges_m[0]),
                }
            }
            Feature::Incidence => {
                let lo = self.incidence_step_deg * bin as f32;
                format!(
                    "incidence [{lo}, {}) deg",
                    (lo + self.incidence_step_deg).min(90.0)
                )
            }
            Feature::EdgeProximity => format!("{bin} px from a depth edge"),
            Feature::Class => format!("class {bin}"),
        }
    }
}

/// Pixels and dropped pixels per (feature, bin), accumulated over scans.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DropCounts {
    /// (feature, bin) -> (pixels, dropped pixels).
    pub bins: BTreeMap<(Feature, i64), (u64, u64)>,
    pub pixels: u64,
    pub dropped: u64,
}

impl DropCounts {
    /// Adds every pixel of one scan.
    pub fn add(&mut self, f: &ScanFeatures, options: &BinOptions) {
        for k in 0..f.len() {
            if f.range_m[k] > options.reach_m || f.in_gap(k) {
                continue;
            }
            let dropped = u64::from(!f.kept[k]);
            self.pixels += 1;
            self.dropped += dropped;
            for feature in Feature::ALL {
                let entry = self
                    .bins
                    .entry((feature, options.bin(feature, f, k)))
                    .or_default();
                entry.0 += 1;
                entry.1 += dropped;
            }
        }
    }

    /// Overall fraction of dropped pixels.
    pub fn drop_rate(&self) -> f64 {
        if self.pixels == 0 {
            0.0
        } else {
            self.dropped as f64 / self.pixels as f64
        }
    }
}

/// The test of one bin: sim vs real drop rate.
#[derive(Debug, Clone, PartialEq)]
pub struct BinTest {
    pub feature: Feature,
    pub bin: i64,
    pub description: String,
    pub pixels_sim: u64,
    pub dropped_sim: u64,
    pub pixels_real: u64,
    pub dropped_real: u64,
    pub rate_sim: f64,
    pub rate_real: f64,
    /// Two-proportion z (real minus sim, pooled variance).
    pub z: f64,
    pub p_value: f64,
    /// Benjamini-Hochberg adjusted p-value over all bins tested.
    pub q_value: f64,
    pub significant: bool,
}

impl BinTest {
    /// Real minus sim drop rate.
    pub fn rate_diff(&self) -> f64 {
        self.rate_real - self.rate_sim
    }
}

/// Significance settings for [`compare`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TestOptions {
    /// False discovery rate for Benjamini-Hochberg.
    pub alpha: f64,
    /// Smallest drop-rate difference worth reporting.
    pub min_rate_diff: f64,
    /// Bins with fewer pixels than this on either side are not tested.
    pub min_pixels: u64,
}

impl Default for TestOptions {
    fn default() -> Self {
        TestOptions {
            alpha: 0.01,
            min_rate_diff: 0.02,
            min_pixels: 50,
        }
    }
}

/// All bin tests, strongest significant divergence first.
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    pub rate_sim: f64,
    pub rate_real: f64,
    pub tests: Vec<BinTest>,
}

impl Comparison {
    pub fn significant(&self) -> impl Iterator<Item = &BinTest> {
        self.tests.iter().filter(|t| t.significant)
    }

    /// The largest significant divergence: where the mismatch is.
    pub fn strongest(&self) -> Option<&BinTest> {
        self.significant().next()
    }

    /// The strongest significant bin of one feature.
    pub fn strongest_of(&self, feature: Feature) -> Option<&BinTest> {
        self.significant().find(|t| t.feature == feature)
    }
}

/// Tests every bin present on both sides, corrects for the number of bins, and
/// sorts significant bins first by absolute rate difference.
pub fn compare(
    sim: &DropCounts,
    real: &DropCounts,
    bins: &BinOptions,
    options: &TestOptions,
) -> Comparison {
    let mut tests: Vec<BinTest> = Vec::new();
    for (&(feature, bin), &(ns, ds)) in &sim.bins {
        let Some(&(nr, dr)) = real.bins.get(&(feature, bin)) else {
            continue;
        };
        if ns < options.min_pixels || nr < options.min_pixels {
            continue;
        }
        let (z, p_value) = two_proportion_test(ds, ns, dr, nr);
        tests.push(BinTest {
            feature,
            bin,
            description: bins.describe(feature, bin),
            pixels_sim: ns,
            dropped_sim: ds,
            pixels_real: nr,
            dropped_real: dr,
            rate_sim: ds as f64 / ns as f64,
            rate_real: dr as f64 / nr as f64,
            z,
            p_value,
            q_value: 1.0,
            significant: false,
        });
    }
    let p: Vec<f64> = tests.iter().map(|t| t.p_value).collect();
    for (t, q) in tests.iter_mut().zip(benjamini_hochberg(&p)) {
        t.q_value = q;
        t.significant = q < options.alpha && t.rate_diff().abs() >= options.min_rate_diff;
    }
    tests.sort_by(|a, b| {
        b.significant
            .cmp(&a.significant)
            .then(b.rate_diff().abs().total_cmp(&a.rate_diff().abs()))
            .then(a.feature.cmp(&b.feature))
            .then(a.bin.cmp(&b.bin))
    });
    Comparison {
        rate_sim: sim.drop_rate(),
        rate_real: real.drop_rate(),
        tests,
    }
}

/// Pooled two-proportion z-test of `x1 / n1` against `x2 / n2`: (z of 2 minus 1,
/// two-sided p-value). Equal proportions of 0 or 1 give z = 0, p = 1.
pub fn two_proportion_test(x1: u64, n1: u64, x2: u64, n2: u64) -> (f64, f64) {
    if n1 == 0 || n2 == 0 {
        return (0.0, 1.0);
    }
    let (p1, p2) = (x1 as f64 / n1 as f64, x2 as f64 / n2 as f64);
    let pooled = (x1 + x2) as f64 / (n1 + n2) as f64;
    let var = pooled * (1.0 - pooled) * (1.0 / n1 as f64 + 1.0 / n2 as f64);
    if var <= 0.0 {
        return (0.0, 1.0);
    }
    let z = (p2 - p1) / var.sqrt();
    (z, erfc(z.abs() / SQRT_2).min(1.0))
}

/// Benjamini-Hochberg adjusted p-values (step-up), in the input order.
pub fn benjamini_hochberg(p: &[f64]) -> Vec<f64> {
    let m = p.len();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let mut q = vec![1.0; m];
    let mut running = 1.0f64;
    for (rank, &i) in order.iter().enumerate().rev() {
        running = running.min(p[i] * m as f64 / (rank + 1) as f64);
        q[i] = running.min(1.0);
    }
    q
}

/// Complementary error function (Numerical Recipes `erfcc`, relative error
/// below 1.2e-7 everywhere), good far into the tail where p-values live.
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * poly.exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::rng::uniform;

    /// A synthetic "scan" of `n` pixels with features drawn from `seed`, each
    /// dropped with probability `drop_prob(range_m)`. Row, azimuth, class and
    /// incidence are independent of range.
    fn synthetic(seed: u64, n: usize, drop_prob: impl Fn(f32) -> f32) -> ScanFeatures {
        let u = |k: usize, s: u64| uniform(&[seed, k as u64, s]);
        let mut f = ScanFeatures::empty(32, n / 32);
        for k in 0..n {
            let range_m = 2.0 + 78.0 * u(k, 1);
            f.row.push((u(k, 2) * 32.0) as u32 % 32);
            f.azimuth_rad
                .push(std::f32::consts::PI * (2.0 * u(k, 3) - 1.0));
            f.elevation_rad.push(0.0);
            f.range_m.push(range_m);
            f.incidence_rad.push(1.5 * u(k, 4));
            f.edge_px.push((u(k, 5) * 8.0) as u8 % 8);
            f.row_edge_px.push((u(k, 5) * 8.0) as u8 % 8);
            f.class.push(1 + (u(k, 6) * 4.0) as u32 % 4);
            f.kept.push(u(k, 7) >= drop_prob(range_m));
        }
        f
    }

    fn counts(f: &ScanFeatures) -> DropCounts {
        let mut c = DropCounts::default();
        c.add(f, &BinOptions::default());
        c
    }

    /// Range drop model: 2 % near, 30 % beyond 50 m. Mean over U(2, 80) m:
    /// (48 * 0.02 + 30 * 0.30) / 78.
    fn far_drops(r: f32) -> f32 {
        if r >= 50.0 { 0.30 } else { 0.02 }
    }

    #[test]
    fn erfc_matches_known_values() {
        assert!((erfc(0.0) - 1.0).abs() < 1e-7);
        // Two-sided p of z = 1.96 is 0.05; of z = 3 is 0.0026998.
        assert!((erfc(1.96 / SQRT_2) - 0.049_996).abs() < 1e-5);
        assert!((erfc(3.0 / SQRT_2) - 0.002_699_8).abs() < 1e-6);
        assert!((erfc(-1.0) - (2.0 - erfc(1.0))).abs() < 1e-12);
        assert!(erfc(10.0) > 0.0 && erfc(10.0) < 1e-40);
    }

    #[test]
    fn benjamini_hochberg_steps_up() {
        let q = benjamini_hochberg(&[0.01, 0.04, 0.03, 0.5]);
        // Sorted: 0.01 (x4/1 = 0.04), 0.03 (x4/2 = 0.06), 0.04 (x4/3 = 0.0533), 0.5.
        // Step-up takes the running minimum from the top: 0.0533 for rank 2.
        let expected = [0.04, 0.16 / 3.0, 0.16 / 3.0, 0.5];
        for (a, b) in q.iter().zip(expected) {
            assert!((a - b).abs() < 1e-12, "{q:?}");
        }
        assert!(benjamini_hochberg(&[]).is_empty());
    }

    #[test]
    fn two_proportion_test_sign_and_degenerate_cases() {
        let (z, p) = two_proportion_test(100, 1000, 200, 1000);
        assert!(z > 5.0 && p < 1e-6, "z={z} p={p}");
        let (z, p) = two_proportion_test(0, 1000, 0, 500);
        assert_eq!((z, p), (0.0, 1.0));
        let (z, p) = two_proportion_test(100, 1000, 100, 1000);
        assert!(z.abs() < 1e-12 && (p - 1.0).abs() < 1e-6);
    }

    #[test]
    fn a_range_mismatch_is_located_in_range_and_nowhere_else() {
        let n = 64 * 2048;
        let real = synthetic(11, n, far_drops);
        let global = (48.0 * 0.02 + 30.0 * 0.30) / 78.0;
        // Concealed: the sim drops uniformly at the real global rate, other scene.
        let sim = synthetic(22, n, |_| global);
        let (cs, cr) = (counts(&sim), counts(&real));
        assert!((cs.drop_rate() - cr.drop_rate()).abs() < 0.005);
        let cmp = compare(&cs, &cr, &BinOptions::default(), &TestOptions::default());
        let top = cmp.strongest().expect("a significant bin");
        assert_eq!(top.feature, Feature::Range, "{top:?}");
        assert!(
            top.rate_diff() > 0.1,
            "far range drops more in real: {top:?}"
        );
        assert!(top.description.starts_with("range"), "{}", top.description);
        for feature in [
            Feature::Row,
            Feature::Azimuth,
            Feature::Incidence,
            Feature::EdgeProximity,
            Feature::Class,
        ] {
            assert!(
                cmp.strongest_of(feature).is_none(),
                "{feature:?}: {:?}",
                cmp.strongest_of(feature)
            );
        }
        // Both sides of the mismatch show: near bins drop less in real.
        let near = cmp
            .significant()
            .find(|t| t.feature == Feature::Range && t.rate_diff() < 0.0);
        assert!(near.is_some());
    }

    #[test]
    fn same_physics_different_scenes_gives_no_significant_bin() {
        let n = 64 * 2048;
        let sim = synthetic(33, n, far_drops);
        let real = synthetic(44, n, far_drops);
        let cmp = compare(
            &counts(&sim),
            &counts(&real),
            &BinOptions::default(),
            &TestOptions::default(),
        );
        assert!(
            cmp.tests.len() > 50,
            "bins were tested: {}",
            cmp.tests.len()
        );
        assert_eq!(cmp.significant().count(), 0, "{:?}", cmp.strongest());
    }

    #[test]
    fn bins_cover_edges_and_unknowns() {
        let o = BinOptions::default();
        let mut f = synthetic(1, 32, |_| 0.0);
        f.range_m[0] = f32::NAN;
        f.range_m[1] = 5.0;
        f.range_m[2] = 100.0;
        f.incidence_rad[0] = f32::NAN;
        f.azimuth_rad[3] = -3.1;
        f.azimuth_rad[4] = 3.1;
        assert_eq!(o.bin(Feature::Range, &f, 0), UNKNOWN_BIN);
        assert_eq!(o.bin(Feature::Range, &f, 1), 1);
        assert_eq!(o.bin(Feature::Range, &f, 2), 9);
        assert_eq!(o.bin(Feature::Incidence, &f, 0), UNKNOWN_BIN);
        assert_eq!(o.bin(Feature::Azimuth, &f, 3), 0);
        assert_eq!(o.bin(Feature::Azimuth, &f, 4), 15);
        assert_eq!(o.describe(Feature::Range, 1), "range [5, 10) m");
        assert_eq!(o.describe(Feature::Range, 9), "range >= 80 m");
        assert_eq!(
            o.describe(Feature::Incidence, UNKNOWN_BIN),
            "incidence unknown (no geometry)"
        );
    }

    use crate::diagnose::features::simulated_recording;

    fn all_counts(scans: &[ScanFeatures]) -> DropCounts {
        let mut c = DropCounts::default();
        for s in scans {
            c.add(s, &BinOptions::default());
        }
        c
    }

    #[test]
    fn simulated_concealed_range_dropout_diverges_most_in_range() {
        use crate::physics::dropout::{RangeDropout, UniformDropout};
        let real = all_counts(&simulated_recording(
            101,
            6,
            vec![Box::new(RangeDropout {
                enabled: true,
                range_50_m: 40.0,
                softness: 0.3,
            })],
        ));
        let ideal = all_counts(&simulated_recording(202, 6, vec![]));
        let (r, s0) = (real.drop_rate(), ideal.drop_rate());
        let prob = ((r - s0) / (1.0 - s0)) as f32;
        let sim = all_counts(&simulated_recording(
            202,
            6,
            vec![Box::new(UniformDropout {
                enabled: true,
                prob,
            })],
        ));
        assert!((sim.drop_rate() - r).abs() < 0.01, "concealed");
        let cmp = compare(&sim, &real, &BinOptions::default(), &TestOptions::default());
        let top = cmp.strongest().expect("a significant bin");
        assert_eq!(top.feature, Feature::Range, "{top:?}");
        assert!(
            top.rate_diff() > 0.0,
            "far range drops more in real: {top:?}"
        );
    }

    #[test]
    fn simulated_same_physics_different_scenes_gives_no_significant_bin() {
        use crate::diagnose::fit::reach_m;
        use crate::physics::dropout::UniformDropout;
        let uniform = || -> Vec<Box<dyn crate::physics::Effect>> {
            vec![Box::new(UniformDropout {
                enabled: true,
                prob: 0.1,
            })]
        };
        let (sim, real) = (
            simulated_recording(7, 6, uniform()),
            simulated_recording(8, 6, uniform()),
        );
        let bins = BinOptions {
            reach_m: reach_m(&sim),
            ..BinOptions::default()
        };
        let count = |scans: &[ScanFeatures]| {
            let mut c = DropCounts::default();
            for s in scans {
                c.add(s, &bins);
            }
            c
        };
        let cmp = compare(&count(&sim), &count(&real), &bins, &TestOptions::default());
        assert!(cmp.tests.len() > 50);
        assert_eq!(cmp.significant().count(), 0, "{:?}", cmp.strongest());
    }
}

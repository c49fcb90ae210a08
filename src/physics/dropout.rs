//! Drop models: each gives the probability that a ray is lost, from the ray's
//! ideal features, in a closed form a diagnosis can fit by maximum likelihood.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::{Effect, RayFeatures};
use crate::sim::Material;
use crate::util::rng::gaussian;

fn yes() -> bool {
    true
}

/// Logistic in log space: `1 / (1 + (x50 / x)^(1 / softness))`, the drop
/// probability when log return power has logistic noise of scale `softness`.
fn log_logistic(x: f32, x50: f32, softness: f32) -> f32 {
    if x <= 0.0 {
        return 0.0;
    }
    1.0 / (1.0 + (x50 / x).powf(1.0 / softness.max(1e-3)))
}

/// `range_dropout`: return power falls as 1/d^2, so rays drop more with range:
/// `p = 1 / (1 + (range_50_m / d)^(2 / softness))`; half the rays drop at `range_50_m`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub range_50_m: f32,
    pub softness: f32,
}

impl Effect for RangeDropout {
    fn id(&self) -> &'static str {
        "range_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        if f.range_m <= 0.0 {
            return 0.0;
        }
        log_logistic(f.range_m, self.range_50_m, self.softness / 2.0)
    }
}

/// `incidence_dropout`: the returned power scales with cos(incidence) (Lambertian),
/// so grazing rays drop: `p = 1 / (1 + (cos(inc) / cos_50)^(1 / softness))`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IncidenceDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    /// cos(incidence) at which half the rays drop (0.1 = 84 deg).
    pub cos_50: f32,
    pub softness: f32,
}

impl Effect for IncidenceDropout {
    fn id(&self) -> &'static str {
        "incidence_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        1.0 - log_logistic(f.incidence_rad.cos().max(0.0), self.cos_50, self.softness)
    }
}

/// `edge_dropout`: rays on and beside depth edges return nothing more often: the beam's
/// footprint straddles two surfaces, and the split echo is too weak or too wide for the
/// detector; behind a near edge the receiver, offset from the emitter, may not see the spot
/// at all. `drop_prob_by_px[d]` is the drop probability `d` pixels along the row from the
/// nearest depth edge of the ideal scan (0 = on the edge); farther rays never drop. How
/// strong this is changes with range, so `bands` may give the rates per range band instead.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdgeDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub drop_prob_by_px: Vec<f32>,
    /// Rates per range band, nearest first (`from_m` ascending from 0); replaces
    /// `drop_prob_by_px`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bands: Vec<EdgeBand>,
}

/// The edge drop rates of rays from `from_m` up to the next band's start.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdgeBand {
    pub from_m: f32,
    pub drop_prob_by_px: Vec<f32>,
}

impl EdgeDropout {
    /// The drop rates by distance that apply at `range_m`.
    fn rates(&self, range_m: f32) -> &[f32] {
        match self.bands.iter().rposition(|b| range_m >= b.from_m) {
            Some(b) => &self.bands[b].drop_prob_by_px,
            None if self.bands.is_empty() => &self.drop_prob_by_px,
            None => &[],
        }
    }
}

impl Effect for EdgeDropout {
    fn id(&self) -> &'static str {
        "edge_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        self.rates(f.range_m)
            .get(usize::from(f.edge_px))
            .copied()
            .unwrap_or(0.0)
    }
}

/// `material_dropout`: a drop probability per material (glass transmits, dark
/// paint and rubber absorb); materials not listed never drop.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default)]
    pub drop_prob: BTreeMap<Material, f32>,
    /// Drop probability per semantic class (SemanticKITTI id), for data that has
    /// classes but no materials (real scans; what `diagnose` fits). A ray takes
    /// the larger of its material's and its class's probability.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub drop_prob_by_class: BTreeMap<u32, f32>,
}

impl Effect for MaterialDropout {
    fn id(&self) -> &'static str {
        "material_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        let by_material = self.drop_prob.get(&f.material).copied().unwrap_or(0.0);
        let by_class = self
            .drop_prob_by_class
            .get(&f.class)
            .copied()
            .unwrap_or(0.0);
        by_material.max(by_class)
    }
}

/// `beam_dropout`: weak or dead lasers. Per-beam drop rates, either listed
/// (`rates`, one per row, top first) or drawn once per sensor from `beam_seed` as
/// `mean_rate * exp(spread * N(0,1))`; `dead_beams` never return.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BeamDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rates: Option<Vec<f32>>,
    #[serde(default)]
    pub mean_rate: f32,
    #[serde(default)]
    pub spread: f32,
    #[serde(default)]
    pub beam_seed: u64,
    #[serde(default)]
    pub dead_beams: Vec<usize>,
}

impl BeamDropout {
    /// The drop rate of beam (row) `row`.
    pub fn rate(&self, row: usize) -> f32 {
        if self.dead_beams.contains(&row) {
            return 1.0;
        }
        match self.rates.as_ref().and_then(|r| r.get(row)) {
            Some(&r) => r,
            None => (self.mean_rate
                * (self.spread * gaussian(&[self.beam_seed, row as u64, 0xbea])).exp())
            .clamp(0.0, 1.0),
        }
    }
}

impl Effect for BeamDropout {
    fn id(&self) -> &'static str {
        "beam_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        self.rate(f.row)
    }
}

/// `self_occlusion`: the ego vehicle blocks a fixed set of directions, whatever
/// the scene. The region is a union of angular `sectors` (azimuth interval, below
/// an elevation) and `boxes` (sensor-frame boxes a ray passes through); a ray in
/// it drops with the region's `prob`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SelfOcclusion {
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default)]
    pub sectors: Vec<OcclusionSector>,
    #[serde(default)]
    pub boxes: Vec<OcclusionBox>,
}

/// Rays with azimuth in [`azimuth_min_deg`, `azimuth_max_deg`] (through +-180 when
/// min > max; 0 = ahead, counter-clockwise) and elevation at or below
/// `elevation_max_deg` drop with `prob`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OcclusionSector {
    pub azimuth_min_deg: f32,
    pub azimuth_max_deg: f32,
    pub elevation_max_deg: f32,
    #[serde(default = "one")]
    pub prob: f32,
}

/// Rays from the sensor origin that pass through `min_m`..`max_m` (sensor frame:
/// x forward, y left, z up) drop with `prob`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OcclusionBox {
    pub min_m: [f32; 3],
    pub max_m: [f32; 3],
    #[serde(default = "one")]
    pub prob: f32,
}

fn one() -> f32 {
    1.0
}

impl OcclusionSector {
    /// Whether a ray at `azimuth_rad`, `elevation_rad` lies in the sector.
    pub fn contains(&self, azimuth_rad: f32, elevation_rad: f32) -> bool {
        let (az, el) = (azimuth_rad.to_degrees(), elevation_rad.to_degrees());
        let in_az = if self.azimuth_min_deg <= self.azimuth_max_deg {
            (self.azimuth_min_deg..=self.azimuth_max_deg).contains(&az)
        } else {
            az >= self.azimuth_min_deg || az <= self.azimuth_max_deg
        };
        in_az && el <= self.elevation_max_deg
    }
}

impl OcclusionBox {
    /// Whether a ray from the sensor origin along `d` passes through the box.
    pub fn blocks(&self, d: [f32; 3]) -> bool {
        let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
        for (a, &da) in d.iter().enumerate() {
            let inv = 1.0 / da;
            let (mut ta, mut tb) = (self.min_m[a] * inv, self.max_m[a] * inv);
            if ta > tb {
                std::mem::swap(&mut ta, &mut tb);
            }
            t0 = t0.max(ta);
            t1 = t1.min(tb);
        }
        t0 <= t1
    }
}

impl SelfOcclusion {
    /// Drop probability of a ray: the largest over the regions it is in.
    pub fn block_prob(&self, f: &RayFeatures) -> f32 {
        let s = self
            .sectors
            .iter()
            .filter(|s| s.contains(f.azimuth_rad, f.elevation_rad))
            .map(|s| s.prob);
        let mut p = s.fold(0.0, f32::max);
        if !self.boxes.is_empty() {
            let d = super::Physics::direction(f);
            p = self
                .boxes
                .iter()
                .filter(|b| b.blocks(d))
                .map(|b| b.prob)
                .fold(p, f32::max);
        }
        p
    }
}

impl Effect for SelfOcclusion {
    fn id(&self) -> &'static str {
        "self_occlusion"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        self.block_prob(f)
    }
}

/// `uniform_dropout`: every ray drops with the same probability (CARLA's
/// `dropoff_general_rate`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UniformDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub prob: f32,
}

impl Effect for UniformDropout {
    fn id(&self) -> &'static str {
        "uniform_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, _f: &RayFeatures) -> f32 {
        self.prob
    }
}

/// `intensity_dropout`: CARLA's intensity-threshold drop. Intensity is
/// `exp(-attenuation_per_m * d)`; below `intensity_limit` a ray drops with `prob`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntensityDropout {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub attenuation_per_m: f32,
    pub intensity_limit: f32,
    pub prob: f32,
}

impl Effect for IntensityDropout {
    fn id(&self) -> &'static str {
        "intensity_dropout"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        if (-self.attenuation_per_m * f.range_m).exp() < self.intensity_limit {
            self.prob
        } else {
            0.0
        }
    }
}

/// A drop probability per pixel of a grid (row-major), e.g. measured on real data: the
/// baseline ray-drop models of the Sim2Real table (global and per-pixel frequency).
#[derive(Debug)]
pub struct DropMap {
    pub id: &'static str,
    /// Columns of the grid.
    pub width: usize,
    pub prob: Vec<f32>,
}

impl Effect for DropMap {
    fn id(&self) -> &'static str {
        self.id
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        self.prob
            .get(f.row * self.width + f.column)
            .copied()
            .unwrap_or(0.0)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::super::{Effect, Physics};
    use super::*;
    use crate::lidar::SensorProfile;
    use crate::sim::{SceneConfig, SimScan, Simulator};

    fn features(range_m: f32, incidence_deg: f32, material: Material, row: usize) -> RayFeatures {
        RayFeatures {
            row,
            column: 0,
            range_m,
            incidence_rad: incidence_deg.to_radians(),
            material,
            class: 0,
            reflectivity: 0.3,
            intensity: 0.2,
            azimuth_rad: 0.0,
            elevation_rad: 0.0,
            edge_px: crate::lidar::edges::MAX_EDGE_PX,
        }
    }

    #[test]
    fn edge_dropout_drops_by_distance_to_the_edge_and_only_there() {
        let e = EdgeDropout {
            enabled: true,
            drop_prob_by_px: vec![0.4, 0.1],
            bands: Vec::new(),
        };
        let at = |edge_px| RayFeatures {
            edge_px,
            ..features(10.0, 0.0, Material::Concrete, 10)
        };
        assert_eq!((e.drop_prob(&at(0)), e.drop_prob(&at(1))), (0.4, 0.1));
        assert_eq!(e.drop_prob(&at(2)), 0.0);
        // In a simulated scan: the drops concentrate where the ideal scan has depth edges.
        let (before, after) = before_after(Box::new(e), 5);
        let edges = crate::physics::ideal_edges(&before);
        let rate = |near: bool| {
            let (mut n, mut lost) = (0, 0);
            for (k, edge) in edges.iter().enumerate() {
                if before.is_return(k) && (*edge == 0) == near {
                    n += 1;
                    lost += usize::from(!after.is_return(k));
                }
            }
            lost as f64 / n.max(1) as f64
        };
        let (on, off) = (rate(true), rate(false));
        assert!((on - 0.4).abs() < 0.05, "on the edge {on}");
        assert!(off < 0.1, "off the edge {off}");
    }

    #[test]
    fn edge_dropout_bands_pick_the_rates_of_the_ray_range() {
        let band = |from_m, p: f32| EdgeBand {
            from_m,
            drop_prob_by_px: vec![p, p / 2.0],
        };
        let e = EdgeDropout {
            enabled: true,
            drop_prob_by_px: Vec::new(),
            bands: vec![band(0.0, 0.4), band(20.0, 0.2), band(40.0, 0.0)],
        };
        let at = |range_m, edge_px| RayFeatures {
            edge_px,
            ..features(range_m, 0.0, Material::Concrete, 10)
        };
        assert_eq!(e.drop_prob(&at(5.0, 0)), 0.4);
        assert_eq!(e.drop_prob(&at(19.9, 1)), 0.2);
        assert_eq!(e.drop_prob(&at(20.0, 0)), 0.2);
        assert_eq!(e.drop_prob(&at(60.0, 0)), 0.0);
        assert_eq!(
            e.drop_prob(&at(30.0, 2)),
            0.0,
            "beyond the listed distances"
        );
    }

    /// An ideal scan, and the same scan after `effect` (drop rates per pixel set).
    pub(crate) fn before_after(effect: Box<dyn Effect>, seed: u64) -> (SimScan, SimScan) {
        let sim = Simulator::new(
            SceneConfig {
                seed,
                duration_s: 0.5,
                ..Default::default()
            },
            SensorProfile::kitti_hdl64e().with_columns(1024),
        );
        let ideal = sim.scan(2);
        let mut real = ideal.clone();
        Physics {
            effects: vec![effect],
        }
        .apply(&mut real, seed);
        (ideal, real)
    }

    /// Share of ideal returns dropped among pixels selected by `pick`.
    fn drop_rate(ideal: &SimScan, real: &SimScan, pick: impl Fn(usize) -> bool) -> (f32, usize) {
        let sel: Vec<usize> = (0..ideal.len())
            .filter(|&k| ideal.is_return(k) && pick(k))
            .collect();
        let dropped = sel.iter().filter(|&&k| !real.is_return(k)).count();
        (dropped as f32 / sel.len().max(1) as f32, sel.len())
    }

    #[test]
    fn range_dropout_grows_with_range() {
        let e = RangeDropout {
            enabled: true,
            range_50_m: 40.0,
            softness: 0.5,
        };
        assert!((e.drop_prob(&features(40.0, 0.0, Material::Concrete, 0)) - 0.5).abs() < 1e-5);
        let (ideal, real) = before_after(Box::new(e), 1);
        let r = |k: usize| ideal.true_range_m[k];
        let (near, n1) = drop_rate(&ideal, &real, |k| r(k) < 10.0);
        let (mid, n2) = drop_rate(&ideal, &real, |k| (30.0..50.0).contains(&r(k)));
        let (far, n3) = drop_rate(&ideal, &real, |k| r(k) > 60.0);
        assert!(n1 > 1000 && n2 > 300 && n3 > 100, "{n1} {n2} {n3}");
        assert!(
            near < 0.05 && (mid - 0.5).abs() < 0.15 && far > 0.75,
            "near {near} mid {mid} far {far}"
        );
    }

    #[test]
    fn incidence_dropout_hits_grazing_rays_and_spares_head_on_ones() {
        let e = IncidenceDropout {
            enabled: true,
            cos_50: 0.15,
            softness: 0.25,
        };
        let (ideal, real) = before_after(Box::new(e), 2);
        let inc = |k: usize| ideal.incidence_rad[k].to_degrees();
        let (normal, n1) = drop_rate(&ideal, &real, |k| inc(k) < 45.0);
        let (grazing, n2) = drop_rate(&ideal, &real, |k| inc(k) > 85.0);
        assert!(n1 > 1000 && n2 > 100, "{n1} {n2}");
        assert!(
            normal < 0.01 && grazing > 0.6,
            "normal {normal} grazing {grazing}"
        );
    }

    #[test]
    fn material_dropout_is_conditioned_on_material() {
        let mut drop_prob = BTreeMap::new();
        drop_prob.insert(Material::Glass, 0.9);
        drop_prob.insert(Material::DarkPaint, 0.5);
        let (ideal, real) = before_after(
            Box::new(MaterialDropout {
                enabled: true,
                drop_prob,
                drop_prob_by_class: BTreeMap::new(),
            }),
            3,
        );
        let (glass, n1) = drop_rate(&ideal, &real, |k| ideal.material[k] == Material::Glass);
        let (asphalt, n2) = drop_rate(&ideal, &real, |k| ideal.material[k] == Material::Asphalt);
        assert!(n1 > 50 && n2 > 1000, "{n1} {n2}");
        assert!(
            (glass - 0.9).abs() < 0.1 && asphalt == 0.0,
            "glass {glass} asphalt {asphalt}"
        );
    }

    #[test]
    fn beam_dropout_gives_row_wise_rates() {
        let mut rates = vec![0.0; 64];
        rates[10] = 0.5;
        let e = BeamDropout {
            enabled: true,
            rates: Some(rates),
            mean_rate: 0.0,
            spread: 0.0,
            beam_seed: 0,
            dead_beams: vec![40],
        };
        let (ideal, real) = before_after(Box::new(e), 4);
        let w = ideal.width();
        for row in [5usize, 10, 40, 50] {
            let (rate, n) = drop_rate(&ideal, &real, |k| k / w == row);
            let expect = match row {
                10 => 0.5,
                40 => 1.0,
                _ => 0.0,
            };
            assert!(
                n > 100 && (rate - expect).abs() < 0.08,
                "row {row}: {rate} of {n}"
            );
        }
        // Drawn rates are fixed per sensor, vary by beam, stay in [0, 1].
        let drawn = BeamDropout {
            enabled: true,
            rates: None,
            mean_rate: 0.05,
            spread: 0.8,
            beam_seed: 9,
            dead_beams: vec![],
        };
        let r: Vec<f32> = (0..64).map(|row| drawn.rate(row)).collect();
        assert!(r.iter().all(|x| (0.0..=1.0).contains(x)));
        assert!(
            r.iter().cloned().fold(0.0, f32::max) > 2.0 * r.iter().cloned().fold(1.0, f32::min)
        );
    }

    #[test]
    fn self_occlusion_blocks_the_same_pixels_in_every_scene() {
        let e = SelfOcclusion {
            enabled: true,
            sectors: vec![OcclusionSector {
                azimuth_min_deg: 150.0,
                azimuth_max_deg: -150.0,
                elevation_max_deg: -18.0,
                prob: 1.0,
            }],
            boxes: vec![OcclusionBox {
                min_m: [-0.5, -2.0, -3.0],
                max_m: [0.5, 2.0, -0.5],
                prob: 1.0,
            }],
        };
        let dir = |az: f32, el: f32| RayFeatures {
            azimuth_rad: az.to_radians(),
            elevation_rad: el.to_radians(),
            ..features(10.0, 0.0, Material::Asphalt, 60)
        };
        assert_eq!(e.block_prob(&dir(180.0, -20.0)), 1.0);
        assert_eq!(e.block_prob(&dir(-170.0, -20.0)), 1.0);
        assert_eq!(e.block_prob(&dir(180.0, -10.0)), 0.0);
        assert_eq!(e.block_prob(&dir(0.0, -20.0)), 0.0);
        assert_eq!(
            e.block_prob(&dir(90.0, -20.0)),
            1.0,
            "the box beside the sensor"
        );
        assert_eq!(e.block_prob(&dir(0.0, 0.0)), 0.0);
        let blocked = |seed| {
            let (ideal, real) = before_after(Box::new(e.clone()), seed);
            (0..ideal.len())
                .filter(|&k| ideal.is_return(k) && !real.is_return(k))
                .collect::<Vec<_>>()
        };
        let (a, b) = (blocked(5), blocked(6));
        assert!(a.len() > 100, "{}", a.len());
        // Blocked pixels sit in the lower half only and are the same set in both scenes
        // (up to pixels that had no ideal return in one of them).
        let w = 1024;
        assert!(
            a.iter().all(|k| k / w >= 32),
            "blocked pixels outside the lower half"
        );
        let common = a.iter().filter(|k| b.binary_search(k).is_ok()).count();
        assert!(
            common as f32 > 0.9 * a.len().min(b.len()) as f32,
            "{common} of {} / {}",
            a.len(),
            b.len()
        );
    }

    #[test]
    fn uniform_dropout_drops_at_its_rate_everywhere() {
        let (ideal, real) = before_after(
            Box::new(UniformDropout {
                enabled: true,
                prob: 0.3,
            }),
            7,
        );
        let w = ideal.width();
        let (all, _) = drop_rate(&ideal, &real, |_| true);
        let (top, _) = drop_rate(&ideal, &real, |k| k / w < 32);
        let (bottom, _) = drop_rate(&ideal, &real, |k| k / w >= 32);
        assert!(
            (all - 0.3).abs() < 0.01 && (top - bottom).abs() < 0.03,
            "{all} {top} {bottom}"
        );
    }

    #[test]
    fn intensity_dropout_only_drops_far_rays() {
        let e = IntensityDropout {
            enabled: true,
            attenuation_per_m: 0.004,
            intensity_limit: 0.8,
            prob: 0.4,
        };
        // exp(-0.004 d) < 0.8  <=>  d > 55.8 m
        assert_eq!(e.drop_prob(&features(50.0, 0.0, Material::Brick, 0)), 0.0);
        assert_eq!(e.drop_prob(&features(60.0, 0.0, Material::Brick, 0)), 0.4);
        let (ideal, real) = before_after(Box::new(e), 8);
        let (near, _) = drop_rate(&ideal, &real, |k| ideal.true_range_m[k] < 55.0);
        let (far, n) = drop_rate(&ideal, &real, |k| ideal.true_range_m[k] > 57.0);
        assert!(
            near == 0.0 && n > 50 && (far - 0.4).abs() < 0.12,
            "{near} {far} {n}"
        );
    }
}

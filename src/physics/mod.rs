//! Sensor physics that turns an ideal simulated scan into a realistic one: the
//! effects catalogue. Each effect is one small type implementing [`Effect`],
//! selected by its catalogue id and switched on with parameters in a
//! [`PhysicsConfig`] (JSON file or preset). All off = the ideal simulator.
//!
//! Two kinds of effect, both with a likelihood-friendly form for diagnosis:
//! - **drop models** give a drop probability per ray from its ideal features
//!   ([`RayFeatures`]: row, column, true range, incidence, material, reflectivity,
//!   intensity, azimuth, elevation, distance to a depth edge). Each draws independently, so a ray's keep
//!   probability is the product of `1 - p` over the enabled drop effects.
//! - **perturbations** move kept returns (range noise, quantisation, mixed pixels
//!   at depth edges, motion distortion), change intensity, or add clutter returns.
//!
//! Every random draw is keyed by (scene seed, scan index, pixel, effect id), so a
//! result never depends on threads or on which other effects are enabled.
//! The Sim2Real diagnosis ([`crate::diagnose`]) fits these effects; this module
//! does not depend on it.

pub mod config;
pub mod dropout;
pub mod perturb;
pub mod pretraining;

pub use config::{PhysicsConfig, PhysicsError, Preset};

use crate::lidar::edges::{EDGE_RELATIVE_JUMP, EdgeAxes, MAX_EDGE_PX, edge_proximity};
use crate::sim::{Material, SimScan};
use crate::util::rng::{gaussian, key_hash, uniform};

/// What a drop model may look at for one ray: its ideal (pre-physics) features.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayFeatures {
    pub row: usize,
    pub column: usize,
    /// True first-hit range, meters.
    pub range_m: f32,
    pub incidence_rad: f32,
    pub material: Material,
    /// Semantic class of the surface (SemanticKITTI id, low 16 bits of the label;
    /// 0 = unknown). Real data has classes where it has no materials.
    pub class: u32,
    pub reflectivity: f32,
    /// Ideal intensity (reflectivity x cos(incidence) x range falloff).
    pub intensity: f32,
    /// Ray azimuth (0 = ahead, counter-clockwise) and elevation, radians.
    pub azimuth_rad: f32,
    pub elevation_rad: f32,
    /// Pixels along the row to the nearest depth edge of the ideal scan (0 = on one; capped
    /// at [`MAX_EDGE_PX`]; [`EdgeAxes::Row`]).
    pub edge_px: u8,
}

impl RayFeatures {
    /// Features of pixel `k` of an ideal scan whose depth-edge distances are `edge_px`
    /// ([`ideal_edges`]).
    pub fn of(scan: &SimScan, k: usize, edge_px: &[u8]) -> Self {
        let w = scan.width();
        RayFeatures {
            row: k / w,
            column: k % w,
            range_m: scan.true_range_m[k],
            incidence_rad: scan.incidence_rad[k],
            material: scan.material[k],
            class: scan.true_label[k] & 0xffff,
            reflectivity: scan.reflectivity[k],
            intensity: scan.image.intensity[k],
            azimuth_rad: scan.image.angles.azimuth_rad[k],
            elevation_rad: scan.image.angles.elevation_rad[k],
            edge_px: edge_px[k],
        }
    }
}

/// Depth-edge distance along the row of every pixel of an ideal scan, from its true
/// first-hit ranges (columns wrap: the simulator casts a full turn).
pub fn ideal_edges(scan: &SimScan) -> Vec<u8> {
    let range: Vec<f32> = scan
        .true_range_m
        .iter()
        .map(|r| if *r > 0.0 { *r } else { f32::NAN })
        .collect();
    edge_proximity(
        &range,
        scan.width(),
        true,
        EdgeAxes::Row,
        EDGE_RELATIVE_JUMP,
        MAX_EDGE_PX,
    )
}

/// Keys for an effect's random draws within one scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EffectContext {
    pub seed: u64,
    pub scan_index: u32,
}

impl EffectContext {
    /// Uniform [0, 1) draw for pixel `k` and stream `salt`.
    pub fn uniform(&self, salt: u64, k: usize) -> f32 {
        uniform(&[self.seed, self.scan_index as u64, k as u64, salt])
    }
    /// Standard normal draw for pixel `k` and stream `salt`.
    pub fn gaussian(&self, salt: u64, k: usize) -> f32 {
        gaussian(&[self.seed, self.scan_index as u64, k as u64, salt])
    }
}

/// A stable per-effect stream id from its catalogue id.
pub fn salt(id: &str) -> u64 {
    key_hash(&id.bytes().map(u64::from).collect::<Vec<_>>())
}

/// One physical effect of the catalogue.
pub trait Effect: std::fmt::Debug + Send + Sync {
    /// The catalogue id (`range_dropout`, `incidence_dropout`, ...).
    fn id(&self) -> &'static str;

    /// Probability that this effect drops a ray with these ideal features
    /// (0 for effects that do not drop rays).
    fn drop_prob(&self, _features: &RayFeatures) -> f32 {
        0.0
    }

    /// Whether [`Effect::drop_prob`] is meaningful (a drop model).
    fn drops(&self) -> bool {
        false
    }

    /// Changes the returns after all drops (perturbation effects; a drop model may
    /// also perturb, e.g. the atmosphere dims what it does not drop).
    fn perturb(&self, _scan: &mut SimScan, _ctx: &EffectContext) {}
}

/// An ordered set of enabled effects: drop models first, then perturbations in
/// a fixed physical order (see [`PhysicsConfig::effects`]).
#[derive(Debug, Default)]
pub struct Physics {
    pub effects: Vec<Box<dyn Effect>>,
}

impl Physics {
    pub fn ideal() -> Self {
        Physics::default()
    }

    pub fn is_ideal(&self) -> bool {
        self.effects.is_empty()
    }

    /// Ids of the enabled effects, in application order.
    pub fn ids(&self) -> Vec<&'static str> {
        self.effects.iter().map(|e| e.id()).collect()
    }

    /// Keep probability of a ray under all drop models (1 - p multiplied).
    pub fn keep_prob(&self, features: &RayFeatures) -> f32 {
        self.effects
            .iter()
            .filter(|e| e.drops())
            .map(|e| 1.0 - e.drop_prob(features).clamp(0.0, 1.0))
            .product()
    }

    /// Unit direction (sensor frame) of a ray with these features.
    pub fn direction(features: &RayFeatures) -> [f32; 3] {
        let (se, ce) = features.elevation_rad.sin_cos();
        let (sa, ca) = features.azimuth_rad.sin_cos();
        [ce * ca, ce * sa, se]
    }

    /// Applies every enabled effect to an ideal scan, in place. `seed` is the scene seed.
    pub fn apply(&self, scan: &mut SimScan, seed: u64) {
        let ctx = EffectContext {
            seed,
            scan_index: scan.index,
        };
        let drops: Vec<(&dyn Effect, u64)> = self
            .effects
            .iter()
            .filter(|e| e.drops())
            .map(|e| (e.as_ref(), salt(e.id())))
            .collect();
        if !drops.is_empty() {
            let edges = ideal_edges(scan);
            for k in 0..scan.len() {
                if !scan.is_return(k) {
                    continue;
                }
                let f = RayFeatures::of(scan, k, &edges);
                // Every model draws, so each effect's draws are independent of the others.
                let mut dropped = false;
                for (effect, salt) in &drops {
                    dropped |= ctx.uniform(*salt, k) < effect.drop_prob(&f);
                }
                if dropped {
                    scan.drop_return(k);
                }
            }
        }
        for effect in &self.effects {
            effect.perturb(scan, &ctx);
        }
    }
}

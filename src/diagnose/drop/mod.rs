//! The candidate drop models of the diagnosis, one [`DropFamily`] each: what
//! feature bin a pixel falls in and how the per-bin drop probabilities are fitted
//! by maximum likelihood (see `fit` for the model and the selection).
//!
//! | family | feature | model |
//! |---|---|---|
//! | `range_dropout` | completed range (drops only where returns enclose them), 1 m bins | the physics module's log-logistic curve (range_50_m, softness) |
//! | `incidence_dropout` | cos(incidence) of the completed normal, 0.02 bins | log-logistic in cos (cos_50, softness) |
//! | `beam_dropout` | row | one free rate per row |
//! | `material_dropout` | semantic class (labels, else neighbours' labels) | one free rate per class |
//! | `edge_dropout` | pixels along the row to the nearest depth edge of the completed range, 0-8 | a free rate for 0-3 px above the rate far from edges |
//! | `self_occlusion` | (row, azimuth sector) in the lower half | per sector a "skyline" of blocked bottom rows and a probability |
//!
//! One file per kind: `curve` (range and incidence curves), `rates` (free rates
//! per laser, edge distance and class) and `self_occlusion`. Motion distortion drops
//! nothing: a sensor fires each beam at its own encoder angle however it moves, so its
//! returns keep their pixels and only their ranges move (`residual`).

mod curve;
mod rates;
mod self_occlusion;

pub use curve::{IncidenceFamily, RangeFamily};
pub use rates::{BeamFamily, ClassFamily, EdgeFamily};
pub use self_occlusion::SelfOcclusionFamily;

use super::fit::{DropFamily, QTable};

/// All drop candidates.
pub fn families() -> Vec<Box<dyn DropFamily>> {
    vec![
        Box::new(RangeFamily),
        Box::new(IncidenceFamily),
        Box::new(BeamFamily),
        Box::new(ClassFamily),
        Box::new(SelfOcclusionFamily),
        Box::new(EdgeFamily),
    ]
}

/// Grid search of a two-parameter curve: the (a, b, per-bin probs) with the
/// smallest NLL.
pub(super) fn fit_curve(
    table: &QTable,
    grid_a: &[f32],
    grid_b: &[f32],
    probs: impl Fn(f32, f32) -> Vec<f64>,
) -> Option<(f32, f32, Vec<f64>)> {
    let mut best: Option<(f64, f32, f32, Vec<f64>)> = None;
    for &a in grid_a {
        for &b in grid_b {
            let p = probs(a, b);
            let nll = table.nll(&p);
            if best.as_ref().is_none_or(|x| nll < x.0) {
                best = Some((nll, a, b, p));
            }
        }
    }
    best.map(|(_, a, b, p)| (a, b, p))
}

pub(super) fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

//! Maximum-likelihood selection of the drop models a simulator left out.
//!
//! Every pixel of a real scan is kept with probability
//! `keep = c · B(x) · Π_e (1 − p_e(x))`:
//! - `B(x)`, the **baseline**, is the simulated recording's own keep rate in the
//!   pixel's (row, completed-range) cell, smoothed towards the range marginal. It
//!   holds what both sides share (no-hit sky, the sensor's reach, fill artefacts)
//!   and the simulator's physics as given.
//! - `c` is a free keep-rate scale (the null model: "only the overall rate differs").
//! - `p_e` are candidate effects ([`DropFamily`]): each maps a pixel to one bin of
//!   its own feature (range, cos incidence, row, class, row × azimuth cell) and
//!   fits a drop probability per bin (a parametric curve or free rates).
//!
//! Selection is greedy forward: each round fits every remaining candidate on the
//! real *training* scans given the effects already chosen, and keeps the one
//! whose held-out gain (NLL per pixel on the real *test* scans, over the current
//! model with `c` refitted) beats its penalty (BIC term, at least
//! [`MIN_GAIN_NATS`]); of two that read the same drops, the one with fewer
//! parameters ([`simpler_rival`]). Nothing is claimed that does not beat the null on
//! held-out data.
//!
//! Fitting one candidate given the others is cheap: pixels are pooled into a
//! [`QTable`] by (candidate bin, level of the rest-of-model keep probability `q`),
//! and the likelihood of any per-bin drop curve is a sum over its cells.
//!
//! One file per part: `pixels` (the pixels a fit uses) with `enclosure` and
//! `level_plane`, `baseline` (`B(x)`), `likelihood` (the NLL and the fit of one
//! candidate given the others) and `select` (the forward selection).

mod baseline;
mod enclosure;
mod level_plane;
mod likelihood;
mod pixels;
mod select;
#[cfg(test)]
mod tests;

#[cfg(doc)]
use select::simpler_rival;

pub use baseline::Baseline;
pub use enclosure::{ENCLOSED_PX, ENCLOSURE_CAP_PX};
pub use likelihood::{QTable, golden, mask_nll};
pub use pixels::{Pixels, REACH_FRACTION, REACH_QUANTILE, kept_range_quantile, reach_m};
pub use select::{DropSelection, FitError, Selected, Tried, keep_under, select};

/// Smallest held-out gain (nats per pixel) an effect must show: pixels of a scan
/// are correlated, so the BIC term alone (which assumes independence) is too lax.
pub const MIN_GAIN_NATS: f64 = 3e-3;

/// One fitted drop model: a drop probability per bin of its family.
#[derive(Debug, Clone, PartialEq)]
pub struct DropFit {
    pub drop_prob: Vec<f64>,
    /// Fitted parameters, as the report shows them.
    pub params: serde_json::Map<String, serde_json::Value>,
    /// The effect as physics-config entries (catalogue id -> parameters), so the
    /// fitted physics can be rendered.
    pub physics: serde_json::Map<String, serde_json::Value>,
    /// Number of free parameters (for the penalty).
    pub n_params: usize,
    /// Where the effect acts, in words.
    pub location: String,
}

/// A candidate drop model: which bin of its feature a pixel falls in, and how the
/// per-bin drop probabilities are fitted.
pub trait DropFamily: Sync {
    /// The catalogue id.
    fn id(&self) -> &'static str;
    /// Number of bins on this pixel set's grid.
    fn bins(&self, px: &Pixels) -> usize;
    /// Bin of pixel `i`, or None where the effect cannot act (unknown feature).
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize>;
    /// Every pixel's bin: a family whose feature comes from a pixel's context computes
    /// it once per context here.
    fn bins_of(&self, px: &Pixels) -> Vec<Option<usize>> {
        (0..px.len()).map(|i| self.bin(px, i)).collect()
    }
    /// Maximum-likelihood fit given the pooled table (None: nothing to fit).
    fn fit(&self, table: &QTable, px: &Pixels) -> Option<DropFit>;
    /// Whether the effect acts the same in every direction (sensor physics
    /// does; scenes do not): then it must improve the held-out fit both ahead
    /// and behind the sensor to be claimed.
    fn azimuth_invariant(&self) -> bool {
        true
    }
}

//! Scoring a spatial model on whole held-out scans, decoded as `convert` decodes them: x_d
//! against the returns it saw, depth in medium patches cut into the scan (as drops, as a user's
//! scan shows them) against the truth, and x_n's likelihood of the true mask inside those
//! patches when they are unknown to the model, beside the per-beam drop rate of the rest of
//! the scan (the simple baseline x_n must beat).

use serde::Serialize;

use super::data::Source;
use crate::lidar::holes::HoleKind;
use crate::model::spatial::decode::{HostModel, decode, rays_of};
use crate::model::spatial::{Ray, SpatialConfig, SpatialNet};
use crate::util::rng::Rng;

/// Scans per validation source (spread over it).
const SCANS: usize = 4;

#[derive(Debug, Clone, Serialize)]
pub struct SourceScore {
    pub source: String,
    pub scans: usize,
    /// Mean |x_d - r| / r over the returns the model saw.
    pub seen_rel_l1: f64,
    /// The same over the true returns inside the cut patches.
    pub hole_rel_l1: f64,
    /// Mean NLL of the true keep mask inside the patches under x_n ...
    pub hole_drop_nll: f64,
    /// ... and under each beam's drop rate outside them.
    pub hole_row_rate_nll: f64,
}

/// Scores `net` on each source.
pub fn score(net: &SpatialNet, config: &SpatialConfig, sources: &[Source]) -> Vec<SourceScore> {
    let model = HostModel::new(net, config);
    sources.iter().map(|s| score_source(&model, s)).collect()
}

/// What chooses between states: hole depth error plus the x_n likelihood ratio, summed over
/// sources (lower is better).
pub fn selection_score(scores: &[SourceScore]) -> f64 {
    scores
        .iter()
        .map(|s| s.hole_rel_l1 + 0.1 * s.hole_drop_nll / s.hole_row_rate_nll.max(1e-9))
        .sum()
}

fn score_source(model: &HostModel, source: &Source) -> SourceScore {
    let config = &model.config;
    let (h, w) = (source.angles.height, source.angles.width);
    let picks: Vec<usize> = (0..SCANS.min(source.scans.len()))
        .map(|i| i * source.scans.len() / SCANS.min(source.scans.len()))
        .collect();
    let mut seen = Mean::default();
    let mut hole = Mean::default();
    let mut nll = Mean::default();
    let mut base = Mean::default();
    for &i in &picks {
        let truth = &source.scans[i];
        let holes = HoleKind::Medium.cut(truth, h, w, &mut Rng::keyed(17, i as u64));
        let observed: Vec<f32> = truth
            .iter()
            .zip(&holes)
            .map(|(&r, &cut)| if cut { 0.0 } else { r })
            .collect();
        let out = decode(model, &rays_of(&observed), &source.angles);
        let unseen = decode(model, &unknown_in(&observed, &holes), &source.angles);
        let row_keep = row_keep_rates(&observed, &holes, h, w);
        for k in 0..h * w {
            let ret = truth[k] > config.min_range_m && truth[k] <= config.max_range_m;
            let rel = |d: f32| ((d - truth[k]) / truth[k]).abs() as f64;
            if !holes[k] {
                if ret {
                    seen.add(rel(out.depth_m[k]));
                }
                continue;
            }
            if ret {
                hole.add(rel(out.depth_m[k]));
            }
            nll.add(bernoulli_nll(1.0 - unseen.drop_prob[k], ret));
            base.add(bernoulli_nll(row_keep[k / w], ret));
        }
    }
    SourceScore {
        source: source.name.clone(),
        scans: picks.len(),
        seen_rel_l1: seen.get(),
        hole_rel_l1: hole.get(),
        hole_drop_nll: nll.get(),
        hole_row_rate_nll: base.get(),
    }
}

/// The rays of `observed` with those in `holes` unknown.
pub fn unknown_in(observed: &[f32], holes: &[bool]) -> Vec<Ray> {
    rays_of(observed)
        .into_iter()
        .zip(holes)
        .map(|(r, &hole)| if hole { Ray::Unknown } else { r })
        .collect()
}

/// Each beam's share of returns among its rays outside `holes`.
pub fn row_keep_rates(observed: &[f32], holes: &[bool], h: usize, w: usize) -> Vec<f32> {
    (0..h)
        .map(|i| {
            let (mut kept, mut all) = (0usize, 0usize);
            for j in 0..w {
                let k = i * w + j;
                if !holes[k] {
                    all += 1;
                    kept += usize::from(observed[k] > 0.0);
                }
            }
            // One pseudo-count each way keeps the rate off 0 and 1.
            (kept as f32 + 1.0) / (all as f32 + 2.0)
        })
        .collect()
}

/// -ln p(returned) under keep probability `keep` (clamped off 0 and 1).
pub fn bernoulli_nll(keep: f32, returned: bool) -> f64 {
    let p = (keep as f64).clamp(1e-4, 1.0 - 1e-4);
    if returned { -p.ln() } else { -(1.0 - p).ln() }
}

#[derive(Default)]
struct Mean(f64, usize);

impl Mean {
    fn add(&mut self, v: f64) {
        self.0 += v;
        self.1 += 1;
    }
    fn get(&self) -> f64 {
        if self.1 == 0 {
            0.0
        } else {
            self.0 / self.1 as f64
        }
    }
}

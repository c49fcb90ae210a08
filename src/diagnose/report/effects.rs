//! The named effects and the candidates tried, as the report lists them: from the drop
//! selection and the range-residual fits, with the fitted physics and their ranking.

use serde_json::{Map, Value};

use super::{CandidateReport, EffectReport, FitMetric, MOTION};
use crate::diagnose::fit::DropSelection;
use crate::diagnose::residual::ResidualFit;
use crate::diagnose::stats::{Comparison, Feature};

fn confidence(gain: f64, penalty: f64) -> f64 {
    if penalty <= 0.0 {
        return 1.0;
    }
    (1.0 - (-(gain / penalty - 1.0)).exp()).clamp(0.0, 1.0)
}

fn stats_feature(id: &str) -> Option<Feature> {
    match id {
        "range_dropout" => Some(Feature::Range),
        "incidence_dropout" => Some(Feature::Incidence),
        "beam_dropout" => Some(Feature::Row),
        "material_dropout" => Some(Feature::Class),
        "self_occlusion" => Some(Feature::Azimuth),
        "edge_dropout" => Some(Feature::EdgeProximity),
        _ => None,
    }
}

/// The reports of the selected drop effects, their physics added to `physics`. The drop
/// side of motion distortion is returned apart (gain, location): it joins the motion effect
/// the seam's range steps found.
pub(super) fn drop_effects(
    selection: &DropSelection,
    comparison: &Comparison,
    physics: &mut Map<String, Value>,
) -> Vec<EffectReport> {
    let mut effects = Vec::new();
    for s in &selection.selected {
        let mut location = s.fit.location.clone();
        if let Some(t) = stats_feature(s.id).and_then(|f| comparison.strongest_of(f)) {
            location.push_str(&format!(
                "; strongest divergence of this feature: {} (real {:.1} % vs sim {:.1} % dropped)",
                t.description,
                100.0 * t.rate_real,
                100.0 * t.rate_sim
            ));
        }
        effects.push(EffectReport {
            id: s.id.to_string(),
            confidence: confidence(s.gain(), s.penalty),
            location,
            params: s.fit.params.clone(),
            fit: FitMetric {
                metric: "drop_mask_nll_per_pixel".into(),
                before: selection.before_nll,
                after: s.nll_with,
            },
            gain_nats_per_pixel: s.gain(),
        });
        physics.extend(s.fit.physics.clone());
    }
    effects
}

/// The range-residual effects that were significant, and the held-out NLL in nats summed
/// over observations before and after them.
pub(super) struct ResidualEffects {
    pub(super) effects: Vec<EffectReport>,
    pub(super) before_nats: f64,
    pub(super) after_nats: f64,
}

/// The reports of the significant range-residual effects, their physics added to
/// `physics`.
pub(super) fn residual_effects(
    fits: &[ResidualFit],
    test_pixels: f64,
    physics: &mut Map<String, Value>,
) -> ResidualEffects {
    let mut out = ResidualEffects {
        effects: Vec::new(),
        before_nats: 0.0,
        after_nats: 0.0,
    };
    for r in fits {
        let n = r.test_obs as f64;
        out.before_nats += r.before_nll * n;
        if !r.significant() {
            out.after_nats += r.before_nll * n;
            continue;
        }
        out.after_nats += r.after_nll * n;
        let location = r.location.clone();
        let gain = r.gain() * n / test_pixels;
        out.effects.push(EffectReport {
            id: r.id.to_string(),
            confidence: confidence(r.gain(), r.penalty),
            location,
            params: r.params.clone(),
            fit: FitMetric {
                metric: format!("{}_nll_per_observation", r.id),
                before: r.before_nll,
                after: r.after_nll,
            },
            gain_nats_per_pixel: gain,
        });
        physics.extend(r.physics.clone());
    }
    out
}

/// Every candidate tried, drop and range-residual, with its gain and penalty.
pub(super) fn candidates(
    selection: &DropSelection,
    residual_fits: &[ResidualFit],
) -> Vec<CandidateReport> {
    let drop = selection
        .tried
        .iter()
        .filter(|t| t.id != MOTION)
        .map(|t| CandidateReport {
            id: t.id.to_string(),
            gain: t.gain,
            penalty: t.penalty,
            significant: selection.selected.iter().any(|s| s.id == t.id),
        });
    let residual = residual_fits.iter().map(|r| CandidateReport {
        id: r.id.to_string(),
        gain: r.gain(),
        penalty: r.penalty,
        significant: r.significant(),
    });
    drop.chain(residual).collect()
}

/// Folds the fitted keep scale `c` into the physics' uniform dropout:
/// keep `c (1 - u)` = `1 - u'`.
pub(super) fn adjust_uniform(physics: &mut Map<String, Value>, c: f64) {
    let u = physics
        .get("uniform_dropout")
        .filter(|e| e.get("enabled").and_then(Value::as_bool) != Some(false))
        .and_then(|e| e.get("prob"))
        .and_then(Value::as_f64)
        .unwrap_or(0.0);
    let u_new = (1.0 - c * (1.0 - u)).clamp(0.0, 1.0);
    if (u_new - u).abs() > 1e-3 {
        physics.insert(
            "uniform_dropout".into(),
            serde_json::json!({ "prob": (u_new * 1e4).round() / 1e4 }),
        );
    }
}

/// Orders the named effects: those `established` by a statistic of their own (motion: the
/// seam's range step, measured per seam step, not per pixel) first; then by held-out gain.
pub(super) fn rank(effects: &mut [EffectReport], established: &[&str]) {
    let first = |e: &EffectReport| established.contains(&e.id.as_str());
    effects.sort_by(|a, b| {
        first(b)
            .cmp(&first(a))
            .then(b.gain_nats_per_pixel.total_cmp(&a.gain_nats_per_pixel))
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn established_effects_rank_first_then_by_gain() {
        let effect = |id: &str, gain: f64| EffectReport {
            id: id.into(),
            confidence: 1.0,
            location: String::new(),
            params: Map::new(),
            fit: FitMetric {
                metric: String::new(),
                before: 1.0,
                after: 0.9,
            },
            gain_nats_per_pixel: gain,
        };
        let mut effects = vec![
            effect("edge_dropout", 0.02),
            effect("motion_distortion", 0.01),
            effect("range_noise", 0.5),
        ];
        rank(&mut effects, &["motion_distortion"]);
        let ids: Vec<&str> = effects.iter().map(|e| e.id.as_str()).collect();
        assert_eq!(ids, ["motion_distortion", "range_noise", "edge_dropout"]);
        rank(&mut effects, &[]);
        let ids: Vec<&str> = effects.iter().map(|e| e.id.as_str()).collect();
        assert_eq!(ids, ["range_noise", "edge_dropout", "motion_distortion"]);
    }
}

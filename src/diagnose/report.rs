//! Sim2Real diagnosis, end to end on projected scans: features of both
//! recordings, where the drop rates diverge (`stats`), which left-out
//! effects explain the divergence (`fit` with the drop candidates of
//! `drop`, and `residual` for effects that move returns), and
//! the numbers the report and its plots show. No I/O: the CLI reads the
//! recordings and writes the report (`crate::report`).

use rayon::prelude::*;
use serde::Serialize;
use serde_json::{Map, Value};

use super::drop;
use super::features::ScanFeatures;
use super::fit::{self, Baseline, DropFamily, DropSelection, FitError, Pixels};
use super::residual::{self, ResidualContext, ResidualFit};
use super::stats::{BinOptions, BinTest, Comparison, DropCounts, Feature, TestOptions, compare};

/// Settings of a diagnosis.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagnoseOptions {
    /// Most drop effects the forward selection may add.
    pub max_effects: usize,
    pub tests: TestOptions,
    pub residual: ResidualContext,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        DiagnoseOptions {
            max_effects: 3,
            tests: TestOptions::default(),
            residual: ResidualContext {
                speed_mps: None,
                period_s: 0.1,
            },
        }
    }
}

/// A before/after pair of one metric on held-out real scans (lower is better).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FitMetric {
    pub metric: String,
    pub before: f64,
    pub after: f64,
}

/// One effect judged significant.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EffectReport {
    pub id: String,
    pub confidence: f64,
    pub location: String,
    pub params: Map<String, Value>,
    pub fit: FitMetric,
    /// Held-out gain, nats per held-out pixel (the ranking key after established effects).
    pub gain_nats_per_pixel: f64,
}

/// A candidate that was tried, significant or not.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CandidateReport {
    pub id: String,
    /// Held-out gain over the null in its own metric's units.
    pub gain: f64,
    pub penalty: f64,
    pub significant: bool,
}

/// One significant bin of the drop-rate comparison.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MismatchReport {
    pub feature: String,
    #[serde(rename = "where")]
    pub location: String,
    pub rate_sim: f64,
    pub rate_real: f64,
    pub q_value: f64,
}

/// Sizes and rates of the inputs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InputsReport {
    pub sim_scans: usize,
    pub real_scans: usize,
    pub real_train_scans: usize,
    pub real_test_scans: usize,
    pub rows: usize,
    pub columns: usize,
    pub drop_rate_sim: f64,
    pub drop_rate_real: f64,
    pub reach_m: f32,
    /// How dropped pixels were completed: `neighbour-fill` or `gan`.
    pub completion: String,
    /// The generator (and encoder) of a GAN completion.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub completion_model: Option<String>,
    /// Scans the GAN could not decode, completed by the neighbour fill instead.
    pub completion_fallback_scans: usize,
    /// Tests and candidates left out, and why: one side lacks their feature, or (for
    /// `incidence_dropout`) the drop rates by incidence show no grazing contrast.
    pub left_out: Vec<String>,
}

/// The report (`report.json`): `effects` and `fit` are the contract other
/// programs read; the rest is detail.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    pub effects: Vec<EffectReport>,
    pub fit: FitMetric,
    /// The fitted keep-rate scale `c` (1 = the sim's overall rate is right).
    pub keep_scale: f64,
    pub candidates: Vec<CandidateReport>,
    pub mismatch: Vec<MismatchReport>,
    pub inputs: InputsReport,
    /// The sim's physics plus the fitted effects, as a physics JSON entry set
    /// (render it with `render --physics`).
    pub fitted_physics: Map<String, Value>,
    /// The fitted model against the held-out real scans, feature by feature.
    pub check: Vec<FeatureCheck>,
}

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

/// Drop rate against one feature: real, sim, and the fitted model.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    pub feature: &'static str,
    pub unit: &'static str,
    /// Bin centres.
    pub x: Vec<f64>,
    pub real: Vec<f64>,
    pub sim: Vec<f64>,
    pub fitted: Vec<f64>,
    /// Held-out real pixels per bin.
    pub real_pixels: Vec<f64>,
}

/// Per-pixel maps on the scan grid (row-major), for images.
#[derive(Debug, Clone, PartialEq)]
pub struct Maps {
    pub height: usize,
    pub width: usize,
    /// Drop frequency per pixel over the held-out real scans / the sim scans.
    pub real_drop: Vec<f32>,
    pub sim_drop: Vec<f32>,
    /// Extra drop probability the fitted effects add, mean over held-out scans.
    pub fitted_extra_drop: Vec<f32>,
    /// One held-out real scan: range (0 = dropped) and the located mismatch.
    pub example_range_m: Vec<f32>,
    pub example_highlight: Vec<f32>,
}

/// Everything a report shows.
#[derive(Debug, Clone, PartialEq)]
pub struct Diagnosis {
    pub report: Report,
    pub curves: Vec<Curve>,
    pub maps: Maps,
}

/// Errors of a diagnosis.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DiagnoseError {
    #[error(
        "the real recording needs at least 2 scans (one to fit on, one to test on); it has {0}"
    )]
    TooFewRealScans(usize),
    #[error("the simulated recording has no scans")]
    NoSimScans,
    #[error(
        "the scan grids differ: sim {sim_h}x{sim_w}, real {real_h}x{real_w}; project both onto one sensor profile (--sensor, --columns)"
    )]
    GridMismatch {
        sim_h: usize,
        sim_w: usize,
        real_h: usize,
        real_w: usize,
    },
    #[error(transparent)]
    Fit(#[from] FitError),
}

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

/// Diagnoses `real` against `sim`: real scans alternate between fitting (even)
/// and held-out testing (odd). `sim_physics` is the sim's own physics (JSON
/// object of catalogue entries), the base the fitted effects are added to.
pub fn diagnose(
    sim: &[ScanFeatures],
    real: &[ScanFeatures],
    sim_physics: &Map<String, Value>,
    completion: &str,
    options: &DiagnoseOptions,
) -> Result<Diagnosis, DiagnoseError> {
    let r0 = check_inputs(sim, real)?;
    let train: Vec<ScanFeatures> = real.iter().step_by(2).cloned().collect();
    let test: Vec<ScanFeatures> = real.iter().skip(1).step_by(2).cloned().collect();
    let reach_m = fit::reach_m(sim);

    // Where: conditional drop rates, BH-corrected.
    let bins = BinOptions {
        reach_m,
        ..BinOptions::default()
    };
    let (mut c_sim, mut c_real) = (DropCounts::default(), DropCounts::default());
    sim.iter().for_each(|f| c_sim.add(f, &bins));
    real.iter().for_each(|f| c_real.add(f, &bins));
    // A side without labels makes every pixel "class 0": comparing classes
    // would report that artefact, so the class test and candidate are left out.
    let mut left_out = Vec::new();
    let unlabelled: Vec<&str> = [("sim", sim), ("real", real)]
        .iter()
        .filter(|(_, scans)| !labelled(scans))
        .map(|(side, _)| *side)
        .collect();
    if !unlabelled.is_empty() {
        for c in [&mut c_sim, &mut c_real] {
            c.bins.retain(|(feature, _), _| *feature != Feature::Class);
        }
        left_out.push(format!(
            "material_dropout and the drop rate by class: the {} recording has no semantic labels",
            unlabelled.join(" and ")
        ));
    }
    let comparison = compare(&c_sim, &c_real, &bins, &options.tests);
    // Grazing drops are a candidate only where the grazing bins lose more rays beyond
    // the sim than the rest do: a fit can otherwise read a scene's far ground as an
    // incidence curve at the grid's edge.
    let grazing = grazing_contrast(&comparison, bins.incidence_step_deg);
    let incidence_testable = grazing.is_none_or(|c| c >= MIN_GRAZING_CONTRAST);
    if let Some(c) = grazing.filter(|_| !incidence_testable) {
        left_out.push(format!(
            "incidence_dropout: at 70-90 deg the real recording loses {:.1} % more of the rays beyond the sim than at other incidences (at least {:.0} % is needed)",
            100.0 * c,
            100.0 * MIN_GRAZING_CONTRAST
        ));
    }

    // What moves returns: range-residual candidates.
    let residual_fits: Vec<ResidualFit> = residual::families()
        .iter()
        .filter_map(|family| {
            family.fit(
                &family.observations(sim),
                &family.observations(&train),
                &family.observations(&test),
                &options.residual,
            )
        })
        .collect();

    // What: drop candidates by forward selection.
    let px_sim = Pixels::collect(sim, reach_m);
    let px_train = Pixels::collect(&train, reach_m);
    let px_test = Pixels::collect(&test, reach_m);
    let baseline = Baseline::from_sim(&px_sim, reach_m);
    let boxed = drop::families();
    let motion_coverage = motion_coverage(&residual_fits, &baseline, &px_train);
    let families: Vec<&dyn DropFamily> = boxed
        .iter()
        .map(|b| b.as_ref())
        .filter(|f| unlabelled.is_empty() || f.id() != "material_dropout")
        .filter(|f| incidence_testable || f.id() != "incidence_dropout")
        .chain(motion_coverage.as_ref().map(|f| f as &dyn DropFamily))
        .collect();
    let selection = fit::select(
        &families,
        &baseline,
        &px_train,
        &px_test,
        options.max_effects,
    )?;

    let test_pixels = px_test.len().max(1) as f64;
    let mut fitted_physics = sim_physics.clone();
    let (mut effects, motion_coverage_part) =
        drop_effects(&selection, &comparison, &mut fitted_physics);
    adjust_uniform(&mut fitted_physics, selection.keep_scale);
    let residual = residual_effects(
        &residual_fits,
        motion_coverage_part,
        test_pixels,
        &mut fitted_physics,
    );
    effects.extend(residual.effects);
    let established: Vec<&str> = families
        .iter()
        .filter(|f| f.established())
        .map(|f| f.id())
        .collect();
    rank(&mut effects, &established);
    let candidates = candidates(&selection, &residual_fits);
    let mismatch = comparison
        .significant()
        .take(12)
        .map(|t| MismatchReport {
            feature: t.feature.name().into(),
            location: t.description.clone(),
            rate_sim: t.rate_sim,
            rate_real: t.rate_real,
            q_value: t.q_value,
        })
        .collect();

    let fit = FitMetric {
        metric: "nll_per_pixel (held-out real drop masks + range-residual statistics)".into(),
        before: selection.before_nll + residual.before_nats / test_pixels,
        after: selection.after_nll + residual.after_nats / test_pixels,
    };
    let drop_rate =
        |s: &[ScanFeatures]| s.iter().map(|f| f.drop_rate()).sum::<f64>() / s.len().max(1) as f64;
    let inputs = InputsReport {
        sim_scans: sim.len(),
        real_scans: real.len(),
        real_train_scans: train.len(),
        real_test_scans: test.len(),
        rows: r0.height,
        columns: r0.width,
        drop_rate_sim: drop_rate(sim),
        drop_rate_real: drop_rate(real),
        reach_m,
        completion: completion.into(),
        completion_model: None,
        completion_fallback_scans: 0,
        left_out,
    };

    let keep_after = fit::keep_under(&families, &selection, &baseline, &px_test);
    // "Before" for the maps: the sim with the fitted keep scale but no effect, so
    // the maps show where the effects act rather than the overall rate.
    let keep_before: Vec<f64> = baseline
        .keep_of(&px_test)
        .iter()
        .map(|k| (k * selection.keep_scale).min(1.0))
        .collect();
    let curves = curves(&px_sim, &px_test, &keep_after);
    let maps = maps(
        &px_sim,
        &px_test,
        &keep_before,
        &keep_after,
        &test[0],
        &families,
        &selection,
        &baseline,
        reach_m,
        &residual_fits,
    );
    Ok(Diagnosis {
        report: Report {
            effects,
            fit,
            keep_scale: selection.keep_scale,
            candidates,
            mismatch,
            inputs,
            fitted_physics,
            check: check_curves(&curves),
        },
        curves,
        maps,
    })
}

/// The first real scan, once both sides are usable: scans on both, two real ones at least
/// (one to fit on, one to test on), and the same grid.
fn check_inputs<'a>(
    sim: &[ScanFeatures],
    real: &'a [ScanFeatures],
) -> Result<&'a ScanFeatures, DiagnoseError> {
    let (Some(s0), Some(r0)) = (sim.first(), real.first()) else {
        return Err(if sim.is_empty() {
            DiagnoseError::NoSimScans
        } else {
            DiagnoseError::TooFewRealScans(0)
        });
    };
    if real.len() < 2 {
        return Err(DiagnoseError::TooFewRealScans(real.len()));
    }
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

/// The reports of the selected drop effects, their physics added to `physics`. The drop
/// side of motion distortion is returned apart (gain, location): it joins the motion effect
/// the seam's range steps found.
fn drop_effects(
    selection: &DropSelection,
    comparison: &Comparison,
    physics: &mut Map<String, Value>,
) -> (Vec<EffectReport>, Option<(f64, String)>) {
    let mut effects = Vec::new();
    let mut motion_part = None;
    for s in &selection.selected {
        if s.id == MOTION {
            motion_part = Some((s.gain(), s.fit.location.clone()));
            continue;
        }
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
    (effects, motion_part)
}

/// The range-residual effects that were significant, and the held-out NLL in nats summed
/// over observations before and after them.
struct ResidualEffects {
    effects: Vec<EffectReport>,
    before_nats: f64,
    after_nats: f64,
}

/// The reports of the significant range-residual effects, their physics added to
/// `physics`; `motion_part` (the drop side of motion) joins the motion effect.
fn residual_effects(
    fits: &[ResidualFit],
    mut motion_part: Option<(f64, String)>,
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
        let mut location = r.location.clone();
        let mut gain = r.gain() * n / test_pixels;
        if let Some((coverage_gain, coverage_location)) =
            motion_part.take().filter(|_| r.id == MOTION)
        {
            location.push_str(&format!("; {coverage_location}"));
            gain += coverage_gain;
        }
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
fn candidates(selection: &DropSelection, residual_fits: &[ResidualFit]) -> Vec<CandidateReport> {
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

const MOTION: &str = "motion_distortion";

/// The drop side of motion distortion, where the seam step found motion beyond the
/// sim's: the sweep direction, where rows come from and the motion per sweep that
/// fit the training scans best. The seam's step sets the scale; the mask decides
/// within it, because the step mixes moved and unmoved surfaces and its size trades
/// off against their share.
fn motion_coverage(
    residual_fits: &[ResidualFit],
    baseline: &Baseline,
    train: &Pixels,
) -> Option<drop::MotionCoverageFamily> {
    let motion = residual_fits
        .iter()
        .find(|r| r.id == MOTION && r.significant())?;
    let shift = |key: &str| motion.params.get(key).and_then(Value::as_f64);
    let extra = shift("seam_shift_m")? - shift("sim_seam_shift_m").unwrap_or(0.0);
    if extra <= 0.05 {
        return None;
    }
    let base = baseline.keep_of(train);
    let mut candidates = Vec::new();
    for counter_clockwise in [false, true] {
        for rows_from_elevation in [false, true] {
            for scale in MOTION_SCALES {
                candidates.push(drop::MotionCoverageFamily::new(
                    (extra * scale) as f32,
                    counter_clockwise,
                    rows_from_elevation,
                ));
            }
        }
    }
    candidates
        .into_par_iter()
        .filter_map(|family| {
            let table = fit::QTable::build(&family, train, &base);
            let nll = table.nll(&family.fit(&table, train)?.drop_prob);
            Some((nll, family))
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, family)| family)
}

/// Motion per sweep the drop mask may pick, as multiples of the seam's step.
const MOTION_SCALES: [f64; 9] = [0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0];

/// Whether a recording carries semantic labels: at least 5 % of its returns
/// have a class.
fn labelled(scans: &[ScanFeatures]) -> bool {
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

/// Folds the fitted keep scale `c` into the physics' uniform dropout:
/// keep `c (1 - u)` = `1 - u'`.
fn adjust_uniform(physics: &mut Map<String, Value>, c: f64) {
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

/// Binned drop rates of sim, real (held-out) and the fitted model.
fn curves(sim: &Pixels, test: &Pixels, keep_after: &[f64]) -> Vec<Curve> {
    type Binner = fn(&Pixels, usize) -> Option<usize>;
    let specs: [(&'static str, &'static str, usize, f64, Binner); 5] = [
        ("range", "m", 32, 2.5, |p, i| {
            let r = p.range_m[i];
            r.is_finite().then(|| ((r / 2.5) as usize).min(31))
        }),
        ("incidence", "deg", 18, 5.0, |p, i| {
            let c = p.cos_incidence[i];
            c.is_finite()
                .then(|| ((c.clamp(0.0, 1.0).acos().to_degrees() / 5.0) as usize).min(17))
        }),
        ("row", "", 0, 1.0, |p, i| Some(p.row[i] as usize)),
        ("edge_distance", "px", 9, 1.0, |p, i| {
            Some(usize::from(p.edge_px.get(i).copied().unwrap_or(u8::MAX)).min(8))
        }),
        ("azimuth", "deg", 36, 10.0, |p, i| {
            let a = p
                .column_azimuth_rad
                .get(p.column[i] as usize)
                .copied()
                .unwrap_or(0.0)
                .to_degrees();
            Some((((a + 180.0) / 10.0) as usize).min(35))
        }),
    ];
    specs
        .iter()
        .map(|&(feature, unit, n, step, bin)| {
            let n = if n == 0 { test.height.max(1) } else { n };
            let mut acc = vec![[0.0f64; 5]; n]; // sim n, sim drop, real n, real drop, fitted drop
            for i in 0..sim.len() {
                if let Some(b) = bin(sim, i).filter(|&b| b < n) {
                    acc[b][0] += 1.0;
                    acc[b][1] += f64::from(u8::from(!sim.kept[i]));
                }
            }
            for (i, keep) in keep_after.iter().enumerate().take(test.len()) {
                if let Some(b) = bin(test, i).filter(|&b| b < n) {
                    acc[b][2] += 1.0;
                    acc[b][3] += f64::from(u8::from(!test.kept[i]));
                    acc[b][4] += 1.0 - keep;
                }
            }
            let x0 = if feature == "azimuth" { -180.0 } else { 0.0 };
            let centre = |b: usize| {
                if feature == "row" || feature == "edge_distance" {
                    b as f64
                } else {
                    x0 + (b as f64 + 0.5) * step
                }
            };
            let rate = |d: f64, n: f64| if n >= 20.0 { d / n } else { f64::NAN };
            Curve {
                feature,
                unit,
                x: (0..n).map(centre).collect(),
                sim: acc.iter().map(|a| rate(a[1], a[0])).collect(),
                real: acc.iter().map(|a| rate(a[3], a[2])).collect(),
                fitted: acc.iter().map(|a| rate(a[4], a[2])).collect(),
                real_pixels: acc.iter().map(|a| a[2]).collect(),
            }
        })
        .collect()
}

#[allow(clippy::too_many_arguments)]
fn maps(
    sim: &Pixels,
    test: &Pixels,
    keep_before: &[f64],
    keep_after: &[f64],
    example: &ScanFeatures,
    families: &[&dyn DropFamily],
    selection: &DropSelection,
    baseline: &Baseline,
    reach_m: f32,
    residual: &[ResidualFit],
) -> Maps {
    let (h, w) = (test.height, test.width);
    let grid = |px: &Pixels, value: &dyn Fn(usize) -> f64| {
        let mut sum = vec![0.0f64; h * w];
        let mut n = vec![0.0f64; h * w];
        for i in 0..px.len() {
            let k = px.row[i] as usize * w + px.column[i] as usize;
            if k < sum.len() {
                sum[k] += value(i);
                n[k] += 1.0;
            }
        }
        sum.iter()
            .zip(&n)
            .map(|(s, n)| if *n > 0.0 { (s / n) as f32 } else { f32::NAN })
            .collect::<Vec<f32>>()
    };
    let real_drop = grid(test, &|i| f64::from(u8::from(!test.kept[i])));
    let sim_drop = grid(sim, &|i| f64::from(u8::from(!sim.kept[i])));
    let fitted_extra_drop = grid(test, &|i| (keep_before[i] - keep_after[i]).max(0.0));
    // The example scan: every pixel (not only those within reach).
    let px = Pixels::collect(std::slice::from_ref(example), f32::INFINITY);
    let after = fit::keep_under(families, selection, baseline, &px);
    let before: Vec<f64> = baseline
        .keep_of(&px)
        .iter()
        .map(|k| (k * selection.keep_scale).min(1.0))
        .collect();
    let mut highlight = vec![0.0f32; h * w];
    for i in 0..px.len() {
        let k = px.row[i] as usize * w + px.column[i] as usize;
        if k < highlight.len() && px.range_m[i] <= reach_m {
            highlight[k] = (before[i] - after[i]).max(0.0) as f32;
        }
    }
    if residual
        .iter()
        .any(|r| r.id == "motion_distortion" && r.significant())
    {
        for row in 0..h {
            for j in [w / 2 - 1, w / 2] {
                highlight[row * w + j] = 1.0;
            }
        }
    }
    Maps {
        height: h,
        width: w,
        real_drop,
        sim_drop,
        fitted_extra_drop,
        example_range_m: (0..example.len())
            .map(|k| {
                if example.kept[k] {
                    example.range_m[k]
                } else {
                    0.0
                }
            })
            .collect(),
        example_highlight: highlight,
    }
}

/// Orders the named effects: those that evidence of their own `established` (motion: the
/// seam's range step) first, since the drops they cause that their coverage model misses
/// show up as other effects, sometimes with a larger gain; then by held-out gain.
fn rank(effects: &mut [EffectReport], established: &[&str]) {
    let first = |e: &EffectReport| established.contains(&e.id.as_str());
    effects.sort_by(|a, b| {
        first(b)
            .cmp(&first(a))
            .then(b.gain_nats_per_pixel.total_cmp(&a.gain_nats_per_pixel))
    });
}

/// Smallest grazing contrast ([`grazing_contrast`]) for which `incidence_dropout` is a
/// candidate.
const MIN_GRAZING_CONTRAST: f64 = 0.05;

/// How much more of the rays the real recording loses beyond the sim at grazing
/// incidence (the largest real-minus-sim drop rate of the bins from 70 deg) than at
/// other incidences (the median of the bins below 70 deg); None without bins on
/// both sides.
fn grazing_contrast(comparison: &Comparison, step_deg: f32) -> Option<f64> {
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

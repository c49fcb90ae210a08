//! Sim2Real diagnosis, end to end on projected scans: features of both
//! recordings, where the drop rates diverge (`stats`), which left-out
//! effects explain the divergence (`fit` with the drop candidates of
//! `drop`, and `residual` for effects that move returns), and
//! the numbers the report and its plots show. No I/O: the CLI reads the
//! recordings and writes the report (`crate::report`).
//!
//! One file per part: `inputs` (their check, and which candidates they can test),
//! `effects` (the named effects, candidates and fitted physics), `plots` (curves
//! and maps) and `check` (the posterior-predictive check).

use serde::Serialize;
use serde_json::{Map, Value};

use super::drop;
use super::features::ScanFeatures;
use super::fit::{self, Baseline, DropFamily, FitError, Pixels};
use super::residual::{self, ResidualContext, ResidualFit};
use super::stats::{BinOptions, DropCounts, Feature, TestOptions, compare};

mod check;
mod effects;
mod inputs;
mod plots;
mod scene;

pub use check::{CHECK_MIN_PIXELS, CLOSE, FeatureCheck, MisfitBin, check_curves};
pub use plots::{Curve, Maps};
pub use scene::SceneContrast;

use effects::{adjust_uniform, candidates, drop_effects, rank, residual_effects};
use inputs::{MIN_GRAZING_CONTRAST, check_inputs, grazing_contrast, labelled};
use plots::{curves, maps};

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
                sweep: None,
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
    /// How far apart the two scenes are; where they differ, the effects' confidence is
    /// halved (a scene difference can look like a missing effect).
    pub scene: SceneContrast,
    /// Sectors of scans without any return in any row: gaps in the recording (lost
    /// packets, a partial revolution), left out of every rate and fit.
    pub gaps: Vec<super::gaps::Gap>,
    /// What the held-out check holds out: `scans` (the odd real scans), or `pixels` for a
    /// recording of one scan (alternate cells of 2 beams by 1/64 of a revolution).
    pub held_out: &'static str,
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
    #[error("the real recording has no scans")]
    NoRealScans,
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

const MOTION: &str = "motion_distortion";

/// The sweep most of `scans` share, where their clouds' firing order says (the seam's
/// azimuth, radians, and whether it turns counter-clockwise).
fn common_sweep(scans: &[ScanFeatures]) -> Option<(f32, bool)> {
    let sweeps: Vec<(f32, bool)> = (scans.iter())
        .filter_map(|f| {
            let seam = f.seam.as_ref()?;
            Some((seam.azimuth_rad(f.width), seam.counter_clockwise()))
        })
        .collect();
    let near = |a: &(f32, bool), b: &(f32, bool)| {
        a.1 == b.1 && crate::lidar::profile::wrap_pi(a.0 - b.0).abs() < 0.05
    };
    let (best, count) = (sweeps.iter())
        .map(|a| (*a, sweeps.iter().filter(|b| near(a, b)).count()))
        .max_by_key(|x| x.1)?;
    (2 * count > scans.len()).then_some(best)
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
    // Sectors without a return in any row are gaps in the recording, not physics.
    let (mut sim_marked, mut real_marked) = (sim.to_vec(), real.to_vec());
    let mut gaps = super::gaps::mark(&mut sim_marked, "sim");
    gaps.extend(super::gaps::mark(&mut real_marked, "real"));
    let (sim, real) = (sim_marked.as_slice(), real_marked.as_slice());
    // Even scans fit, odd scans check; a single scan fits on half its pixels and is checked
    // on the others (a weaker check: they share the scan's scene).
    let (train, test): (Vec<ScanFeatures>, Vec<ScanFeatures>) = if real.len() >= 2 {
        (
            real.iter().step_by(2).cloned().collect(),
            real.iter().skip(1).step_by(2).cloned().collect(),
        )
    } else {
        let (a, b) = super::gaps::split_pixels(&real[0]);
        (vec![a], vec![b])
    };
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
    let context = ResidualContext {
        sweep: options.residual.sweep.or_else(|| common_sweep(real)),
        ..options.residual
    };
    let residual_fits: Vec<ResidualFit> = residual::families()
        .iter()
        .filter_map(|family| {
            family.fit(
                &family.observations(sim),
                &family.observations(&train),
                &family.observations(&test),
                &context,
            )
        })
        .collect();

    // What: drop candidates by forward selection.
    let px_sim = Pixels::collect(sim, reach_m);
    let px_train = Pixels::collect(&train, reach_m);
    let px_test = Pixels::collect(&test, reach_m);
    let baseline = Baseline::from_sim(&px_sim, reach_m);
    let boxed = drop::families();
    let families: Vec<&dyn DropFamily> = boxed
        .iter()
        .map(|b| b.as_ref())
        .filter(|f| unlabelled.is_empty() || f.id() != "material_dropout")
        .filter(|f| incidence_testable || f.id() != "incidence_dropout")
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
    let mut effects = drop_effects(&selection, &comparison, &mut fitted_physics);
    adjust_uniform(&mut fitted_physics, selection.keep_scale);
    let residual = residual_effects(&residual_fits, test_pixels, &mut fitted_physics);
    effects.extend(residual.effects);
    rank(&mut effects, &[MOTION]);
    let scene = SceneContrast::measure(sim, real);
    if scene.differs {
        for e in &mut effects {
            e.confidence *= 0.5;
        }
    }
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
        scene,
        gaps,
        held_out: if real.len() >= 2 { "scans" } else { "pixels" },
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

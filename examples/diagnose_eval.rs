//! How well `diagnose` names left-out physics on sensors and scenes it was not
//! tuned on: randomised concealed sim/real pairs from the independent generator
//! of the tests (`tests/common/testgen/`: its own scenes and ray caster,
//! 16 / 32 / 64 / 128 beams, organized or not, ring field or not), every pair
//! diagnosed with the neighbour completion and judged against the truth.
//!
//! ```text
//! cargo run --release --example diagnose_eval [-- --seed 7 --only 0,5,9 --gains]
//! cargo run --release --example diagnose_eval -- --seed 437..459:2   # twelve plan seeds at once
//! ```
//! `--seed` takes one plan seed, a list (`7,9,11`) or a range with a step (`437..459:2`, both
//! ends included); `--only` picks pairs by their index within each seed's plan.
//! `--gains` shows each named effect's held-out gain (nats per pixel, x1000) beside it, and
//! each true effect left unnamed with the gain and penalty it had as a candidate.
//! Prints one row per pair, the summary, and the summary per sensor family (beams,
//! organized or not) as Markdown tables, so a gap shows where it is.

#[path = "../tests/common/testgen/mod.rs"]
mod testgen;

use rangegan_mcap::diagnose::Diagnosis;
use rayon::prelude::*;

struct Outcome {
    line: String,
    /// Sensor family: beams, organized or not.
    family: String,
    first_ok: bool,
    all_named: bool,
    null_clean: Option<bool>,
    fit_better: bool,
    single: bool,
    /// Share of the real side's rays the left-out effects dropped, where they drop rays.
    share: Option<f64>,
    /// Every left-out effect that can be seen (it moves returns, or drops at least
    /// [`VISIBLE_SHARE`] of the rays alone) is among the named.
    visible_named: bool,
    /// Effects named that are not in the pair (null pairs' are counted by `null_clean`).
    extras: usize,
    /// Single motion pairs: whether the motion moved enough seam steps to be seen.
    motion_visible: Option<bool>,
}

/// Left-out effects that dropped less than this share of the real rays are reported
/// apart: what no method can see is not evidence about the method.
const VISIBLE_SHARE: f64 = 0.005;

/// Seam steps a hidden motion has to move (10 cm or more, over the pair's 16 real scans) to
/// count as visible: one a scan. Motion moves only surfaces facing it, and a seam over open
/// road has none.
const VISIBLE_SEAM_STEPS: usize = 16;

/// Whether a left-out effect can be seen at all: it drops at least [`VISIBLE_SHARE`] of the
/// rays alone, moves returns other than by motion, or (motion) moves at least
/// [`VISIBLE_SEAM_STEPS`] seam steps.
fn visible(p: &testgen::Pair, effect: &str, share: Option<f64>) -> bool {
    match (effect, share) {
        ("motion_distortion", _) => p.motion_seam_steps.unwrap_or(0) >= VISIBLE_SEAM_STEPS,
        (_, Some(s)) => s >= VISIBLE_SHARE,
        (_, None) => true,
    }
}

fn judge(p: &testgen::Pair, d: &Diagnosis, seconds: f64, gains: bool) -> Outcome {
    let named: Vec<&str> = d.report.effects.iter().map(|e| e.id.as_str()).collect();
    let truth: Vec<&str> = p.truth.iter().map(String::as_str).collect();
    let null = truth.is_empty();
    let first_ok = if null {
        named.is_empty()
    } else {
        named.first().is_some_and(|f| truth.contains(f))
    };
    let all_named = truth.iter().all(|t| named.contains(t));
    let visible_named = truth
        .iter()
        .zip(&p.effect_shares)
        .all(|(t, share)| !visible(p, t, *share) || named.contains(t));
    let fit = &d.report.fit;
    let fit_better = if null {
        fit.after <= fit.before + 1e-9
    } else {
        fit.after < fit.before
    };
    let ok = first_ok && all_named && fit_better && (!null || named.is_empty());
    let line = format!(
        "| {} | {} | {} | {} | {} | {:.4} → {:.4} | {:.1} | {} |",
        p.seed,
        p.kind.name(),
        p.sensor.describe(),
        if null {
            "(none)".into()
        } else {
            truth
                .iter()
                .zip(&p.effect_shares)
                .map(|(t, share)| match (share, p.motion_seam_steps) {
                    (Some(s), _) => format!("{t} ({:.1} % of rays)", 100.0 * s),
                    (None, Some(steps)) if *t == "motion_distortion" => {
                        format!("{t} ({steps} seam steps moved)")
                    }
                    _ => t.to_string(),
                })
                .collect::<Vec<_>>()
                .join(", ")
        },
        named_column(d, &truth, gains),
        fit.before,
        fit.after,
        seconds,
        if ok { "ok" } else { "**miss**" }
    );
    Outcome {
        line,
        family: format!(
            "{} beams, {}",
            p.sensor.profile.beams(),
            if p.sensor.organized {
                "organized"
            } else {
                "unorganized"
            }
        ),
        first_ok,
        all_named,
        null_clean: null.then_some(named.is_empty()),
        fit_better,
        single: truth.len() == 1,
        motion_visible: (truth == ["motion_distortion"]).then(|| visible(p, truth[0], None)),
        share: p.effect_share,
        visible_named,
        extras: if null {
            0
        } else {
            named.iter().filter(|n| !truth.contains(n)).count()
        },
    }
}

/// The named effects; with `gains`, each one's held-out gain, and each true effect left
/// unnamed with the gain and penalty it had as a candidate (nats per pixel, x1000).
fn named_column(d: &Diagnosis, truth: &[&str], gains: bool) -> String {
    let mut parts: Vec<String> = d
        .report
        .effects
        .iter()
        .map(|e| {
            if gains {
                format!("{} ({:.2})", e.id, 1000.0 * e.gain_nats_per_pixel)
            } else {
                e.id.clone()
            }
        })
        .collect();
    if parts.is_empty() {
        parts.push("(none)".into());
    }
    if gains {
        for c in (d.report.candidates.iter())
            .filter(|c| truth.contains(&c.id.as_str()) && !c.significant)
        {
            parts.push(format!(
                "unnamed {} ({:.2} / {:.2})",
                c.id,
                1000.0 * c.gain,
                1000.0 * c.penalty
            ));
        }
    }
    parts.join(", ")
}

fn main() {
    let mut seeds = vec![7u64];
    let mut only: Option<Vec<usize>> = None;
    let mut gains = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seed" => {
                seeds = args
                    .next()
                    .as_deref()
                    .and_then(parse_seeds)
                    .expect("--seed N, N,M,... or A..B:STEP")
            }
            "--only" => {
                only = Some(
                    args.next()
                        .expect("--only I,J")
                        .split(',')
                        .map(|s| s.parse().expect("index"))
                        .collect(),
                )
            }
            "--gains" => gains = true,
            other => panic!("unknown argument {other}"),
        }
    }
    let chosen: Vec<_> = (seeds.iter())
        .flat_map(|&seed| testgen::plan(seed).into_iter().enumerate())
        .filter(|(i, _)| only.as_ref().is_none_or(|o| o.contains(i)))
        .collect();
    let started = std::time::Instant::now();
    let outcomes: Vec<(usize, Outcome)> = chosen
        .par_iter()
        .map(|(i, (pair_seed, effects, beams))| {
            let t = std::time::Instant::now();
            let p = testgen::pair(*pair_seed, effects, *beams);
            let d = testgen::diagnose_pair(&p);
            let o = judge(&p, &d, t.elapsed().as_secs_f64(), gains);
            eprintln!("{i}: {}", o.line);
            if std::env::var_os("DIAGNOSE_EVAL_VERBOSE").is_some() {
                eprintln!(
                    "   truth {:?}\n   drop rates sim {:.3} real {:.3}\n   candidates {:?}",
                    p.truth_params,
                    p.drop_rate_sim,
                    p.drop_rate_real,
                    d.report
                        .candidates
                        .iter()
                        .map(|c| format!("{} {:.4}/{:.4}", c.id, c.gain, c.penalty))
                        .collect::<Vec<_>>()
                );
                for e in &d.report.effects {
                    eprintln!(
                        "   {} (gain {:.4}, confidence {:.2}): {}",
                        e.id, e.gain_nats_per_pixel, e.confidence, e.location
                    );
                }
            }
            (*i, o)
        })
        .collect();
    println!(
        "| seed | scene | sensor | left out | named (ranked) | held-out NLL per pixel | s | |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (_, o) in &outcomes {
        println!("{}", o.line);
    }
    let with_effect: Vec<&Outcome> = outcomes
        .iter()
        .map(|(_, o)| o)
        .filter(|o| o.null_clean.is_none())
        .collect();
    let count = |f: &dyn Fn(&Outcome) -> bool, v: &[&Outcome]| v.iter().filter(|o| f(o)).count();
    let singles: Vec<&Outcome> = with_effect.iter().copied().filter(|o| o.single).collect();
    let multi: Vec<&Outcome> = with_effect.iter().copied().filter(|o| !o.single).collect();
    let nulls: Vec<&Outcome> = outcomes
        .iter()
        .map(|(_, o)| o)
        .filter(|o| o.null_clean.is_some())
        .collect();
    println!();
    println!("| measure | result |");
    println!("|---|---|");
    println!(
        "| a true effect named first (pairs with effects) | {} / {} |",
        count(&|o| o.first_ok, &with_effect),
        with_effect.len()
    );
    println!(
        "| the true effect named first (single-effect pairs) | {} / {} |",
        count(&|o| o.first_ok, &singles),
        singles.len()
    );
    println!(
        "| every true effect among the named | {} / {} |",
        count(&|o| o.all_named, &with_effect),
        with_effect.len()
    );
    println!(
        "| every true effect among the named (multi-effect pairs) | {} / {} |",
        count(&|o| o.all_named, &multi),
        multi.len()
    );
    println!(
        "| every true effect that dropped >= {:.1} % of the rays alone, moved returns, or (motion) moved >= {VISIBLE_SEAM_STEPS} seam steps, among the named (multi-effect pairs) | {} / {} |",
        100.0 * VISIBLE_SHARE,
        count(&|o| o.visible_named, &multi),
        multi.len()
    );
    println!(
        "| null pairs with nothing named | {} / {} |",
        count(&|o| o.null_clean == Some(true), &nulls),
        nulls.len()
    );
    let extras: usize = with_effect.iter().map(|o| o.extras).sum();
    println!(
        "| effects named that are not in the pair (pairs with effects) | {extras} ({:.0} per 736 pairs) |",
        736.0 * extras as f64 / outcomes.len().max(1) as f64
    );
    println!(
        "| held-out fit better with the fitted effects | {} / {} |",
        count(&|o| o.fit_better, &with_effect),
        with_effect.len()
    );
    for (words, faint) in [(">=", false), ("<", true)] {
        let drops: Vec<&Outcome> = singles
            .iter()
            .copied()
            .filter(|o| o.share.is_some_and(|s| (s < VISIBLE_SHARE) == faint))
            .collect();
        println!(
            "| the true effect named first (single drop effects that dropped {words} {:.1} % of the rays) | {} / {} |",
            100.0 * VISIBLE_SHARE,
            count(&|o| o.first_ok, &drops),
            drops.len()
        );
    }
    for (words, seen) in [(">=", true), ("<", false)] {
        let motion: Vec<&Outcome> = singles
            .iter()
            .copied()
            .filter(|o| o.motion_visible == Some(seen))
            .collect();
        println!(
            "| motion distortion named first (single pairs where it moved {words} {VISIBLE_SEAM_STEPS} seam steps) | {} / {} |",
            count(&|o| o.first_ok, &motion),
            motion.len()
        );
    }
    print_families(&outcomes);
    println!(
        "\n{} pairs in {:.0} s wall ({} threads)",
        outcomes.len(),
        started.elapsed().as_secs_f64(),
        rayon::current_num_threads()
    );
}

/// Plan seeds from `N`, `N,M,...` or `A..B:STEP` (both ends included; the step 1 if left out).
fn parse_seeds(arg: &str) -> Option<Vec<u64>> {
    if let Some((from, rest)) = arg.split_once("..") {
        let (to, step) = rest.split_once(':').unwrap_or((rest, "1"));
        let (from, to, step): (u64, u64, usize) =
            (from.parse().ok()?, to.parse().ok()?, step.parse().ok()?);
        return (step > 0 && from <= to).then(|| (from..=to).step_by(step).collect());
    }
    arg.split(',').map(|s| s.parse().ok()).collect()
}

/// The summary per sensor family: pairs, a true effect named first, every true effect
/// named (pairs with effects), null pairs clean.
fn print_families(outcomes: &[(usize, Outcome)]) {
    let mut families: Vec<&str> = outcomes.iter().map(|(_, o)| o.family.as_str()).collect();
    families.sort_by_key(|f| {
        let beams: usize = f
            .split(' ')
            .next()
            .and_then(|b| b.parse().ok())
            .unwrap_or(0);
        (beams, f.to_string())
    });
    families.dedup();
    println!();
    println!(
        "| sensor family | pairs | true effect first | every true effect named | null pairs clean |"
    );
    println!("|---|---|---|---|---|");
    for family in families {
        let of: Vec<&Outcome> = outcomes
            .iter()
            .map(|(_, o)| o)
            .filter(|o| o.family == family)
            .collect();
        let effects: Vec<&&Outcome> = of.iter().filter(|o| o.null_clean.is_none()).collect();
        let nulls = of.len() - effects.len();
        println!(
            "| {family} | {} | {} / {} | {} / {} | {} / {nulls} |",
            of.len(),
            effects.iter().filter(|o| o.first_ok).count(),
            effects.len(),
            effects.iter().filter(|o| o.all_named).count(),
            effects.len(),
            of.iter().filter(|o| o.null_clean == Some(true)).count(),
        );
    }
}

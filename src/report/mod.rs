//! The diagnosis report on disk: `report.json` (the contract other programs read),
//! `fitted_physics.json` (for `render --physics`), PNG plots (drop-rate curves of
//! real vs sim vs sim + fitted; per-pixel drop maps; one real scan with the
//! located mismatch highlighted) and `report.html` tying them together. Every
//! file is written atomically. Knows nothing of MCAP or of how the fit works.

pub mod plot;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::diagnose::report::{CLOSE, Curve, Diagnosis, EffectReport, FeatureCheck, Report};
use crate::util::fs::write_atomic;
use plot::{FITTED, LineChart, REAL, SIM, Series, line_chart, viridis};

/// Where the inputs came from, for the HTML header.
#[derive(Debug, Clone, Default)]
pub struct Provenance {
    pub sim: String,
    pub real: String,
    pub topic_sim: String,
    pub topic_real: String,
    pub sensor: String,
}

/// One image of the report and its caption.
struct Figure {
    file: String,
    caption: String,
}

fn curve_figure(dir: &Path, curve: &Curve) -> anyhow::Result<Figure> {
    let file = format!("drop_vs_{}.png", curve.feature);
    let name = curve.feature.replace('_', " ");
    let x_label = if curve.unit.is_empty() {
        name.clone()
    } else {
        format!("{name} ({})", curve.unit)
    };
    let png = line_chart(&LineChart {
        title: &format!("Drop rate against {name}"),
        x_label: &x_label,
        y_label: "drop rate",
        x: &curve.x,
        series: &[
            Series {
                label: "real held-out scans",
                colour: REAL,
                y: &curve.real,
            },
            Series {
                label: "sim as given",
                colour: SIM,
                y: &curve.sim,
            },
            Series {
                label: "sim + fitted effects",
                colour: FITTED,
                y: &curve.fitted,
            },
        ],
    })
    .with_context(|| format!("cannot draw {}", dir.join(&file).display()))?;
    write_atomic(&dir.join(&file), &png)
        .with_context(|| format!("cannot write {}", dir.join(&file).display()))?;
    Ok(Figure {
        file,
        caption: format!(
            "Drop rate against {x_label}: \
             <span style='color:#d62728'>red: real (held-out scans)</span>, \
             <span style='color:#1f77b4'>blue: sim as given</span>, \
             <span style='color:#2ca02c'>green: sim + fitted effects</span>; gaps where a bin has too few pixels."
        ),
    })
}

/// Writes a map chart (`plot::map_chart`: title, azimuth and row axes, colour
/// bar where `colour_bar` is given) as `dir/file`.
fn map_file(
    dir: &Path,
    file: &str,
    title: &str,
    (h, w): (usize, usize),
    colour: &dyn Fn(usize) -> plot::Rgb,
    colour_bar: Option<(f32, &str)>,
) -> anyhow::Result<()> {
    let png = plot::map_chart(&plot::MapChart {
        title,
        height: h,
        width: w,
        colour,
        colour_bar,
    })
    .with_context(|| format!("cannot draw {}", dir.join(file).display()))?;
    write_atomic(&dir.join(file), &png)
        .with_context(|| format!("cannot write {}", dir.join(file).display()))
}

#[allow(clippy::too_many_arguments)]
fn map_figure(
    dir: &Path,
    file: &str,
    title: &str,
    h: usize,
    w: usize,
    values: &[f32],
    max: f32,
    caption: String,
) -> anyhow::Result<Figure> {
    let colour = |k: usize| {
        let v = values.get(k).copied().unwrap_or(f32::NAN);
        if v.is_finite() {
            viridis(v / max.max(1e-6))
        } else {
            [255, 255, 255]
        }
    };
    map_file(
        dir,
        file,
        title,
        (h, w),
        &colour,
        Some((max, "drop probability")),
    )?;
    Ok(Figure {
        file: file.into(),
        caption,
    })
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Writes the whole report into `dir` (created if missing); returns the files. The JSON, the
/// plots in the order the page shows them, then the page.
pub fn write(dir: &Path, d: &Diagnosis, provenance: &Provenance) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut files = Vec::new();
    let json = serde_json::to_vec_pretty(&d.report)?;
    write_atomic(&dir.join("report.json"), &json)
        .with_context(|| format!("cannot write {}/report.json", dir.display()))?;
    files.push(dir.join("report.json"));
    let physics = serde_json::to_vec_pretty(&d.report.fitted_physics)?;
    write_atomic(&dir.join("fitted_physics.json"), &physics)
        .with_context(|| format!("cannot write {}/fitted_physics.json", dir.display()))?;
    files.push(dir.join("fitted_physics.json"));

    let mut figures = Vec::new();
    for curve in &d.curves {
        figures.push(curve_figure(dir, curve)?);
    }
    let m = &d.maps;
    let (h, w) = (m.height, m.width);
    figures.push(map_figure(dir, "drop_map_real.png", "Real: drop frequency per pixel (held-out scans)", h, w, &m.real_drop, 1.0,
        "Real drop frequency per pixel over the held-out scans (rows top to bottom, azimuth +180 deg at the left to -180 deg at the right; dark 0, yellow 1; white = left out).".into())?);
    figures.push(map_figure(
        dir,
        "drop_map_sim.png",
        "Sim: drop frequency per pixel",
        h,
        w,
        &m.sim_drop,
        1.0,
        "Sim drop frequency per pixel (same scale).".into(),
    )?);
    let extra_max = m
        .fitted_extra_drop
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f32, f32::max)
        .max(0.05);
    figures.push(map_figure(dir, "fitted_extra_drop.png", "Where the fitted effects act: extra drop probability", h, w, &m.fitted_extra_drop, extra_max,
        format!("Where the fitted effects act: extra drop probability per pixel, mean over held-out scans (dark 0, yellow {extra_max:.2})."))?);
    // One held-out real scan: grey by range, black where dropped, red where the
    // fitted effects add drop probability (the located mismatch).
    let max_range = m.example_range_m.iter().copied().fold(1.0f32, f32::max);
    let example = |k: usize| {
        let r = m.example_range_m.get(k).copied().unwrap_or(0.0);
        let hl = m
            .example_highlight
            .get(k)
            .copied()
            .unwrap_or(0.0)
            .clamp(0.0, 1.0);
        let grey = if r > 0.0 {
            (255.0 * (1.0 - (r / max_range).sqrt() * 0.8)) as u8
        } else {
            0
        };
        if hl > 0.1 {
            let t = (hl * 2.0).min(1.0);
            let mix = |a: u8, b: u8| (f32::from(a) * (1.0 - t) + f32::from(b) * t) as u8;
            [mix(grey, 255), mix(grey, 0), mix(grey, 0)]
        } else {
            [grey, grey, grey]
        }
    };
    map_file(
        dir,
        "example_scan.png",
        "One held-out real scan: range (grey), dropped (black), located mismatch (red)",
        (h, w),
        &example,
        None,
    )?;
    figures.push(Figure {
        file: "example_scan.png".into(),
        caption: "One held-out real scan: grey by range (light near, dark far), black where dropped, red where the fitted effects located the mismatch (extra drop probability; the scan seam for motion distortion).".into(),
    });

    for f in &figures {
        files.push(dir.join(&f.file));
    }
    let html = html(&d.report, &figures, provenance);
    write_atomic(&dir.join("report.html"), html.as_bytes())
        .with_context(|| format!("cannot write {}/report.html", dir.display()))?;
    files.push(dir.join("report.html"));
    Ok(files)
}

const STYLE: &str = "body{font-family:sans-serif;max-width:1100px;margin:auto;padding:0 12px}\
    table{border-collapse:collapse;width:100%;table-layout:fixed}\
    td,th{border:1px solid #ccc;padding:3px 6px;vertical-align:top;overflow-wrap:anywhere}\
    img{max-width:100%;border:1px solid #ccc}\
    #summary{background:#f4f6f8;padding:4px 16px;border-radius:6px}\
    .plots{display:grid;grid-template-columns:repeat(auto-fill,minmax(460px,1fr));gap:8px}\
    figure{margin:0}figcaption{font-size:90%}details{margin:10px 0}summary{cursor:pointer}";

/// The page: the answer first (what differs, which physics is missing, how much the fit
/// improves, where it still misses), the plots, then the details folded away.
fn html(r: &Report, figures: &[Figure], provenance: &Provenance) -> String {
    let mut html = format!(
        "<!doctype html><html><head><meta charset='utf-8'>\
         <meta name='viewport' content='width=device-width'>\
         <title>rangegan-mcap diagnose</title><style>{STYLE}</style></head><body>\
         <h1>Sim2Real diagnosis</h1>"
    );
    html.push_str(&summary(r));
    let i = &r.inputs;
    let _ = write!(
        html,
        "<p>sim: <code>{}</code> ({}), real: <code>{}</code> ({}), sensor {}; {} sim scans, \
         {} real scans ({} fit, {} held out), {}x{} grid, completion: {}; pixels completed \
         beyond {:.0} m left out.</p>",
        escape(&provenance.sim),
        escape(&provenance.topic_sim),
        escape(&provenance.real),
        escape(&provenance.topic_real),
        escape(&provenance.sensor),
        i.sim_scans,
        i.real_scans,
        i.real_train_scans,
        i.real_test_scans,
        i.rows,
        i.columns,
        escape(&i.completion),
        i.reach_m
    );
    for why in &i.left_out {
        let _ = write!(html, "<p>Left out: {}.</p>", escape(why));
    }
    html.push_str("<h2>Plots</h2><div class='plots'>");
    for f in figures {
        let _ = write!(
            html,
            "<figure id='{}'><img src='{}' alt='{}'><figcaption>{}</figcaption></figure>",
            f.file.trim_end_matches(".png"),
            f.file,
            f.file,
            f.caption
        );
    }
    html.push_str("</div>");
    html.push_str(&details(r));
    html.push_str(
        "<p>Apply the fit to simulated data: <code>rangegan-mcap render --physics \
         fitted_physics.json SIM.mcap OUT.mcap</code>.</p></body></html>",
    );
    html
}

/// What an effect is, in words, and the plot that shows it best.
fn effect_words(id: &str) -> (&'static str, Option<&'static str>) {
    match id {
        "range_dropout" => ("rays lost with distance", Some("drop_vs_range")),
        "incidence_dropout" => ("rays lost at grazing incidence", Some("drop_vs_incidence")),
        "beam_dropout" => ("weak or dead beams", Some("drop_vs_row")),
        "self_occlusion" => ("the ego vehicle blocking rays", Some("fitted_extra_drop")),
        "material_dropout" => ("rays lost on dark or glass surfaces", None),
        "range_noise" => ("noise on the measured range", None),
        "mixed_pixels" => ("mixed returns at depth edges", None),
        "edge_dropout" => ("rays lost at depth edges", Some("drop_vs_edge_distance")),
        "motion_distortion" => ("the sensor moving during a sweep", Some("example_scan")),
        _ => ("a sensor effect", None),
    }
}

/// `text` cut to at most `max` characters, with an ellipsis where it was cut.
fn truncate(text: &str, max: usize) -> String {
    match text.char_indices().nth(max) {
        Some((cut, _)) => format!("{}…", &text[..cut]),
        None => text.to_string(),
    }
}

/// The first clause of an effect's location (up to a `;` outside parentheses), at most
/// `max` characters.
fn first_clause(location: &str, max: usize) -> String {
    let mut depth = 0i32;
    let end = location
        .char_indices()
        .find(|&(_, c)| {
            depth += match c {
                '(' | '[' => 1,
                ')' | ']' => -1,
                _ => 0,
            };
            c == ';' && depth == 0
        })
        .map_or(location.len(), |(i, _)| i);
    truncate(location[..end].trim(), max)
}

fn effect_line(e: &EffectReport) -> String {
    let (words, plot) = effect_words(&e.id);
    let link = plot.map_or(String::new(), |p| format!(" <a href='#{p}'>plot</a>"));
    format!(
        "<li><b>{words}</b> (<code>{}</code>, confidence {:.2}): {}.{link}</li>",
        e.id,
        e.confidence,
        escape(&first_clause(&e.location, 160))
    )
}

/// One sentence on where the fitted model still misses the held-out real drop rate.
fn check_sentence(checks: &[FeatureCheck]) -> String {
    let (bins, close) = checks
        .iter()
        .fold((0, 0), |(b, c), f| (b + f.bins, c + f.close));
    let features: Vec<String> = checks.iter().map(|c| c.feature.replace('_', " ")).collect();
    let mut s = format!(
        "Along {}, the sim with the fitted effects is within {CLOSE} of the real drop rate in \
         {close} of {bins} bins",
        features.join(", ")
    );
    let worse: Vec<String> = checks
        .iter()
        .flat_map(|c| {
            c.worse_than_sim.iter().take(2).map(move |m| {
                format!(
                    "{} {:.1}{} (real {:.2}, sim {:.2}, fitted {:.2})",
                    c.feature.replace('_', " "),
                    m.at,
                    c.unit,
                    m.real,
                    m.sim,
                    m.fitted
                )
            })
        })
        .collect();
    let n_worse: usize = checks.iter().map(|c| c.worse_than_sim.len()).sum();
    if n_worse == 0 {
        s.push_str(", and nowhere farther from it than the raw simulator.");
    } else {
        let _ = write!(
            s,
            "; it is farther from it than the raw simulator in {n_worse} bins: {}.",
            worse.join("; ")
        );
    }
    s
}

/// The first screen: what differs, the missing physics, the fit and the check.
fn summary(r: &Report) -> String {
    let i = &r.inputs;
    let mut s = format!(
        "<section id='summary'><p><b>What differs:</b> the real scans drop {:.1} % of rays, the \
         simulated ones {:.1} %",
        100.0 * i.drop_rate_real,
        100.0 * i.drop_rate_sim
    );
    if let Some(t) = r.mismatch.first() {
        let _ = write!(
            s,
            "; the largest divergence: {} (real {:.1} % vs sim {:.1} % dropped)",
            escape(&t.location),
            100.0 * t.rate_real,
            100.0 * t.rate_sim
        );
    }
    s.push_str(".</p>");
    if i.scene.differs {
        let _ = write!(
            s,
            "<p class='warn'><b>Different scenes:</b> {}.</p>",
            escape(&i.scene.sentence())
        );
    }
    if i.held_out == "pixels" {
        let _ = write!(
            s,
            "<p class='warn'><b>One real scan:</b> {}.</p>",
            escape(crate::diagnose::gaps::ONE_SCAN_CAVEAT)
        );
    }
    if let Some(gaps) = crate::diagnose::gaps::summary(&i.gaps) {
        let _ = write!(
            s,
            "<p class='warn'><b>Gaps in the recording:</b> {}.</p>",
            escape(&gaps)
        );
    }
    s.push_str("<p><b>Missing physics:</b></p>");
    if r.effects.is_empty() {
        s.push_str("<p>none found: no candidate beats the null on held-out scans.</p>");
    } else {
        s.push_str("<ul>");
        for e in &r.effects {
            s.push_str(&effect_line(e));
        }
        s.push_str("</ul>");
    }
    let _ = write!(
        s,
        "<p><b>Fit on held-out real scans:</b> {:.3} → {:.3} nats per pixel (lower is better).</p>\
         <p><b>Check:</b> {}</p></section>",
        r.fit.before,
        r.fit.after,
        escape(&check_sentence(&r.check))
    );
    s
}

/// The effects' parameters and fits, the candidates and the divergences, folded.
fn details(r: &Report) -> String {
    let mut s = String::from(
        "<details><summary>Effects in detail: where, parameters, fit</summary>\
         <table><tr><th style='width:14%'>effect</th><th style='width:40%'>where</th>\
         <th style='width:30%'>parameters</th><th>fit before → after</th></tr>",
    );
    for e in &r.effects {
        let params = serde_json::to_string(&e.params).unwrap_or_default();
        let _ = write!(
            s,
            "<tr><td><b>{}</b><br>confidence {:.2}</td><td>{}</td><td><code>{}</code></td>\
             <td>{}: {:.5} → {:.5}</td></tr>",
            e.id,
            e.confidence,
            escape(&e.location),
            escape(&truncate(&params, 400)),
            escape(&e.fit.metric),
            e.fit.before,
            e.fit.after
        );
    }
    s.push_str(
        "</table></details><details><summary>Candidates: held-out gain against penalty</summary>\
         <table><tr><th>id</th><th>gain</th><th>penalty</th><th>significant</th></tr>",
    );
    for c in &r.candidates {
        let _ = write!(
            s,
            "<tr><td>{}</td><td>{:.5}</td><td>{:.5}</td><td>{}</td></tr>",
            c.id, c.gain, c.penalty, c.significant
        );
    }
    s.push_str(
        "</table></details><details><summary>Largest significant drop-rate divergences \
         (Benjamini-Hochberg)</summary><table><tr><th>feature</th><th>where</th><th>sim</th>\
         <th>real</th><th>q</th></tr>",
    );
    for t in &r.mismatch {
        let _ = write!(
            s,
            "<tr><td>{}</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.1e}</td></tr>",
            t.feature,
            escape(&t.location),
            t.rate_sim,
            t.rate_real,
            t.q_value
        );
    }
    s.push_str("</table></details>");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_clause_ends_at_a_semicolon_outside_parentheses() {
        assert_eq!(
            first_clause("angles above 86 deg (grazing; real 31 %); more", 100),
            "angles above 86 deg (grazing; real 31 %)"
        );
        assert_eq!(first_clause("rows 52-63; sides", 100), "rows 52-63");
        assert_eq!(first_clause("abcdef", 3), "abc…");
    }
}

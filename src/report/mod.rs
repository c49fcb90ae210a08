//! The diagnosis report on disk: `report.json` (the contract other programs read),
//! `fitted_physics.json` (for `render --physics`), PNG plots (drop-rate curves of
//! real vs sim vs sim + fitted; per-pixel drop maps; one real scan with the
//! located mismatch highlighted) and `report.html` tying them together. Every
//! file is written atomically. Knows nothing of MCAP or of how the fit works.

pub mod plot;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::diagnose::report::{Curve, Diagnosis};
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
    let x_label = if curve.unit.is_empty() {
        curve.feature.to_string()
    } else {
        format!("{} ({})", curve.feature, curve.unit)
    };
    let png = line_chart(&LineChart {
        title: &format!("Drop rate against {}", curve.feature),
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

/// Writes the whole report into `dir` (created if missing); returns the files. The plots
/// first, then the HTML top to bottom in the order a reader sees it (summary, effects,
/// candidates, divergences, plots): the function follows the page rather than being cut into
/// pieces that each write a part of it.
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

    let r = &d.report;
    let mut html = String::new();
    let _ = write!(
        html,
        "<!doctype html><html><head><meta charset='utf-8'><title>rangegan-mcap diagnose</title>\
         <style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}td,th{{border:1px solid #ccc;padding:3px 6px}}table{{border-collapse:collapse}}img{{max-width:100%;border:1px solid #ccc}}</style></head><body>\
         <h1>Sim2Real diagnosis</h1><p>sim: <code>{}</code> ({}), real: <code>{}</code> ({}), sensor {}; {} sim scans, {} real scans ({} fit, {} held out), {}x{} grid, completion: {}. \
         Drop rate sim {:.1} %, real {:.1} %; pixels completed beyond {:.0} m left out.</p>",
        escape(&provenance.sim),
        escape(&provenance.topic_sim),
        escape(&provenance.real),
        escape(&provenance.topic_real),
        escape(&provenance.sensor),
        r.inputs.sim_scans,
        r.inputs.real_scans,
        r.inputs.real_train_scans,
        r.inputs.real_test_scans,
        r.inputs.rows,
        r.inputs.columns,
        escape(&r.inputs.completion),
        100.0 * r.inputs.drop_rate_sim,
        100.0 * r.inputs.drop_rate_real,
        r.inputs.reach_m
    );
    for why in &r.inputs.left_out {
        let _ = write!(html, "<p>Left out: {}.</p>", escape(why));
    }
    let _ = write!(
        html,
        "<h2>Fit on held-out real scans</h2><p>{}: before {:.5}, after {:.5} (lower is better).</p><h2>Effects found</h2>",
        escape(&r.fit.metric),
        r.fit.before,
        r.fit.after
    );
    if r.effects.is_empty() {
        html.push_str("<p>None: no candidate beats the null on held-out scans.</p>");
    } else {
        html.push_str("<table><tr><th>effect</th><th>confidence</th><th>where</th><th>parameters</th><th>fit before → after</th></tr>");
        for e in &r.effects {
            let params = serde_json::to_string(&e.params).unwrap_or_default();
            let params = if params.len() > 400 {
                format!(
                    "{}…",
                    &params[..params.char_indices().nth(400).map_or(params.len(), |c| c.0)]
                )
            } else {
                params
            };
            let _ = write!(
                html,
                "<tr><td><b>{}</b></td><td>{:.2}</td><td>{}</td><td><code>{}</code></td><td>{}: {:.5} → {:.5}</td></tr>",
                e.id,
                e.confidence,
                escape(&e.location),
                escape(&params),
                escape(&e.fit.metric),
                e.fit.before,
                e.fit.after
            );
        }
        html.push_str("</table>");
    }
    html.push_str("<h2>Candidates (held-out gain vs penalty)</h2><table><tr><th>id</th><th>gain</th><th>penalty</th><th>significant</th></tr>");
    for c in &r.candidates {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{:.5}</td><td>{:.5}</td><td>{}</td></tr>",
            c.id, c.gain, c.penalty, c.significant
        );
    }
    html.push_str("</table><h2>Largest significant drop-rate divergences (Benjamini-Hochberg)</h2><table><tr><th>feature</th><th>where</th><th>sim</th><th>real</th><th>q</th></tr>");
    for t in &r.mismatch {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.1e}</td></tr>",
            t.feature,
            escape(&t.location),
            t.rate_sim,
            t.rate_real,
            t.q_value
        );
    }
    html.push_str("</table><h2>Plots</h2>");
    for f in &figures {
        let _ = write!(
            html,
            "<figure><img src='{}' alt='{}'><figcaption>{}</figcaption></figure>",
            f.file, f.file, f.caption
        );
        files.push(dir.join(&f.file));
    }
    html.push_str("<p>Apply the fit to simulated data: <code>rangegan-mcap render --physics fitted_physics.json SIM.mcap OUT.mcap</code>.</p></body></html>");
    write_atomic(&dir.join("report.html"), html.as_bytes())
        .with_context(|| format!("cannot write {}/report.html", dir.display()))?;
    files.push(dir.join("report.html"));
    Ok(files)
}

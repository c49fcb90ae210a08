//! Training curves of GAN runs from their `log.jsonl`: discriminator and generator losses,
//! D(real) and D(fake), the finite-difference R1 estimate, the ADA probability and what D was
//! shown (the generated batches' drop share and spread of inverse depth beside the real
//! ones'), against real images seen. Shows whether D keeps a lead, and what the generator
//! moves when it takes it away.
//!
//! ```text
//! cargo run --release --example training_curves -- [--from IMAGES] OUT.png LABEL=RUN_DIR ...
//! ```
//! `--from` plots only the log lines from that many images on.

use std::path::{Path, PathBuf};

use plotters::prelude::*;

type Res<T> = Result<T, Box<dyn std::error::Error>>;
/// (run index, points, solid line?)
type Curve = (usize, Vec<(f64, f64)>, bool);

/// One logged quantity of one run (a JSON pointer into each log line): (images, value),
/// smoothed over `window` log lines.
fn series(lines: &[serde_json::Value], pointer: &str, window: usize) -> Vec<(f64, f64)> {
    let raw: Vec<(f64, f64)> = lines
        .iter()
        .filter_map(|l| Some((l["images"].as_f64()?, l.pointer(pointer)?.as_f64()?)))
        .collect();
    (0..raw.len())
        .map(|i| {
            let lo = i.saturating_sub(window - 1);
            let mean = raw[lo..=i].iter().map(|p| p.1).sum::<f64>() / (i - lo + 1) as f64;
            (raw[i].0, mean)
        })
        .collect()
}

fn read_log(run: &Path) -> Res<Vec<serde_json::Value>> {
    let text = std::fs::read_to_string(run.join("log.jsonl"))
        .map_err(|e| format!("{}: {e}", run.join("log.jsonl").display()))?;
    // a resumed run logs some steps twice: keep the last line per step
    let mut by_step = std::collections::BTreeMap::new();
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let v: serde_json::Value = serde_json::from_str(line)?;
        by_step.insert(v["step"].as_u64().unwrap_or(0), v);
    }
    Ok(by_step.into_values().collect())
}

fn main() -> Res<()> {
    let usage = "usage: training_curves [--from IMAGES] OUT.png LABEL=RUN_DIR ...";
    let mut args = std::env::args().skip(1).peekable();
    let from: f64 = match args.next_if_eq("--from") {
        Some(_) => args.next().ok_or(usage)?.parse()?,
        None => 0.0,
    };
    let out = PathBuf::from(args.next().ok_or(usage)?);
    let runs: Vec<(String, Vec<serde_json::Value>)> = args
        .map(|a| {
            let (label, dir) = a.split_once('=').unwrap_or((&a, &a));
            let mut lines = read_log(Path::new(dir))?;
            lines.retain(|l| l["images"].as_f64().is_some_and(|i| i >= from));
            Ok((label.to_string(), lines))
        })
        .collect::<Res<_>>()?;
    if runs.is_empty() {
        return Err("no runs given".into());
    }
    rangegan_mcap::report::plot::register_font();
    let colours = [RED, BLUE, GREEN, MAGENTA, CYAN];
    // (title, solid line, thin line)
    let panels = [
        ("discriminator loss", "/loss_d", None),
        ("generator loss", "/loss_g", None),
        (
            "D(real) (solid) and D(fake) (thin)",
            "/d_real",
            Some("/d_fake"),
        ),
        ("finite-difference R1 estimate", "/r1", None),
        ("ADA augmentation probability", "/ada_p", None),
        ("images/s", "/images_per_s", None),
        (
            "drop share: generated (solid), real (thin)",
            "/fake/drop",
            Some("/real/drop"),
        ),
        (
            "spread of inverse depth: generated, real",
            "/fake/std",
            Some("/real/std"),
        ),
    ];
    let size = (2000u32, 1000u32);
    let mut buf = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE)?;
        for (area, (title, solid, thin)) in root.split_evenly((2, 4)).iter().zip(panels) {
            let mut all: Vec<Curve> = Vec::new();
            for (i, (_, lines)) in runs.iter().enumerate() {
                all.push((i, series(lines, solid, 20), true));
                if let Some(thin) = thin {
                    all.push((i, series(lines, thin, 20), false));
                }
            }
            let pts = all.iter().flat_map(|s| s.1.iter());
            let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, 1.0f64, f64::MAX, f64::MIN);
            for p in pts.filter(|p| p.1.is_finite()) {
                x0 = x0.min(p.0);
                x1 = x1.max(p.0);
                y0 = y0.min(p.1);
                y1 = y1.max(p.1);
            }
            if y0 > y1 {
                (y0, y1) = (0.0, 1.0);
            }
            let pad = 0.05 * (y1 - y0).max(1e-6);
            let mut chart = ChartBuilder::on(area)
                .caption(title, ("sans-serif", 18))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(55)
                .build_cartesian_2d(x0.min(x1 - 1.0)..x1, (y0 - pad)..(y1 + pad))?;
            chart
                .configure_mesh()
                .x_desc("real images seen")
                .label_style(("sans-serif", 12))
                .draw()?;
            for (i, pts, solid) in all {
                let c = colours[i % colours.len()];
                let style = c.stroke_width(if solid { 2 } else { 1 });
                let s = chart.draw_series(LineSeries::new(
                    pts.into_iter().filter(|p| p.1.is_finite()),
                    style,
                ))?;
                if solid {
                    s.label(runs[i].0.as_str()).legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2))
                    });
                }
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 12))
                .draw()?;
        }
        root.present()?;
    }
    let png = rangegan_mcap::util::png::encode_rgb(size.0, size.1, &buf)?;
    rangegan_mcap::util::fs::write_atomic(&out, &png)
        .map_err(|e| format!("{}: {e}", out.display()))?;
    println!("wrote {}", out.display());
    Ok(())
}

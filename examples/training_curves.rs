//! Training curves of GAN runs from their `log.jsonl`: discriminator and generator losses,
//! D(real) and D(fake), the finite-difference R1 estimate and the ADA probability, against
//! real images seen. Shows whether training is stable without the second-order R1.
//!
//! ```text
//! cargo run --release --example training_curves -- OUT.png LABEL=RUN_DIR ...
//! ```

use std::path::{Path, PathBuf};

use plotters::prelude::*;

type Res<T> = Result<T, Box<dyn std::error::Error>>;
/// (run index, points, solid line?)
type Curve = (usize, Vec<(f64, f64)>, bool);

/// One logged quantity of one run: (images, value), smoothed over `window` log lines.
fn series(lines: &[serde_json::Value], key: &str, window: usize) -> Vec<(f64, f64)> {
    let raw: Vec<(f64, f64)> = lines
        .iter()
        .filter_map(|l| Some((l["images"].as_f64()?, l[key].as_f64()?)))
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
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(
        args.next()
            .ok_or("usage: training_curves OUT.png LABEL=RUN_DIR ...")?,
    );
    let runs: Vec<(String, Vec<serde_json::Value>)> = args
        .map(|a| {
            let (label, dir) = a.split_once('=').unwrap_or((&a, &a));
            Ok((label.to_string(), read_log(Path::new(dir))?))
        })
        .collect::<Res<_>>()?;
    if runs.is_empty() {
        return Err("no runs given".into());
    }
    rangegan_mcap::report::plot::register_font();
    let colours = [RED, BLUE, GREEN, MAGENTA, CYAN];
    let panels = [
        ("discriminator loss", "loss_d"),
        ("generator loss", "loss_g"),
        ("D(real) (solid) and D(fake) (thin)", "d_real"),
        ("finite-difference R1 estimate", "r1"),
        ("ADA augmentation probability", "ada_p"),
        ("images/s", "images_per_s"),
    ];
    let size = (1500u32, 1000u32);
    let mut buf = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE)?;
        for (area, (title, key)) in root.split_evenly((2, 3)).iter().zip(panels) {
            let mut all: Vec<Curve> = Vec::new();
            for (i, (_, lines)) in runs.iter().enumerate() {
                all.push((i, series(lines, key, 20), true));
                if key == "d_real" {
                    all.push((i, series(lines, "d_fake", 20), false));
                }
            }
            let pts = all.iter().flat_map(|s| s.1.iter());
            let (mut x1, mut y0, mut y1) = (1.0f64, f64::MAX, f64::MIN);
            for p in pts.filter(|p| p.1.is_finite()) {
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
                .build_cartesian_2d(0.0..x1, (y0 - pad)..(y1 + pad))?;
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

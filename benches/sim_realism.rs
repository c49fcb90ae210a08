//! Realism report: simulated HDL-64E scans (ideal and `realistic` physics) against
//! real KITTI scans, at the real files' 64 x 512 resolution. Writes the plots
//! into `docs/` and prints the numbers as a markdown table:
//!
//! `cargo bench --bench sim_realism`            (real data from ../shared/real_lidar)
//!
//! Optional arguments: `--real DIR` (a folder of KITTI `velodyne/*.bin`, repeatable),
//! `--seeds N` (scenes, default 12), `--out DIR` (default docs).
//! Not a timing benchmark: a bench target so it runs optimised and outside tests.

use std::path::{Path, PathBuf};

use plotters::prelude::*;
use rangegan_mcap::lidar::{RangeImage, SensorProfile};
use rangegan_mcap::physics::Preset;
use rangegan_mcap::sim::realism::{
    RANGE_BIN_M, RANGE_BINS, RealismStats, find_kitti_scans, real_range_image,
};
use rangegan_mcap::sim::{SceneConfig, Simulator};

type Res<T> = Result<T, Box<dyn std::error::Error>>;
/// A named, coloured curve.
type Series<'a> = (&'a str, RGBColor, Vec<(f64, f64)>);

fn main() -> Res<()> {
    let args: Vec<String> = std::env::args().collect();
    let mut real_dirs: Vec<PathBuf> = Vec::new();
    let mut seeds = 12u64;
    let mut out = PathBuf::from("docs");
    let mut i = 1;
    while i < args.len() {
        match args[i].as_str() {
            "--real" if i + 1 < args.len() => {
                real_dirs.push(args[i + 1].clone().into());
                i += 1;
            }
            "--seeds" if i + 1 < args.len() => {
                seeds = args[i + 1].parse()?;
                i += 1;
            }
            "--out" if i + 1 < args.len() => {
                out = args[i + 1].clone().into();
                i += 1;
            }
            _ => {} // cargo bench passes --bench
        }
        i += 1;
    }
    if real_dirs.is_empty() {
        real_dirs = vec![
            "../shared/real_lidar/semantickitti_mini".into(),
            "../shared/real_lidar/kitti_raw_drive_a".into(),
        ];
    }
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let (h, w) = (profile.beams(), profile.columns);

    let mut real = RealismStats::new("real KITTI", h, w);
    let mut real_example: Option<RangeImage> = None;
    for dir in &real_dirs {
        if !dir.exists() {
            eprintln!("skipped {}: absent", dir.display());
            continue;
        }
        for (bin, labels) in find_kitti_scans(dir) {
            let img = real_range_image(&bin, labels.as_deref(), &profile)
                .map_err(|e| format!("{}: {e}", bin.display()))?;
            real.add(&img, labels.is_some());
            if real_example.is_none() {
                real_example = Some(img);
            }
        }
    }
    if real.scans == 0 {
        return Err("no real KITTI scans found; pass --real DIR".into());
    }

    let physics = Preset::Realistic.config().effects();
    let mut ideal = RealismStats::new("sim ideal", h, w);
    let mut realistic = RealismStats::new("sim realistic", h, w);
    let mut examples: Option<(RangeImage, RangeImage)> = None;
    for seed in 1..=seeds {
        let sim = Simulator::new(
            SceneConfig {
                seed,
                duration_s: 5.0,
                ..Default::default()
            },
            profile.clone(),
        );
        for index in (0..50).step_by(10) {
            let scan = sim.scan(index);
            ideal.add(&scan.image, true);
            let mut r = scan.clone();
            physics.apply(&mut r, seed);
            realistic.add(&r.image, true);
            if examples.is_none() {
                examples = Some((scan.image.clone(), r.image.clone()));
            }
        }
    }

    std::fs::create_dir_all(&out)?;
    rangegan_mcap::report::plot::register_font();
    let sets = [(&real, BLACK), (&ideal, BLUE), (&realistic, RED)];
    curves_png(&out.join("simulator_realism.png"), &sets)?;
    classes_png(&out.join("simulator_classes.png"), &sets)?;
    if let (Some(r), Some((si, sr))) = (&real_example, &examples) {
        range_images_png(&out.join("simulator_range_images.png"), &[r, si, sr])?;
    }
    print_table(&sets);
    Ok(())
}

fn save_png(path: &Path, buf: &[u8], size: (u32, u32)) -> Res<()> {
    let png = rangegan_mcap::util::png::encode_rgb(size.0, size.1, buf)?;
    rangegan_mcap::util::fs::write_atomic(path, &png)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

fn line_panel(
    area: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
    title: &str,
    x_label: &str,
    y_label: &str,
    x_range: std::ops::Range<f64>,
    y_range: std::ops::Range<f64>,
    series: &[Series<'_>],
) -> Res<()> {
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(x_range, y_range)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .label_style(("sans-serif", 13))
        .draw()?;
    for (name, color, pts) in series {
        let c = *color;
        chart
            .draw_series(LineSeries::new(
                pts.iter().copied().filter(|p| p.1.is_finite()),
                c.stroke_width(2),
            ))?
            .label(*name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()?;
    Ok(())
}

fn curves_png(path: &Path, sets: &[(&RealismStats, RGBColor)]) -> Res<()> {
    let size = (1400u32, 1000u32);
    let mut buf = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE)?;
        let panels = root.split_evenly((2, 2));
        let named = |f: &dyn Fn(&RealismStats) -> Vec<(f64, f64)>| -> Vec<Series<'_>> {
            sets.iter()
                .map(|(s, c)| (s.name.as_str(), *c, f(s)))
                .collect()
        };
        let rows = named(&|s| {
            s.row_keep()
                .into_iter()
                .enumerate()
                .map(|(i, v)| (i as f64, v))
                .collect()
        });
        line_panel(
            &panels[0],
            "keep rate per row (0 = top beam)",
            "row",
            "keep rate",
            0.0..64.0,
            0.0..1.05,
            &rows,
        )?;
        let drop = named(&|s| {
            s.drop_vs_range()
                .into_iter()
                .take(RANGE_BINS)
                .enumerate()
                .map(|(i, v)| ((i as f64 + 0.5) * RANGE_BIN_M as f64, v))
                .collect()
        });
        line_panel(
            &panels[1],
            "drop rate vs range of the surroundings",
            "median range of 3x9 neighbours (m)",
            "drop rate",
            0.0..80.0,
            0.0..1.0,
            &drop,
        )?;
        let hist = named(&|s| {
            s.range_histogram()
                .into_iter()
                .enumerate()
                .map(|(i, v)| ((i as f64 + 0.5) * RANGE_BIN_M as f64, v))
                .collect()
        });
        line_panel(
            &panels[2],
            "range histogram of returns",
            "range (m)",
            "share of returns per 4 m",
            0.0..80.0,
            0.0..0.4,
            &hist,
        )?;
        let cols = named(&|s| {
            let g = 8;
            s.column_keep(g)
                .into_iter()
                .enumerate()
                .map(|(i, v)| {
                    (
                        ((i * g) as f64 + g as f64 / 2.0) / s.width as f64 * 360.0 - 180.0,
                        v,
                    )
                })
                .collect()
        });
        line_panel(
            &panels[3],
            "keep rate per azimuth (0 = straight ahead)",
            "azimuth from the rear, clockwise (deg; 0 = ahead)",
            "keep rate",
            -180.0..180.0,
            0.5..1.0,
            &cols,
        )?;
        root.present()?;
    }
    save_png(path, &buf, size)
}

fn classes_png(path: &Path, sets: &[(&RealismStats, RGBColor)]) -> Res<()> {
    let classes = [
        "road",
        "sidewalk",
        "parking/other-ground",
        "building",
        "fence",
        "vegetation",
        "trunk",
        "terrain",
        "pole",
        "traffic-sign",
        "car",
        "other-vehicle",
        "person",
        "bicyclist",
        "bicycle",
        "other",
    ];
    let labelled: Vec<&(&RealismStats, RGBColor)> = sets
        .iter()
        .filter(|(s, _)| !s.class_share().is_empty())
        .collect();
    let size = (1400u32, 600u32);
    let mut buf = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                "share of returns per class (SemanticKITTI ids)",
                ("sans-serif", 20),
            )
            .margin(10)
            .x_label_area_size(150)
            .y_label_area_size(50)
            .build_cartesian_2d(0.0..classes.len() as f64, 0.0..0.5)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(0)
            .y_desc("share of returns")
            .label_style(("sans-serif", 13))
            .draw()?;
        // Class names under the bar groups, turned 90 degrees.
        let style = ("sans-serif", 14)
            .into_font()
            .transform(FontTransform::Rotate90)
            .color(&BLACK);
        for (i, name) in classes.iter().enumerate() {
            let (x, y) = chart.backend_coord(&(i as f64 + 0.45, 0.0));
            root.draw(&Text::new(name.to_string(), (x, y + 6), style.clone()))?;
        }
        let n = labelled.len() as f64;
        for (k, (s, color)) in labelled.iter().enumerate() {
            let share = s.class_share();
            let c = *color;
            chart
                .draw_series(classes.iter().enumerate().map(|(i, name)| {
                    let v = share.get(name).copied().unwrap_or(0.0);
                    let x0 = i as f64 + 0.1 + 0.8 * k as f64 / n;
                    Rectangle::new([(x0, 0.0), (x0 + 0.8 / n, v)], c.filled())
                }))?
                .label(s.name.as_str())
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], c.filled()));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()?;
        root.present()?;
    }
    save_png(path, &buf, size)
}

/// Range images stacked (real, sim ideal, sim realistic): grey by inverse depth,
/// red where a ray returned nothing.
fn range_images_png(path: &Path, images: &[&RangeImage]) -> Res<()> {
    let (h, w) = (images[0].height, images[0].width);
    let scale = 2usize;
    let gap = 6usize;
    let (pw, ph) = (w * scale, images.len() * (h * scale + gap));
    let mut buf = vec![255u8; pw * ph * 3];
    for (n, img) in images.iter().enumerate() {
        for r in 0..h * scale {
            for c in 0..pw {
                let k = (r / scale) * w + c / scale;
                let px = [if img.is_valid(k) {
                    let v = (255.0 * (1.45 / img.range_m[k]).clamp(0.0, 1.0).sqrt()) as u8;
                    [v, v, v]
                } else {
                    [150, 20, 20]
                }][0];
                let o = ((n * (h * scale + gap) + r) * pw + c) * 3;
                buf[o..o + 3].copy_from_slice(&px);
            }
        }
    }
    save_png(path, &buf, (pw as u32, ph as u32))
}

fn print_table(sets: &[(&RealismStats, RGBColor)]) {
    println!(
        "\n| statistic | {} |",
        sets.iter()
            .map(|(s, _)| s.name.clone())
            .collect::<Vec<_>>()
            .join(" | ")
    );
    println!("|---|{}", "---|".repeat(sets.len()));
    let row = |name: &str, f: &dyn Fn(&RealismStats) -> String| {
        println!(
            "| {name} | {} |",
            sets.iter()
                .map(|(s, _)| f(s))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    };
    row("scans", &|s| s.scans.to_string());
    row("keep rate, all pixels", &|s| {
        format!("{:.3}", s.keep_rate())
    });
    row("keep rate, rows 0-7 (top)", &|s| {
        format!("{:.3}", s.rows_keep(0..8))
    });
    row("keep rate, rows 16-47", &|s| {
        format!("{:.3}", s.rows_keep(16..48))
    });
    row("keep rate, rows 56-63 (bottom)", &|s| {
        format!("{:.3}", s.rows_keep(56..64))
    });
    let real = sets[0].0;
    let l1 = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| (x - y).abs())
            .sum::<f64>()
            / a.len() as f64
    };
    row("mean abs. diff. of row keep vs real", &|s| {
        format!("{:.3}", l1(&s.row_keep(), &real.row_keep()))
    });
    row("mean abs. diff. of drop-vs-range vs real", &|s| {
        format!(
            "{:.3}",
            l1(
                &s.drop_vs_range()[..RANGE_BINS],
                &real.drop_vs_range()[..RANGE_BINS]
            )
        )
    });
    row("share of pixels with no return around (sky)", &|s| {
        format!("{:.3}", s.context_share()[RANGE_BINS])
    });
    row("range histogram: total variation vs real", &|s| {
        format!(
            "{:.3}",
            0.5 * l1(&s.range_histogram(), &real.range_histogram()) * RANGE_BINS as f64
        )
    });
    let median = |s: &RealismStats| {
        let h = s.range_histogram();
        let mut acc = 0.0;
        for (i, v) in h.iter().enumerate() {
            acc += v;
            if acc >= 0.5 {
                return format!(
                    "{:.0}-{:.0} m",
                    i as f32 * RANGE_BIN_M,
                    (i + 1) as f32 * RANGE_BIN_M
                );
            }
        }
        "-".into()
    };
    row("median range bin of returns", &median);
    let classes = [
        "road",
        "sidewalk",
        "building",
        "vegetation",
        "terrain",
        "car",
        "fence",
        "pole",
        "trunk",
    ];
    for c in classes {
        row(&format!("class share: {c}"), &|s| {
            s.class_share()
                .get(c)
                .map_or("-".into(), |v| format!("{v:.3}"))
        });
    }
}

//! A picture of what `convert` writes for one held-out real KITTI scan: the measured range
//! image, the completed depth x_d, the calibrated ray-drop probability x_n, a sampled ray-drop
//! mask, and the decoded scene rendered at 4x the columns (a quarter of the azimuth, to show
//! the pixels). `fast` decoding with the shipped weights.
//!
//!     cargo run --release --example decode_figure -- ../shared/real_lidar/semantickitti_ssv3/000000.bin \
//!         docs/img/decode_example.png

use std::path::PathBuf;

use anyhow::{Context, Result};
use plotters::prelude::*;
use rangegan_mcap::decode::{DecodeOptions, Decoder, Quality, scan_seed};
use rangegan_mcap::lidar::{self, SensorProfile, Strategy};
use rangegan_mcap::model::weights::Model;
use rangegan_mcap::report::plot::{register_font, viridis};
use rangegan_mcap::util::fs::write_atomic;
use rangegan_mcap::util::png::encode_rgb;

/// Panel width in pixels; the 64-row images are drawn with 2x2 pixels per range-image pixel.
const WIDTH: u32 = 1024;
const TITLE: u32 = 22;

/// One panel: a title and an `h x w` image coloured per pixel.
struct Panel {
    title: String,
    h: usize,
    w: usize,
    colour: Box<dyn Fn(usize) -> [u8; 3]>,
}

/// Near = bright: log depth over 1.45-80 m, black where there is no value.
fn depth_colour(d: f32) -> [u8; 3] {
    if d > 0.0 {
        viridis(1.0 - (d / 1.45).ln() / (80.0f32 / 1.45).ln())
    } else {
        [0, 0, 0]
    }
}

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let scan_path = PathBuf::from(
        args.next()
            .context("usage: decode_figure SCAN.bin OUT.png")?,
    );
    let out = PathBuf::from(
        args.next()
            .context("usage: decode_figure SCAN.bin OUT.png")?,
    );
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let scan = lidar::kitti::read_bin(&scan_path)?;
    let image = lidar::project(&scan, &profile, Strategy::Auto)?;
    let device = burn::tensor::Device::flex();
    let decoder = Decoder::new(Model::shipped(&device)?, DecodeOptions::new(Quality::Fast))?;
    let decoded = decoder.decode(&image, scan_seed("/velodyne_points", 0))?;
    let mask = decoded.sample_masks(1).remove(0);
    let dense = decoded.render(&decoder, &profile.with_columns(2048).angle_grid());
    eprintln!(
        "{}: relative error on the measured pixels {:.3}",
        scan_path.display(),
        decoded.error.unwrap_or(f32::NAN)
    );

    let (range, depth) = (image.range_m.clone(), decoded.model.depth_m.clone());
    let x_n = decoded.model.drop_prob.clone();
    let quarter: Vec<f32> = (0..64 * 512)
        .map(|k| dense.depth_m[(k / 512) * 2048 + 768 + k % 512])
        .collect();
    let measured_quarter: Vec<f32> = (0..64 * 512)
        .map(|k| {
            let (r, c) = (k / 512, 192 + (k % 512) / 4);
            image.range_m[r * 512 + c]
        })
        .collect();
    let panels = [
        Panel {
            title:
                "measured range, 64 x 512 (log scale: yellow 1.45 m, dark 80 m; black: no return)"
                    .into(),
            h: 64,
            w: 512,
            colour: Box::new(move |k| depth_colour(range[k])),
        },
        Panel {
            title: format!(
                "completed depth x_d (fast decode; {:.1} % relative error on the measured pixels)",
                100.0 * decoded.error.unwrap_or(f32::NAN)
            ),
            h: 64,
            w: 512,
            colour: Box::new(move |k| depth_colour(depth[k])),
        },
        Panel {
            title: "ray-drop probability x_n, calibrated (dark 0, yellow 1)".into(),
            h: 64,
            w: 512,
            colour: Box::new(move |k| viridis(x_n[k])),
        },
        Panel {
            title: "a sampled ray-drop mask (white: return kept)".into(),
            h: 64,
            w: 512,
            colour: Box::new(move |k| if mask[k] { [255; 3] } else { [0; 3] }),
        },
        Panel {
            title: "measured, columns 192-319 of 512 (the front quarter), each shown 4x wide"
                .into(),
            h: 64,
            w: 512,
            colour: Box::new(move |k| depth_colour(measured_quarter[k])),
        },
        Panel {
            title: "x_d rendered at 2048 columns, the same quarter (columns 768-1279)".into(),
            h: 64,
            w: 512,
            colour: Box::new(move |k| depth_colour(quarter[k])),
        },
    ];

    register_font();
    let panel_h = TITLE + 128;
    let height = panel_h * panels.len() as u32;
    let mut buf = vec![255u8; (WIDTH * height * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, height)).into_drawing_area();
        for (panel, area) in panels.iter().zip(root.split_evenly((panels.len(), 1))) {
            area.draw_text(
                &panel.title,
                &("sans-serif", 15).into_font().color(&BLACK),
                (4, 3),
            )?;
            let (sx, sy) = (WIDTH as usize / panel.w, 128 / panel.h);
            for k in 0..panel.h * panel.w {
                let [r, g, b] = (panel.colour)(k);
                let (x0, y0) = ((k % panel.w) * sx, TITLE as usize + (k / panel.w) * sy);
                for dy in 0..sy {
                    for dx in 0..sx {
                        area.draw_pixel(((x0 + dx) as i32, (y0 + dy) as i32), &RGBColor(r, g, b))?;
                    }
                }
            }
        }
        root.present()?;
    }
    write_atomic(&out, &encode_rgb(WIDTH, height, &buf)?)
        .with_context(|| format!("failed to write {}", out.display()))?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

//! A picture of what `convert` writes for one held-out, full-resolution real KITTI scan
//! (64 x 2048, never trained or tuned on), decoded by the shipped spatial-latent model: the
//! measured range, x_d, `depth`, x_n, a sampled ray-drop mask, and x_d restored from 16 of
//! the 64 beams. Each panel shows the front quarter of the turn (columns 768-1279), each
//! pixel drawn 2 x 2.
//!
//!     cargo run --release --example decode_figure -- ../shared/real_lidar/semantickitti_ssv3/000000.bin \
//!         docs/img/decode_example.png [MODEL_DIR]

use std::path::PathBuf;

use anyhow::{Context, Result};
use plotters::prelude::*;
use rangegan_mcap::decode::{Sparsify, sample_masks, scan_seed};
use rangegan_mcap::lidar::{self, SensorProfile, Strategy};
use rangegan_mcap::model::spatial::decode::{decode, rays_of};
use rangegan_mcap::model::spatial::{Ray, SpatialModel};
use rangegan_mcap::report::plot::{register_font, viridis};
use rangegan_mcap::util::fs::write_atomic;
use rangegan_mcap::util::png::encode_rgb;

/// Panel width in pixels; the 64-row images are drawn with 2x2 pixels per range-image pixel.
const WIDTH: u32 = 1024;
const TITLE: u32 = 22;
/// Columns of the full-resolution grid.
const COLUMNS: usize = 2048;

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
    let usage = "usage: decode_figure SCAN.bin OUT.png [MODEL_DIR]";
    let scan_path = PathBuf::from(args.next().context(usage)?);
    let out = PathBuf::from(args.next().context(usage)?);
    let device = burn::tensor::Device::flex();
    let model = match args.next() {
        Some(dir) => SpatialModel::load(std::path::Path::new(&dir), &device)?,
        None => SpatialModel::shipped(&device)?,
    };
    let profile = SensorProfile::kitti_hdl64e().with_columns(COLUMNS);
    let scan = lidar::kitti::read_bin(&scan_path)?;
    let image = lidar::project(&scan, &profile, Strategy::Auto)?;
    let host = model.host();
    let rays = rays_of(&image.range_m);
    let decoded = decode(&host, &rays, &image.angles);
    let mask = sample_masks(&decoded.drop_prob, 1, scan_seed("/velodyne_points", 0)).remove(0);
    let kept = Sparsify::kept_rows(16, 64);
    let sparse: Vec<Ray> = (rays.iter().enumerate())
        .map(|(k, &r)| {
            if kept.contains(&(k / COLUMNS)) {
                r
            } else {
                Ray::Unknown
            }
        })
        .collect();
    let restored = decode(&host, &sparse, &image.angles);
    let returns: Vec<usize> = (0..image.len())
        .filter(|&k| image.range_m[k] > 0.0)
        .collect();
    let rel = returns
        .iter()
        .map(|&k| ((decoded.depth_m[k] - image.range_m[k]) / image.range_m[k]).abs())
        .sum::<f32>()
        / returns.len().max(1) as f32;
    eprintln!(
        "{}: x_d relative L1 at the returns {rel:.4}",
        scan_path.display()
    );
    let depth: Vec<f32> = (0..image.len())
        .map(|k| match image.range_m[k] > 0.0 {
            true => image.range_m[k],
            false => decoded.depth_m[k],
        })
        .collect();
    // The front quarter of the turn.
    let front = |v: &[f32]| -> Vec<f32> {
        (0..64 * 512)
            .map(|k| v[(k / 512) * COLUMNS + 768 + k % 512])
            .collect()
    };
    let (range, x_d, depth) = (
        front(&image.range_m),
        front(&decoded.depth_m),
        front(&depth),
    );
    let (x_n, restored) = (front(&decoded.drop_prob), front(&restored.depth_m));
    let mask: Vec<bool> = (0..64 * 512)
        .map(|k| mask[(k / 512) * COLUMNS + 768 + k % 512])
        .collect();
    let panel = |title: String, colour: Box<dyn Fn(usize) -> [u8; 3]>| Panel {
        title,
        h: 64,
        w: 512,
        colour,
    };
    let panels = [
        panel(
            "measured range, 64 x 2048, front quarter (log scale: yellow 1.45 m, dark 80 m; black: no return)".into(),
            Box::new(move |k| depth_colour(range[k])),
        ),
        panel(
            format!("x_d, the decoded depth at every ray ({:.1} % relative error at the returns)", 100.0 * rel),
            Box::new(move |k| depth_colour(x_d[k])),
        ),
        panel(
            "the measured returns with x_d in the rays that came back empty".into(),
            Box::new(move |k| depth_colour(depth[k])),
        ),
        panel(
            "ray-drop probability x_n, each ray predicted without seeing it (dark 0, yellow 1)".into(),
            Box::new(move |k| viridis(x_n[k])),
        ),
        panel(
            "a ray-drop mask drawn from x_n (white: return kept)".into(),
            Box::new(move |k| if mask[k] { [255; 3] } else { [0; 3] }),
        ),
        panel(
            "x_d restored from 16 of the 64 beams (the other 48 unknown to the model)".into(),
            Box::new(move |k| depth_colour(restored[k])),
        ),
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

//! Where a spatial decode's time goes on one full-resolution KITTI scan (64 x 2048), one
//! thread: encoding (both passes), preparing the grid's queries (once per grid), rendering.
//!
//!     RAYON_NUM_THREADS=1 cargo run --release --example spatial_timing -- SCAN.bin [MODEL_DIR]

use std::time::Instant;

use anyhow::{Context, Result};
use burn::tensor::Device;
use rangegan_mcap::lidar::{self, SensorProfile, Strategy};
use rangegan_mcap::model::spatial::decode::{encode, own_queries, rays_of, render};
use rangegan_mcap::model::spatial::{Observation, SpatialModel, encoder_input, own_features};

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let scan = lidar::kitti::read_bin(std::path::Path::new(&args.next().context("SCAN.bin")?))?;
    let device = Device::flex();
    let model = match args.next() {
        Some(dir) => SpatialModel::load(std::path::Path::new(&dir), &device)?,
        None => SpatialModel::shipped(&device)?,
    };
    let profile = SensorProfile::kitti_hdl64e().with_columns(2048);
    let image = lidar::project(&scan, &profile, Strategy::Auto)?;
    let rays = rays_of(&image.range_m);
    let config = &model.config;
    let t = Instant::now();
    let host = model.host();
    let queries = own_queries(&host, &image.angles);
    let prepare = t.elapsed();
    for _ in 0..3 {
        // What the model is shown of the rays (both passes' inputs cost about this twice).
        let t = Instant::now();
        let obs = Observation {
            rays: &rays,
            angles: &image.angles,
            circular: true,
        };
        let own = own_features(&obs, config);
        let (input, _) = encoder_input(&own, &image.angles);
        let inputs = t.elapsed();
        std::hint::black_box(input);
        let t = Instant::now();
        let encoded = encode(&host, &rays, &image.angles);
        let enc = t.elapsed();
        let t = Instant::now();
        let out = render(&host, &encoded, &queries);
        let ren = t.elapsed();
        eprintln!(
            "prepare {prepare:?} (once per grid), encode {enc:?} (of which one pass's inputs {inputs:?}), render {ren:?} ({} rays)",
            out.depth_m.len()
        );
    }
    Ok(())
}

//! Criterion benchmarks of the `lidar` module on one full-resolution KITTI scan
//! (~124k points): projection per strategy at 64x2048, sensor estimation, and
//! resampling. Reads `../shared/real_lidar/semantickitti_ssv3/000000.bin` when it
//! exists, else generates a scan with the same layout (64 rings x 2010 points in
//! KITTI ring order). Run: `cargo bench --bench lidar_projection`; numbers in
//! `docs/lidar.md`.

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use rangegan_mcap::lidar::{
    Interpolation, Scan, SensorProfile, Strategy, estimate_profile, kitti, project, resample_image,
};

/// The real scan, or a generated one in the same layout.
fn kitti_scan() -> (Scan, &'static str) {
    let path = Path::new("../shared/real_lidar/semantickitti_ssv3/000000.bin");
    if let Ok(scan) = kitti::read_scan(path, None) {
        return (scan, "real KITTI 000000.bin");
    }
    let table = SensorProfile::kitti_hdl64e().elevation_deg;
    let per_ring = 2010;
    let mut xyz = Vec::with_capacity(table.len() * per_ring);
    for (ring, e) in table.iter().enumerate() {
        for k in 0..per_ring {
            // Each ring starts just left of ahead and sweeps counter-clockwise.
            let az = 0.001 + k as f32 * std::f32::consts::TAU / per_ring as f32;
            let r = 4.0 + 30.0 * (0.5 + 0.5 * (3.0 * az + ring as f32).sin());
            let e = e.to_radians();
            xyz.push([r * e.cos() * az.cos(), r * e.cos() * az.sin(), r * e.sin()]);
        }
    }
    (Scan::from_xyz(xyz), "generated KITTI-like scan")
}

fn benches(c: &mut Criterion) {
    let (scan, what) = kitti_scan();
    eprintln!("input: {what}, {} points", scan.len());
    let profile = SensorProfile::kitti_hdl64e().with_columns(2048);
    let mut g = c.benchmark_group("lidar");
    for (name, strategy) in [
        ("ring-order", Strategy::RingOrder),
        ("auto", Strategy::Auto),
        ("spherical", Strategy::Spherical),
    ] {
        g.bench_function(format!("project/{name}/64x2048"), |b| {
            b.iter(|| project(black_box(&scan), &profile, strategy).unwrap())
        });
    }
    g.bench_function("estimate/ring-order/1-scan", |b| {
        b.iter(|| estimate_profile(std::slice::from_ref(black_box(&scan))).unwrap())
    });
    let small = project(
        &scan,
        &SensorProfile::kitti_hdl64e().with_columns(512),
        Strategy::RingOrder,
    )
    .unwrap();
    let fine = small.angles.resized(64, 2048);
    g.bench_function("grid-resize/64x512-to-128x2048", |b| {
        b.iter(|| black_box(&small.angles).resized(128, 2048))
    });
    for m in [Interpolation::Nearest, Interpolation::Bilinear] {
        g.bench_function(format!("resample/{}/64x512-to-64x2048", m.name()), |b| {
            b.iter(|| resample_image(black_box(&small), &fine, m))
        });
    }
    g.finish();
}

criterion_group!(lidar, benches);
criterion_main!(lidar);

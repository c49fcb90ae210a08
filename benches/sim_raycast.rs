//! Ray-casting speed: one 64 x 2048 HDL-64E scan of a generated street scene on
//! one core (rayon pool of one thread), plus the same on all cores and the
//! `realistic` physics on top. Plain timing harness (no criterion):
//!
//! `cargo bench --bench sim_raycast`
//!
//! Prints `group/case/size: median ms (min .. max) over N scans`.

use std::time::Instant;

use rangegan_mcap::lidar::SensorProfile;
use rangegan_mcap::physics::Preset;
use rangegan_mcap::sim::{SceneConfig, Simulator};

/// CPU seconds used by this process so far (user + system, all threads), from
/// `/proc/self/stat`; on a shared machine this is the fair single-core cost.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0) // USER_HZ is 100 on Linux
}

fn time_scans(label: &str, scans: u32, mut f: impl FnMut(u32)) {
    f(0); // warm up caches and the dynamic BVH path
    let cpu0 = cpu_seconds();
    let mut ms: Vec<f64> = (1..=scans)
        .map(|i| {
            let t = Instant::now();
            f(i);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let cpu = cpu0
        .zip(cpu_seconds())
        .map(|(a, b)| (b - a) * 1e3 / scans as f64);
    ms.sort_by(f64::total_cmp);
    let cpu = cpu.map_or(String::new(), |c| format!("; CPU {c:.1} ms/scan"));
    println!(
        "{label}: wall median {:.1} ms (min {:.1} .. max {:.1}) over {scans} scans{cpu}",
        ms[ms.len() / 2],
        ms[0],
        ms[ms.len() - 1]
    );
}

fn main() {
    let t = Instant::now();
    let sim = Simulator::new(
        SceneConfig {
            seed: 1,
            duration_s: 3.0,
            ..Default::default()
        },
        SensorProfile::kitti_hdl64e(),
    );
    println!(
        "sim/scene/seed1: generated in {:.0} ms ({} static primitives, {} actors)",
        t.elapsed().as_secs_f64() * 1e3,
        sim.scene.static_primitives(),
        sim.scene.actor_count()
    );
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a one-thread pool");
    let scans = 40;
    one.install(|| time_scans("sim/raycast-1core/64x2048", scans, |i| drop(sim.scan(i))));
    time_scans(
        &format!("sim/raycast-{}cores/64x2048", rayon::current_num_threads()),
        scans,
        |i| drop(sim.scan(i)),
    );
    let physics = Preset::Realistic.config().effects();
    let base = sim.scan(0);
    one.install(|| {
        time_scans("sim/physics-realistic-1core/64x2048", scans, |_| {
            let mut s = base.clone();
            physics.apply(&mut s, 1);
        })
    });
}

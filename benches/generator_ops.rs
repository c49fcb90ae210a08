//! Generator operations at the reference size (`GeneratorConfig::new()`, 64x512 KITTI grid),
//! timed one by one and printed as one JSON line, for the side-by-side run against the reference
//! PyTorch code (`benches/vs_pytorch.sh`, which alternates this with
//! `benches/reference_pytorch.py`).
//!
//! `cargo bench --bench generator_ops -- [--reps N] [--ops fwd_b1,fwd_b8,...] [--model DIR]`
//!
//! Operations (same names and same work as `reference_pytorch.py`; the generator always runs
//! from w on the cached grid, mapping excluded):
//! - `fwd_b1`, `fwd_b8`: forward, no autodiff.
//! - `fwdbwd_b1`, `fwdbwd_b8`: forward + backward of `sum(x_d) + sum(logit)` to w and every
//!   weight.
//! - `inv_w_b1`: one auto-decoding step: forward, L1 loss to a fixed target, backward to w
//!   only (weights frozen), Adam step on w.
//! - `pti_b1`: one pivotal-tuning step: same loss, backward to w and every weight, Adam step on
//!   all of them.
//!
//! Each figure is the list of per-call wall seconds after one warm-up call; `<op>_cpu` is the
//! process CPU time (all threads) of the same calls, which shows how much of the cores the
//! process got on a shared machine.

use std::time::Instant;

use burn::module::{Module, Param};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};
use rangegan_mcap::lidar::SensorProfile;
use rangegan_mcap::model::generator::{Generator, GeneratorConfig, GridCache};
use rangegan_mcap::util::rng::Rng;

const ALL_OPS: [&str; 6] = [
    "fwd_b1",
    "fwd_b8",
    "fwdbwd_b1",
    "fwdbwd_b8",
    "inv_w_b1",
    "pti_b1",
];

/// Process CPU time (user + system, all threads), seconds.
fn cpu_time() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own; CLOCK_PROCESS_CPUTIME_ID exists
    // on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// (wall, cpu) seconds of `reps` calls after one warm-up.
fn times(reps: usize, mut f: impl FnMut()) -> (Vec<f64>, Vec<f64>) {
    f(); // warm-up
    (0..reps)
        .map(|_| {
            let (s, c) = (Instant::now(), cpu_time());
            f();
            (s.elapsed().as_secs_f64(), cpu_time() - c)
        })
        .unzip()
}

fn sync(x: Tensor<1>) {
    let _ = x.into_data();
}

/// The generator together with the latent it renders from, so that one Adam optimises both
/// (pivotal tuning) or, with the generator frozen, w alone.
#[derive(Module, Debug)]
struct Inversion {
    g: Generator,
    w: Param<Tensor<2>>,
}

fn grid(g: &Generator, device: &Device) -> GridCache {
    g.prepare(
        &SensorProfile::kitti_hdl64e().with_columns(512).angle_grid(),
        device,
    )
}

fn plain(cfg: &GeneratorConfig, batch: usize, reps: usize, backward: bool) -> (Vec<f64>, Vec<f64>) {
    let device = if backward {
        Device::flex().autodiff()
    } else {
        Device::flex()
    };
    let g = cfg.init(&device);
    let grid = grid(&g, &device);
    let mut rng = Rng::new(1);
    let d_w = g.d_w();
    times(reps, || {
        let w = rng.normal_tensor([batch, d_w], &device);
        let w = if backward { w.require_grad() } else { w };
        let out = g.render(w.clone(), &grid, None);
        let loss = out.x_d.sum() + out.keep_logit.sum();
        if backward {
            let grads = loss.backward();
            sync(w.grad(&grads).expect("grad").sum());
        } else {
            sync(loss);
        }
    })
}

fn inversion(cfg: &GeneratorConfig, reps: usize, tune_weights: bool) -> (Vec<f64>, Vec<f64>) {
    let device = Device::flex().autodiff();
    let g = cfg.init(&device);
    let grid = grid(&g, &device);
    let mut rng = Rng::new(2);
    let target = rng.normal_tensor([1, 1, grid.height, grid.width], &device);
    let w = rng.normal_tensor([1, g.d_w()], &device);
    let g = if tune_weights { g } else { g.no_grad() };
    let mut model = Inversion {
        g,
        w: Param::from_tensor(w),
    };
    let mut opt = AdamConfig::new().with_beta_1(0.9).with_beta_2(0.999).init();
    let lr = if tune_weights { 5e-4 } else { 0.05 };
    times(reps, || {
        let out = model.g.render(model.w.val(), &grid, None);
        let loss = (out.x_d - target.clone()).abs().mean();
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        model = opt.step(lr, model.clone(), grads);
        sync(model.w.val().sum());
    })
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    // `--default-malloc` keeps glibc's default thresholds (for the before/after comparison).
    if !args.iter().any(|a| a == "--default-malloc") {
        rangegan_mcap::model::tune_allocator();
    }
    let reps: usize = arg("--reps").and_then(|r| r.parse().ok()).unwrap_or(3);
    let ops: Vec<String> = arg("--ops")
        .map(|s| s.split(',').map(str::to_string).collect())
        .unwrap_or_else(|| ALL_OPS.iter().map(|s| s.to_string()).collect());
    // `--model DIR` times that model's generator (its `config.json`) instead of the reference size.
    let cfg = match arg("--model") {
        Some(dir) => {
            let text = std::fs::read_to_string(format!("{dir}/config.json")).expect("config.json");
            let json: serde_json::Value = serde_json::from_str(&text).expect("config.json is JSON");
            serde_json::from_value(json["generator"].clone()).expect("a generator config")
        }
        None => GeneratorConfig::new(),
    };
    let mut fields = vec![
        "\"impl\": \"rangegan-mcap (burn flex)\"".to_string(),
        format!("\"threads\": {}", rayon::current_num_threads()),
        format!("\"params\": {}", cfg.init(&Device::flex()).num_params()),
        format!(
            "\"gmac_per_image\": {:.4}",
            cfg.macs_per_image(64, 512) as f64 * 1e-9
        ),
    ];
    for op in &ops {
        let (t, c) = match op.as_str() {
            "fwd_b1" => plain(&cfg, 1, reps, false),
            "fwd_b8" => plain(&cfg, 8, reps, false),
            "fwdbwd_b1" => plain(&cfg, 1, reps, true),
            "fwdbwd_b8" => plain(&cfg, 8, reps, true),
            "inv_w_b1" => inversion(&cfg, reps, false),
            "pti_b1" => inversion(&cfg, reps, true),
            other => panic!("unknown op {other}; known: {ALL_OPS:?}"),
        };
        let list = |v: &[f64]| -> String {
            v.iter()
                .map(|s| format!("{s:.5}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        fields.push(format!("\"{op}\": [{}]", list(&t)));
        fields.push(format!("\"{op}_cpu\": [{}]", list(&c)));
    }
    println!("{{{}}}", fields.join(", "));
}

//! Generator speed on the CPU backends (plain `harness = false` main printing medians).
//!
//! `cargo bench --bench model_backends` (add `-- --quick` for fewer repetitions). Measures, in
//! one run: flex vs ndarray on generator forward+backward at 64x512 batch 8 (reference size and
//! the CPU size), forward and forward+backward at batch 1 and 8, one inversion step (w only,
//! batch 1) at the reference size, candidate CPU sizes for training (G and D fwd+bwd), and the
//! discriminator's full-resolution pieces (`-- --discriminator` for that section alone).

use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use rangegan_mcap::lidar::SensorProfile;
use rangegan_mcap::model::discriminator::DiscriminatorConfig;
use rangegan_mcap::model::generator::{GeneratorConfig, MappingConfig};
use rangegan_mcap::util::rng::Rng;

fn median_secs(reps: usize, mut f: impl FnMut()) -> f64 {
    f(); // warm-up
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(|a, b| a.total_cmp(b));
    t[t.len() / 2]
}

fn sync(x: Tensor<1>) {
    let _ = x.into_data();
}

/// Forward (+ backward when `device` is autodiff) of the generator from w on a cached grid.
fn gen_step(
    cfg: &GeneratorConfig,
    device: &Device,
    batch: usize,
    reps: usize,
    weights_grad: bool,
) -> f64 {
    let g = cfg.init(device);
    let g = if weights_grad { g } else { g.no_grad() };
    let grid = g.prepare(
        &SensorProfile::kitti_hdl64e().with_columns(512).angle_grid(),
        device,
    );
    let mut rng = Rng::new(1);
    let d_w = g.d_w();
    median_secs(reps, || {
        let w = rng.normal_tensor([batch, d_w], device);
        let w = if device.is_autodiff() {
            w.require_grad()
        } else {
            w
        };
        let out = g.render(w.clone(), &grid, None);
        let loss = out.x_d.sum() + out.keep_logit.sum();
        if device.is_autodiff() {
            let grads = loss.backward();
            sync(w.grad(&grads).expect("grad").sum());
        } else {
            sync(loss);
        }
    })
}

fn disc_step(cfg: &DiscriminatorConfig, device: &Device, batch: usize, reps: usize) -> f64 {
    let d = cfg.init(device);
    let mut rng = Rng::new(2);
    median_secs(reps, || {
        let x = rng.normal_tensor([batch, 1, 64, 512], device);
        let loss = d.forward(x).sum();
        let grads = loss.backward();
        sync(d.fc.weight.val().grad(&grads).expect("grad").sum());
    })
}

fn main() {
    rangegan_mcap::model::tune_allocator();
    let quick = std::env::args().any(|a| a == "--quick");
    // `--candidates` runs only the CPU-size section.
    let only_candidates = std::env::args().any(|a| a == "--candidates");
    let reps = if quick { 3 } else { 7 };
    let reference = GeneratorConfig::new();
    let cpu = GeneratorConfig::cpu();
    println!(
        "# model_backends (release, f32, {} threads)",
        rayon::current_num_threads()
    );
    println!(
        "reference: {} params, {:.3} GMAC/image; cpu: {} params, {:.3} GMAC/image",
        reference.init(&Device::flex()).num_params(),
        reference.macs_per_image(64, 512) as f64 * 1e-9,
        cpu.init(&Device::flex()).num_params(),
        cpu.macs_per_image(64, 512) as f64 * 1e-9
    );

    let flex = Device::flex();
    // `--discriminator` runs only the section on the discriminator's pieces.
    if std::env::args().any(|a| a == "--discriminator") {
        discriminator_pieces(&flex.clone().autodiff(), reps);
        return;
    }
    if !only_candidates {
        backend_and_speed_sections(&reference, &cpu, reps);
    }
    candidate_section(&flex, reps);
    discriminator_pieces(&flex.clone().autodiff(), reps);
}

/// Forward + backward of `f` on a fixed random `[batch, ch, H, W]` input.
fn op_step(
    device: &Device,
    dims: [usize; 4],
    reps: usize,
    f: impl Fn(Tensor<4>) -> Tensor<4>,
) -> f64 {
    let x0 = Rng::new(3).normal_tensor(dims, device);
    median_secs(reps, || {
        let x = x0.clone().detach().require_grad();
        let grads = f(x.clone()).sum().backward();
        sync(x.grad(&grads).expect("grad").sum());
    })
}

/// Where the discriminator's time goes at the shipped CPU size (it is ~3/4 of a training
/// step): its full-resolution pieces, forward + backward, batch 8.
fn discriminator_pieces(device: &Device, reps: usize) {
    use burn::tensor::module::conv2d;
    use burn::tensor::ops::ConvOptions;
    use rangegan_mcap::model::conv::{downsample2x, pad_circular};
    let big = [8, 8, 64, 512];
    let weight = Rng::new(6).normal_tensor([8, 8, 3, 3], device);
    let conv = |x: Tensor<4>| {
        conv2d(
            x,
            weight.clone(),
            None,
            ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
        )
    };
    println!("\n## discriminator pieces (flex, fwd+bwd, batch 8, 64x512), median s");
    println!("| piece | s |");
    println!("|---|---|");
    let d = DiscriminatorConfig::cpu();
    println!(
        "| whole D, CPU size | {:.3} |",
        disc_step(&d, device, 8, reps)
    );
    println!(
        "| 3x3 conv 8->8 channels | {:.3} |",
        op_step(device, [8, 8, 66, 514], reps, conv)
    );
    println!(
        "| blur-downsampling {big:?} | {:.3} |",
        op_step(device, big, reps, downsample2x)
    );
    println!(
        "| circular padding {big:?} | {:.3} |",
        op_step(device, big, reps, |x| pad_circular(x, 1))
    );
}

fn backend_and_speed_sections(reference: &GeneratorConfig, cpu: &GeneratorConfig, reps: usize) {
    println!("\n## flex vs ndarray, generator fwd+bwd (w and weights), 64x512, batch 8, median s");
    println!("| size | flex | ndarray |");
    println!("|---|---|---|");
    #[allow(deprecated)]
    let backends = [("flex", Device::flex()), ("ndarray", Device::ndarray())];
    for (name, cfg) in [("reference", reference), ("cpu", cpu)] {
        let r = if name == "reference" {
            reps.min(3)
        } else {
            reps
        };
        let t: Vec<f64> = backends
            .iter()
            .map(|(_, dev)| gen_step(cfg, &dev.clone().autodiff(), 8, r, true))
            .collect();
        println!("| {name} | {:.3} | {:.3} |", t[0], t[1]);
    }

    println!("\n## flex, generator, 64x512, median s per call (images/s)");
    println!("| size | fwd b1 | fwd b8 | fwd+bwd b1 | fwd+bwd b8 |");
    println!("|---|---|---|---|---|");
    let flex = Device::flex();
    for (name, cfg) in [("reference", reference), ("cpu", cpu)] {
        let f1 = gen_step(cfg, &flex, 1, reps, false);
        let f8 = gen_step(cfg, &flex, 8, reps.min(5), false);
        let b1 = gen_step(cfg, &flex.clone().autodiff(), 1, reps, true);
        let b8 = gen_step(cfg, &flex.clone().autodiff(), 8, reps.min(3), true);
        println!(
            "| {name} | {f1:.3} ({:.1}) | {f8:.3} ({:.1}) | {b1:.3} ({:.1}) | {b8:.3} ({:.1}) |",
            1.0 / f1,
            8.0 / f8,
            1.0 / b1,
            8.0 / b8
        );
    }

    println!("\n## inversion step (fwd + bwd to w only, batch 1, cached grid), median s");
    let inv = gen_step(reference, &flex.clone().autodiff(), 1, reps, false);
    let pti = gen_step(reference, &flex.clone().autodiff(), 1, reps, true);
    println!("| reference, w only | {inv:.3} |");
    println!("| reference, w + all weights (PTI) | {pti:.3} |");
}

fn candidate_section(flex: &Device, reps: usize) {
    println!("\n## candidate CPU sizes for training (flex, fwd+bwd, batch 8), median s");
    println!("| generator channels / n_freq | params | GMAC/img | G fwd+bwd | D | D fwd+bwd |");
    println!("|---|---|---|---|---|---|");
    let candidates = [
        (vec![256, 128, 64, 32, 16], vec![128, 128, 64, 64, 32], 256),
        (vec![128, 128, 64, 32, 16], vec![64, 64, 64, 32, 32], 128),
        (vec![128, 64, 32, 16, 16], vec![64, 64, 32, 32, 16], 128),
    ];
    let dcands = [
        vec![16, 32, 64, 128, 128],
        vec![8, 16, 32, 64, 128],
        vec![8, 16, 32, 64, 64],
    ];
    for (ch, nf, dw) in candidates {
        let cfg = GeneratorConfig::new()
            .with_mapping(MappingConfig::new().with_d_z(dw).with_d_w(dw))
            .with_channels(ch.clone())
            .with_n_freq(nf.clone());
        let t = gen_step(&cfg, &flex.clone().autodiff(), 8, reps.min(3), true);
        println!(
            "| {ch:?} / {nf:?} (w {dw}) | {} | {:.3} | {t:.3} | | |",
            cfg.init(flex).num_params(),
            cfg.macs_per_image(64, 512) as f64 * 1e-9
        );
    }
    for dc in dcands {
        let cfg = DiscriminatorConfig::new().with_channels(dc.clone());
        let t = disc_step(&cfg, &flex.clone().autodiff(), 8, reps.min(3));
        println!(
            "| | | | | {dc:?} ({} params) | {t:.3} |",
            cfg.init(flex).num_params()
        );
    }
}

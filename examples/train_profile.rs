//! Where one GAN training step's time goes, at the shipped CPU size, 64 x 512, batch 8:
//! generator forward+backward, discriminator forward+backward, and the discriminator's
//! padding / blur-downsampling pieces on their own. Medians of `--reps` runs (default 5).
//!
//!     cargo run --release --example train_profile [-- --reps 5 --batch 8]

use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use rangegan_mcap::lidar::SensorProfile;
use rangegan_mcap::model::discriminator::{DiscriminatorConfig, downsample2x, pad_circular};
use rangegan_mcap::model::generator::GeneratorConfig;
use rangegan_mcap::model::layers::roll;
use rangegan_mcap::model::rng::Rng;

fn median_secs(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
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

/// Forward + backward of `f` on a random `[batch, ch, H, W]` input.
fn op(device: &Device, dims: [usize; 4], reps: usize, f: impl Fn(Tensor<4>) -> Tensor<4>) -> f64 {
    let x0 = Rng::new(3).normal_tensor(dims, device);
    median_secs(reps, || {
        let x = x0.clone().detach().require_grad();
        let grads = f(x.clone()).sum().backward();
        sync(x.grad(&grads).expect("grad").sum());
    })
}

/// Index tensor for `select`.
fn index(v: Vec<i64>, device: &Device) -> Tensor<1, burn::tensor::Int> {
    let n = v.len();
    Tensor::from_data(burn::tensor::TensorData::new(v, [n]), device)
}

fn pad_select(x: Tensor<4>, p: usize) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    let dev = x.device();
    let cols = (0..w + 2 * p).map(|j| ((j + w - p) % w) as i64).collect();
    let rows = (0..h + 2 * p)
        .map(|i| (i as i64 - p as i64).clamp(0, h as i64 - 1))
        .collect();
    x.select(3, index(cols, &dev)).select(2, index(rows, &dev))
}

fn downsample_conv(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let dev = x.device();
    let taps = [1.0f32, 3.0, 3.0, 1.0];
    let k: Vec<f32> = taps
        .iter()
        .flat_map(|a| taps.iter().map(move |b| a * b / 64.0))
        .collect();
    let k = Tensor::<4>::from_data(burn::tensor::TensorData::new(k, [1, 1, 4, 4]), &dev);
    let x = pad_circular(x.reshape([b * c, 1, h, w]), 1);
    let y = burn::tensor::module::conv2d(
        x,
        k,
        None,
        burn::tensor::ops::ConvOptions::new([2, 2], [0, 0], [1, 1], 1),
    );
    y.reshape([b, c, h / 2, w / 2])
}

fn main() {
    rangegan_mcap::model::tune_allocator();
    let mut reps = 5;
    let mut batch = 8;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let v: usize = args.next().and_then(|v| v.parse().ok()).expect("a number");
        match a.as_str() {
            "--reps" => reps = v,
            "--batch" => batch = v,
            _ => panic!("unknown flag {a}"),
        }
    }
    let device = Device::flex().autodiff();
    let grid = SensorProfile::kitti_hdl64e().with_columns(512).angle_grid();
    let g = GeneratorConfig::cpu().init(&device);
    let cache = g.prepare(&grid, &device);
    let mut rng = Rng::new(1);
    let g_s = median_secs(reps, || {
        let z = rng.normal_tensor([batch, g.d_z()], &device);
        let w = g.mapping.forward(z);
        let out = g.render(w, &cache, None);
        let grads = (out.x_d.sum() + out.keep_logit.sum()).backward();
        sync(
            g.blocks[0]
                .conv0
                .weight
                .val()
                .grad(&grads)
                .expect("grad")
                .sum(),
        );
    });
    let d = DiscriminatorConfig::cpu().init(&device);
    let d_s = median_secs(reps, || {
        let x = rng.normal_tensor([batch, 1, 64, 512], &device);
        let grads = d.forward(x).sum().backward();
        sync(d.fc.weight.val().grad(&grads).expect("grad").sum());
    });
    let d_fwd = median_secs(reps, || {
        let x = rng.normal_tensor([batch, 1, 64, 512], &Device::flex());
        let _ = d.valid().forward(x).into_data();
    });
    let big = [batch, 8, 64, 512];
    println!("batch {batch}, reps {reps} (seconds, median)");
    println!("G fwd+bwd            {g_s:.3}");
    println!("D fwd+bwd            {d_s:.3}");
    println!("D fwd (no autodiff)  {d_fwd:.3}");
    println!(
        "pad_circular {big:?} fwd+bwd {:.3}",
        op(&device, big, reps, |x| pad_circular(x, 1))
    );
    println!(
        "downsample2x {big:?} fwd+bwd {:.3}",
        op(&device, big, reps, downsample2x)
    );
    println!(
        "roll W       {big:?} fwd+bwd {:.3}",
        op(&device, big, reps, |x| roll(x, 1, 3))
    );
    println!(
        "pad_select   {big:?} fwd+bwd {:.3}",
        op(&device, big, reps, |x| pad_select(x, 1))
    );
    println!(
        "downsample_conv {big:?} fwd+bwd {:.3}",
        op(&device, big, reps, downsample_conv)
    );
    let a = downsample2x(Rng::new(5).normal_tensor(big, &Device::flex()));
    let b = downsample_conv(Rng::new(5).normal_tensor(big, &Device::flex()));
    println!(
        "downsample_conv - downsample2x max |diff| {}",
        (a - b).abs().max().into_scalar::<f32>()
    );
    let conv = burn::tensor::module::conv2d;
    let wt = Rng::new(6).normal_tensor([8, 8, 3, 3], &device);
    println!(
        "conv3x3 8->8 (pre-padded) fwd+bwd {:.3}",
        op(&device, [batch, 8, 66, 514], reps, |x| conv(
            x,
            wt.clone(),
            None,
            burn::tensor::ops::ConvOptions::new([1, 1], [0, 0], [1, 1], 1)
        ))
    );
    println!(
        "mul_scalar   {big:?} fwd+bwd {:.3}",
        op(&device, big, reps, |x| x.mul_scalar(2.0))
    );
}

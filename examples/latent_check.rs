//! Where a reconstruction-assisted run's in-loop encoder puts real scans in w space, beside
//! where the mapping network puts random latents: if the two clouds do not overlap, the
//! generator learns to render real scans from latents its prior never draws, and its samples
//! cannot look like them however well it reconstructs. Prints the two clouds' statistics and
//! writes renderings from both (x_d, then the real scans) to a PNG.
//!
//! ```text
//! cargo run --release --example latent_check -- RUN_DIR DATASET_CACHE OUT.png
//! ```

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::module::Module;
use burn::tensor::{Device, Tensor};
use rangegan_mcap::decode::amortised::EncoderConfig;
use rangegan_mcap::model::AnyGenerator;
use rangegan_mcap::model::data::RangeDataset;
use rangegan_mcap::model::weights::Model;
use rangegan_mcap::train::write_png;
use rangegan_mcap::util::rng::Rng;
use rangegan_mcap::util::tensor::{tensor_from, tensor_to_vec};

/// Per-dimension mean and standard deviation of `n` rows of `d` values.
fn moments(w: &[f32], d: usize) -> (Vec<f64>, Vec<f64>) {
    let n = (w.len() / d).max(1) as f64;
    let mut mean = vec![0.0; d];
    for row in w.chunks(d) {
        row.iter()
            .zip(&mut mean)
            .for_each(|(v, m)| *m += f64::from(*v) / n);
    }
    let mut var = vec![0.0; d];
    for row in w.chunks(d) {
        for ((v, m), s) in row.iter().zip(&mean).zip(&mut var) {
            *s += (f64::from(*v) - m).powi(2) / n;
        }
    }
    (mean, var.into_iter().map(f64::sqrt).collect())
}

/// Mean distance from each row of `a` to its nearest row of `b` (skipping itself when `a` is `b`).
fn nearest(a: &[f32], b: &[f32], d: usize, same: bool) -> f64 {
    let rows = a.chunks(d).enumerate().map(|(i, x)| {
        b.chunks(d)
            .enumerate()
            .filter(|(j, _)| !(same && *j == i))
            .map(|(_, y)| x.iter().zip(y).map(|(p, q)| (p - q).powi(2)).sum::<f32>())
            .fold(f32::INFINITY, f32::min)
            .sqrt() as f64
    });
    let n = a.len() / d;
    rows.sum::<f64>() / n.max(1) as f64
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [run, cache, out] = args.as_slice() else {
        bail!("usage: latent_check RUN_DIR DATASET_CACHE OUT.png");
    };
    let run = PathBuf::from(run);
    let device = Device::flex();
    let model = Model::from_dir(&run, &device)?;
    let AnyGenerator::Implicit(g) = &model.generator else {
        bail!("the run's generator is not the implicit one");
    };
    let data = RangeDataset::load(&PathBuf::from(cache))?;
    let (h, w) = (data.height, data.width);
    let d_w = g.d_w();
    let encoder = EncoderConfig::new()
        .with_height(h)
        .with_width(w)
        .with_d_w(d_w)
        .init(&device)
        .try_load_file(run.join("checkpoint").join("e.bpk"))
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("the run's in-loop encoder")?;
    let n = 128.min(data.len());
    let step = data.len() / n;
    let reals: Vec<f32> = (0..n).flat_map(|i| data.image(i * step).to_vec()).collect();
    let x = tensor_from(reals.clone(), [n, 1, h, w], &device);
    let mask = x.clone().greater_elem(-1.0 + 1e-4).float();
    let w_avg = g.mapping.w_avg.val().unsqueeze_dim::<2>(0); // [1, d_w]
    let w_real = encoder.forward(x, mask) + w_avg.clone(); // [n, d_w]
    let z = Rng::new(7).normal_tensor([n, g.d_z()], &device);
    let w_fake = g.mapping.forward(z); // [n, d_w]
    let (wr, wf) = (tensor_to_vec(w_real.clone()), tensor_to_vec(w_fake.clone()));
    let avg = tensor_to_vec(w_avg);
    let radius = |v: &[f32]| {
        v.chunks(d_w)
            .map(|r| {
                r.iter()
                    .zip(&avg)
                    .map(|(a, b)| (a - b).powi(2))
                    .sum::<f32>()
                    .sqrt() as f64
            })
            .sum::<f64>()
            / n as f64
    };
    let ((mr, sr), (mf, sf)) = (moments(&wr, d_w), moments(&wf, d_w));
    let mean_gap = mr
        .iter()
        .zip(&mf)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt();
    let spread = |s: &[f64]| s.iter().sum::<f64>() / d_w as f64;
    let frechet_diag: f64 = mr
        .iter()
        .zip(&mf)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        + sr.iter()
            .zip(&sf)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>();
    println!("{n} real scans encoded, {n} latents mapped, d_w {d_w}");
    println!(
        "distance from w_avg: real {:.3}  mapped {:.3}",
        radius(&wr),
        radius(&wf)
    );
    println!(
        "mean spread per dimension: real {:.4}  mapped {:.4}",
        spread(&sr),
        spread(&sf)
    );
    println!("distance between the means {mean_gap:.3}; diagonal Frechet {frechet_diag:.4}");
    println!(
        "nearest-neighbour distance: real->mapped {:.3}  mapped->mapped {:.3}  real->real {:.3}",
        nearest(&wr, &wf, d_w, false),
        nearest(&wf, &wf, d_w, true),
        nearest(&wr, &wr, d_w, true)
    );
    let grid = g.prepare(&data.angles, &device);
    let k = 4.min(n);
    let render = |w: Tensor<2>| tensor_to_vec(g.render(w.narrow(0, 0, k), &grid, None).x_d);
    let (from_real, from_fake) = (render(w_real), render(w_fake));
    let px = h * w;
    let mut rows: Vec<&[f32]> = Vec::new();
    for i in 0..k {
        rows.push(&reals[i * px..(i + 1) * px]);
        rows.push(&from_real[i * px..(i + 1) * px]);
    }
    for i in 0..k {
        rows.push(&from_fake[i * px..(i + 1) * px]);
    }
    write_png(&PathBuf::from(out), &rows, h, w)?;
    println!("wrote {out}: real scan / its reconstruction (x {k}), then {k} samples");
    Ok(())
}

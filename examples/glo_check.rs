//! Can a generator's architecture draw real scans at all? Each of a few real scans gets a
//! latent of its own (as in GLO), and the latents are fitted to the scans together with the
//! generator's weights (one set of weights for every scan, unlike `convert --quality paper`,
//! which tunes a copy per scan). If the fitted renderings show the scans' cars, poles and
//! walls, the architecture has room for them and what keeps them out of the samples is the
//! training signal; if they stay smooth fields, it is the architecture (or the steps given).
//! Fresh generators of either family, fitted for the same steps, show which one learns the
//! scans' detail sooner.
//!
//! ```text
//! cargo run --release --example glo_check -- OUT.png DATASET_CACHE MODEL... [--scans 16] [--steps 300]
//! cargo run --release --example glo_check -- OUT.png heldout:../shared/real_lidar MODEL... # held-out scans
//! ```
//! MODEL: a run or model directory, `fresh-dusty2` (the CPU-size implicit generator) or
//! `fresh-dusty1` (the transposed-convolution generator of the same widths);
//! `fresh-dusty2:freq=F1,...,F5;channels=C1,...,C5;lh=...;lw=...;local=N` sets the implicit
//! generator's Fourier pairs, channels and log2 bandwidths (elevation, azimuth) per block and
//! gives its N finest blocks the local 3x3 path;
//! `DIR:local=N` adds that path to a trained implicit generator. Prints the masked
//! L1 of inverse depth (network units) every 25 steps and the relative depth error at the end,
//! over all returns and at depth edges;
//! the PNG shows, per scan, the real scan, then each model's fit.

use std::path::PathBuf;

use anyhow::{Result, bail};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};
use rangegan_mcap::decode::loss::relative_depth_error;
use rangegan_mcap::lidar::edges::edge_strength;
use rangegan_mcap::model::AnyGenerator;
use rangegan_mcap::model::baseline::ConvGeneratorConfig;
use rangegan_mcap::model::data::DepthRange;
use rangegan_mcap::model::data::{DROPPED, RangeDataset, kitti_heldout_files};
use rangegan_mcap::model::generator::{GeneratorConfig, GridCache};
use rangegan_mcap::model::weights::Model;
use rangegan_mcap::train::reconstruct::returns_l1;
use rangegan_mcap::train::write_png;
use rangegan_mcap::util::adam::Adam;
use rangegan_mcap::util::rng::Rng;
use rangegan_mcap::util::tensor::{tensor_from, tensor_to_vec};

const Z_LR: f32 = 0.02;
const G_LR: f64 = 1e-3;

/// The generator to fit: a trained one, or a fresh one of either family, with the spec's
/// settings (`freq`, `channels`, `lh`, `lw`, `local`) after a colon; a trained one takes
/// only `local`.
fn generator(spec: &str, device: &Device) -> Result<AnyGenerator> {
    let (base, settings) = spec.split_once(':').unwrap_or((spec, ""));
    let mut config = GeneratorConfig::cpu();
    for setting in settings.split(';').filter(|s| !s.is_empty()) {
        let (key, values) = setting
            .split_once('=')
            .ok_or_else(|| anyhow::anyhow!("{setting}: expected KEY=VALUES"))?;
        let values = values
            .split(',')
            .map(str::parse)
            .collect::<Result<Vec<usize>, _>>()?;
        config = match (key, values.as_slice()) {
            ("freq", _) => config.with_n_freq(values),
            ("channels", _) => config.with_channels(values),
            ("lh", _) => config.with_lh(values.iter().map(|&v| v as u32).collect()),
            ("lw", _) => config.with_lw(values.iter().map(|&v| v as u32).collect()),
            ("local", [n]) => config.with_local_blocks(*n),
            _ => bail!(
                "{setting}: expected freq=, channels=, lh=, lw= (one value per block) or local=N"
            ),
        };
    }
    Ok(match base {
        "fresh-dusty2" => AnyGenerator::Implicit(config.init(device)),
        "fresh-dusty1" => AnyGenerator::Conv(ConvGeneratorConfig::cpu(2).init(device)),
        dir => {
            let model = Model::from_dir(&PathBuf::from(dir), device)?;
            match model.generator {
                AnyGenerator::Implicit(g) if config.local_blocks > 0 => {
                    let grown = model
                        .config
                        .generator
                        .with_local_blocks(config.local_blocks);
                    AnyGenerator::Implicit(g.with_local_paths_of(grown.init(device)))
                }
                g => g,
            }
        }
    })
}

/// Fit one latent z per scan and the weights together; the final renderings.
fn fit(
    label: &str,
    g: &AnyGenerator,
    grid: Option<&GridCache>,
    real: &Tensor<4>,
    steps: usize,
    device: &Device,
) -> Vec<f32> {
    let [n, _, _, _] = real.dims();
    let returns = real.clone().greater_elem(DROPPED).float();
    let d_z = g.d_z();
    let mut rng = Rng::new(3);
    let mut z: Vec<f32> = (0..n * d_z).map(|_| rng.normal()).collect();
    let mut adam_z = Adam::new(z.len());
    let mut generator = g.clone().fork(device).train();
    let mut opt = AdamConfig::new().with_epsilon(1e-8).init();
    let render = |generator: &AnyGenerator, z: Tensor<2>| generator.generate(z, grid, None).0.x_d;
    for step in 0..steps {
        let z_t = tensor_from(z.clone(), [n, d_z], device).require_grad();
        let loss = returns_l1(
            render(&generator, z_t.clone()),
            real.clone(),
            returns.clone(),
        );
        if step % 25 == 0 {
            let value = loss.clone().inner().into_scalar::<f32>();
            println!("{label} step {step:4}: L1 {value:.4}");
        }
        let mut grads = loss.backward();
        if let Some(grad) = z_t.grad_remove(&mut grads) {
            adam_z.step(&mut z, &tensor_to_vec(grad), Z_LR);
        }
        let grads = GradientsParams::from_grads(grads, &generator);
        generator = opt.step(G_LR, generator, grads);
    }
    tensor_to_vec(render(&generator, tensor_from(z, [n, d_z], device)))
}

/// Relative depth error on the returns at a depth edge of the observed scans (a 4-neighbour
/// more than 10 % nearer or farther): where objects' outlines are.
fn edge_error(fitted: &[f32], observed: &[f32], width: usize) -> f32 {
    let strength = edge_strength(observed, width);
    let (mut sum, mut n) = (0.0f64, 0usize);
    for k in 0..observed.len() {
        if observed[k] > 0.0 && strength[k] > 0.1f32.ln_1p() {
            sum += ((fitted[k] - observed[k]).abs() / observed[k]) as f64;
            n += 1;
        }
    }
    (sum / n.max(1) as f64) as f32
}

fn main() -> Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut option = |name: &str, default: usize| -> Result<usize> {
        match args.iter().position(|a| a == name) {
            Some(i) if i + 1 < args.len() => {
                let value = args.remove(i + 1).parse()?;
                args.remove(i);
                Ok(value)
            }
            Some(_) => bail!("{name} needs a value"),
            None => Ok(default),
        }
    };
    let n = option("--scans", 16)?;
    let steps = option("--steps", 300)?;
    let [out, cache, models @ ..] = args.as_slice() else {
        bail!("usage: glo_check OUT.png DATASET_CACHE MODEL... [--scans N] [--steps N]");
    };
    if models.is_empty() {
        bail!("name at least one MODEL");
    }
    let device = Device::flex().autodiff();
    // `heldout:DIR`: the held-out KITTI scans under DIR (SemanticKITTI 00 and 07, never trained on).
    let data = match cache.strip_prefix("heldout:") {
        Some(dir) => {
            RangeDataset::from_kitti_files(&kitti_heldout_files(&PathBuf::from(dir))?, 512)?
        }
        None => RangeDataset::load(&PathBuf::from(cache))?,
    };
    let (h, w) = (data.height, data.width);
    let n = n.clamp(1, data.len());
    let every = data.len() / n;
    let reals: Vec<f32> = (0..n)
        .flat_map(|i| data.image(i * every).to_vec())
        .collect();
    let real = tensor_from(reals.clone(), [n, 1, h, w], &device);
    let observed: Vec<f32> = DepthRange::KITTI
        .clamped_depths(&reals)
        .iter()
        .zip(&reals)
        .map(|(d, x)| if *x > DROPPED { *d } else { 0.0 })
        .collect();
    let mut fits = Vec::new();
    for spec in models {
        let g = generator(spec, &device)?;
        let grid = match &g {
            AnyGenerator::Implicit(implicit) => Some(implicit.prepare(&data.angles, &device)),
            AnyGenerator::Conv(_) => None,
        };
        let start = std::time::Instant::now();
        let x = fit(spec, &g, grid.as_ref(), &real, steps, &device);
        let secs = start.elapsed().as_secs_f64();
        let fitted = DepthRange::KITTI.clamped_depths(&x);
        let err = relative_depth_error(&fitted, &observed).unwrap_or(f32::NAN);
        let edges = edge_error(&fitted, &observed, w);
        println!(
            "{spec}: relative depth error {err:.4} over {n} scans, {edges:.4} at depth edges, after {steps} steps ({secs:.0} s)"
        );
        fits.push(x);
    }
    let px = h * w;
    let rows: Vec<&[f32]> = (0..n.min(4))
        .flat_map(|i| {
            std::iter::once(&reals)
                .chain(&fits)
                .map(move |v| &v[i * px..(i + 1) * px])
        })
        .collect();
    write_png(&PathBuf::from(out), &rows, h, w)?;
    println!("wrote {out}: per scan the real scan, then each model's fit");
    Ok(())
}

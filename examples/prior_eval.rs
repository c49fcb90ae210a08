//! How real the generator's samples look, with measures that can see structure. Each model's
//! samples are told apart from real scans by the classifier two-sample test
//! (`model::two_sample`: accuracy and cross-validated log-loss) and compared by the Fréchet
//! distance of the same texture statistics (FTD) and by SWD, beside two references measured
//! in the same run:
//!
//! - real: the training scans are interleaved into two halves; every set is told apart from
//!   one half, and the other half scores what a perfect generator would (about 0.5);
//! - known bad: that other half with its returns 3 x 3-blurred: a measure that does not
//!   score it clearly worse than real scans cannot be trusted.
//!
//! The same sets are also told apart from the held-out scans (the validation drive, and
//! SemanticKITTI 00 and 07), and SWD is reported against each held-out set separately, to
//! show how much it moves with the choice of scans. `diversity` (how much the shapes of a
//! set's scenes differ from each other) shows a generator that draws one scene whatever its
//! latent; its known-bad reference is one scan copied with random shifts and ray drops.
//!
//! ```text
//! cargo run --release --example prior_eval -- [--data ../shared/real_lidar] \
//!     [--validation-drive kitti_raw_drive_d] [--blocks K] [--png FILE] LABEL=MODEL_DIR ...
//! ```
//! `--blocks K` judges the first K synthesis blocks on their own grid (a coarse-to-fine
//! stage), with the real scans point-sampled to it. A MODEL_DIR is a model directory or a
//! training run; `shipped` is the compiled-in model. Prints one JSON object.
//!
//! For a training run whose checkpoint holds the discriminator of that grid, `memorisation`
//! says how well that discriminator tells the training scans it learned on from real scans
//! it never saw: the AUC of its logits on the two (0.5: no better than chance, 1: it knows
//! every training scan), and its mean logit on training, held-out and generated scans.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::module::Module;
use burn::tensor::Device;
use rangegan_mcap::lidar::AngleGrid;
use rangegan_mcap::model::AnyGenerator;
use rangegan_mcap::model::data::{RangeDataset, kitti_heldout_files, kitti_validation_split};
use rangegan_mcap::model::discriminator::{Discriminator, column_azimuths};
use rangegan_mcap::model::generator::Generator;
use rangegan_mcap::model::layers::AngleGridExt;
use rangegan_mcap::model::metrics::{SwdConfig, swd};
use rangegan_mcap::model::sample::{SampleOptions, sample};
use rangegan_mcap::model::two_sample::{
    C2stConfig, C2stReport, blur_returns, c2st, frechet_distance, texture_features,
};
use rangegan_mcap::model::weights::{CHECKPOINT, Model, parse_labelled_model};
use rangegan_mcap::train::growth::{Level, Stage};
use rangegan_mcap::train::write_png;
use rangegan_mcap::train::{TrainState, load_config};
use rangegan_mcap::util::rng::Rng;
use rangegan_mcap::util::tensor::{tensor_from, tensor_to_vec};

#[derive(clap::Parser)]
struct Args {
    #[arg(long, default_value = "../shared/real_lidar")]
    data: PathBuf,
    /// Held-out KITTI raw drives.
    #[arg(long = "validation-drive", default_value = "kitti_raw_drive_d")]
    validation_drives: Vec<String>,
    /// Judge the first K synthesis blocks on their own grid.
    #[arg(long)]
    blocks: Option<usize>,
    /// L2 weight of the two-sample classifier.
    #[arg(long, default_value_t = C2stConfig::default().l2)]
    l2: f64,
    /// Every this many training and validation scans (1: all).
    #[arg(long, default_value_t = 1)]
    frame_stride: usize,
    #[arg(long)]
    png: Option<PathBuf>,
    /// LABEL=MODEL_DIR (or `shipped`).
    #[arg(required = true, value_parser = parse_labelled_model)]
    models: Vec<(String, Option<PathBuf>)>,
}

/// Blocks of the generator this evaluation assumes when no model says otherwise.
const BLOCKS: usize = 5;

/// A set of images on one level's grid.
struct Images {
    h: usize,
    w: usize,
    images: Vec<Vec<f32>>,
}

impl Images {
    /// `data`'s scans sampled at `level`, each at a phase drawn from its index.
    fn real(data: &RangeDataset, level: &Level) -> Images {
        let images = (0..data.len())
            .map(|i| {
                let phase = level.random_phase(&mut Rng::new(i as u64));
                level.sample(data.image(i), data.width, phase)
            })
            .collect();
        Images {
            h: level.height,
            w: level.width,
            images,
        }
    }

    fn features(&self) -> Vec<Vec<f64>> {
        self.images
            .iter()
            .map(|x| texture_features(x, self.h, self.w))
            .collect()
    }

    /// Inverse depth in [0, 1], dropped rays at 0: what the paper's SWD compares.
    fn inverse_depth(&self) -> Vec<Vec<f32>> {
        self.images
            .iter()
            .map(|x| x.iter().map(|v| ((v + 1.0) * 0.5).max(0.0)).collect())
            .collect()
    }
}

/// Blocks per side of the coarse layout [`diversity`] compares.
const LAYOUT_BLOCKS: usize = 16;

/// An image's layout: the mean inverse depth of its returns in each of 16 x 16 blocks (`None`
/// where a block has none), so the drop noise of single pixels does not count as variety.
fn layout(x: &[f32], h: usize, w: usize) -> Vec<Option<f64>> {
    let (bh, bw) = (h.div_ceil(LAYOUT_BLOCKS), w.div_ceil(LAYOUT_BLOCKS));
    let mut sum = vec![(0.0f64, 0usize); LAYOUT_BLOCKS * LAYOUT_BLOCKS];
    for (k, &v) in x.iter().enumerate() {
        if v > 0.0 {
            let cell = &mut sum[(k / w / bh) * LAYOUT_BLOCKS + (k % w) / bw];
            cell.0 += f64::from(v);
            cell.1 += 1;
        }
    }
    sum.iter()
        .map(|&(s, n)| (n > 0).then(|| s / n as f64))
        .collect()
}

/// How much two layouts differ in shape: the mean absolute difference over the blocks where
/// both have returns, after each is shifted to mean zero there. A scene drawn nearer or
/// farther as a whole, or with other blocks emptied by ray drop, is the same scene.
fn layout_distance(a: &[Option<f64>], b: &[Option<f64>]) -> f64 {
    let both: Vec<(f64, f64)> = a
        .iter()
        .zip(b)
        .filter_map(|(x, y)| Some(((*x)?, (*y)?)))
        .collect();
    if both.is_empty() {
        return 0.0;
    }
    let n = both.len() as f64;
    let (ma, mb) = both
        .iter()
        .fold((0.0, 0.0), |(p, q), (x, y)| (p + x / n, q + y / n));
    both.iter()
        .map(|(x, y)| ((x - ma) - (y - mb)).abs())
        .sum::<f64>()
        / n
}

/// Mean [`layout_distance`] of image `i` and image `i + n/2` of a set: how much its scenes
/// differ from each other. A collapsed generator draws nearly the same scene whatever its
/// latent and scores near the collapsed reference, far below real scans (pairs half a set
/// apart are other places).
fn diversity(set: &Images) -> f64 {
    let layouts: Vec<Vec<Option<f64>>> = set
        .inverse_depth()
        .iter()
        .map(|x| layout(x, set.h, set.w))
        .collect();
    let half = layouts.len() / 2;
    let total: f64 = (0..half)
        .map(|i| layout_distance(&layouts[i], &layouts[i + half]))
        .sum();
    total / half.max(1) as f64
}

/// What a fully collapsed generator draws: one scan, copied `n` times, each copy nearer or
/// farther as a whole (up to 0.05 network units) and with 15 % more of its rays dropped.
fn collapsed(scan: &[f32], n: usize, h: usize, w: usize) -> Images {
    let images = (0..n)
        .map(|i| {
            let mut rng = Rng::new(1000 + i as u64);
            let shift = (rng.uniform() - 0.5) * 0.1;
            scan.iter()
                .map(|&v| {
                    let dropped = v <= -1.0 || rng.uniform() < 0.15;
                    if dropped { -1.0 } else { (v + shift).min(1.0) }
                })
                .collect()
        })
        .collect();
    Images { h, w, images }
}

fn slices(v: &[Vec<f32>]) -> Vec<&[f32]> {
    v.iter().map(|x| x.as_slice()).collect()
}

/// `model`'s EMA generator cut to its first `blocks` blocks, sampled `n` times on `level`.
fn samples(
    mut model: Model,
    level: &Level,
    full: &AngleGrid,
    n: usize,
    device: &Device,
) -> Result<Images> {
    let mut grid = full.clone();
    for _ in 0..level.factor.trailing_zeros() {
        grid = grid.downsample2x();
    }
    if let AnyGenerator::Implicit(g) = &model.generator {
        model.generator = AnyGenerator::Implicit(Generator {
            mapping: g.mapping.clone(),
            blocks: g.blocks[..level.blocks.min(g.blocks.len())].to_vec(),
            output_gain: g.output_gain,
        });
    } else if level.factor > 1 {
        bail!("--blocks needs an implicit (dusty2) generator");
    }
    let opts = SampleOptions {
        n,
        seed: 1,
        truncation: 1.0,
        grid: Some(grid),
    };
    let images = sample(&model, &opts, device)?
        .iter()
        .map(|s| {
            s.x_d
                .iter()
                .zip(&s.mask)
                .map(|(x, &m)| if m { 2.0 * x - 1.0 } else { -1.0 })
                .collect()
        })
        .collect();
    Ok(Images {
        h: level.height,
        w: level.width,
        images,
    })
}

/// Logits of `d` on `set`, in batches of `batch` (its minibatch-stddev groups see one set).
/// A discriminator of windows (`window` columns) scores each scan by its mean over the
/// windows that tile the turn.
fn logits(
    d: &Discriminator,
    set: &Images,
    batch: usize,
    window: Option<usize>,
    device: &Device,
) -> Vec<f32> {
    let width = window.unwrap_or(set.w);
    let starts: Vec<usize> = (0..set.w / width).map(|k| k * width).collect();
    set.images
        .chunks(batch)
        .filter(|c| c.len() == batch)
        .flat_map(|chunk| {
            let mut sum = vec![0.0f32; batch];
            for &start in &starts {
                let v: Vec<f32> = (chunk.iter())
                    .flat_map(|image| {
                        image
                            .chunks_exact(set.w)
                            .flat_map(move |row| row[start..start + width].iter().copied())
                    })
                    .collect();
                let x = tensor_from(v, [batch, 1, set.h, width], device);
                let azimuth =
                    window.map(|_| column_azimuths(&vec![start; batch], width, set.w, device));
                let logits = tensor_to_vec(d.forward_at(x, azimuth));
                sum.iter_mut().zip(logits).for_each(|(s, l)| *s += l);
            }
            let n = starts.len() as f32;
            sum.into_iter().map(move |s| s / n)
        })
        .collect()
}

/// Probability that a random `a` scores above a random `b` (ties count half).
fn auc(a: &[f32], b: &[f32]) -> f64 {
    let above: f64 = a
        .iter()
        .map(|x| {
            b.iter()
                .map(|y| match x.partial_cmp(y) {
                    Some(std::cmp::Ordering::Greater) => 1.0,
                    Some(std::cmp::Ordering::Equal) => 0.5,
                    _ => 0.0,
                })
                .sum::<f64>()
        })
        .sum();
    above / (a.len() * b.len()).max(1) as f64
}

/// The run's discriminator on training, held-out and generated scans, where `dir` is a
/// training run whose checkpoint's discriminator judges `level`'s grid.
fn memorisation(
    dir: &Path,
    level: &Level,
    sets: [&Images; 3],
    device: &Device,
) -> Result<Option<serde_json::Value>> {
    let ck = dir.join(CHECKPOINT);
    if !ck.join("d.bpk").exists() {
        return Ok(None);
    }
    let config = load_config(&dir.join("config.json"))?;
    let state: TrainState = serde_json::from_str(&std::fs::read_to_string(ck.join("state.json"))?)?;
    let stage = state.stage;
    let full = stage >= config.stages.len();
    if full != (level.factor == 1) {
        return Ok(None);
    }
    let d = config
        .discriminator_of(stage)
        .clone()
        .with_height(level.height)
        .with_width(config.window.unwrap_or(level.width))
        .with_azimuth_input(config.window.is_some())
        .init(device)
        .try_load_file(ck.join("d.bpk"))
        .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", ck.display()))?;
    let batch = config.batch_size.clamp(1, 8);
    let [train, heldout, generated] = sets.map(|s| logits(&d, s, batch, config.window, device));
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    Ok(Some(serde_json::json!({
        "auc_training_vs_heldout": auc(&train, &heldout),
        "auc_heldout_vs_generated": auc(&heldout, &generated),
        "mean_logit": {"training": mean(&train), "heldout": mean(&heldout), "generated": mean(&generated)},
    })))
}

fn main() -> Result<()> {
    let args = <Args as clap::Parser>::parse();
    let device = Device::flex();
    let (train_files, validation_files) =
        kitti_validation_split(&args.data, &args.validation_drives)?;
    let every = |files: Vec<PathBuf>| -> Vec<PathBuf> {
        files
            .into_iter()
            .step_by(args.frame_stride.max(1))
            .collect()
    };
    let (train_files, validation_files) = (every(train_files), every(validation_files));
    let train = RangeDataset::from_kitti_files(&train_files, 512)?;
    let full_angles = train.angles.clone();
    let validation = RangeDataset::from_kitti_files(&validation_files, 512)?;
    let mini = RangeDataset::from_kitti_files(&kitti_heldout_files(&args.data)?, 512)?;
    let blocks = args.blocks.unwrap_or(BLOCKS).clamp(1, BLOCKS);
    let level = Level::of(
        &[Stage::new(blocks, 1)],
        0,
        BLOCKS,
        train.height,
        train.width,
    );
    let train = Images::real(&train, &level);
    let heldout_sets = [
        ("validation drives", Images::real(&validation, &level)),
        ("semantickitti 00+07", Images::real(&mini, &level)),
    ];
    let heldout = Images {
        h: level.height,
        w: level.width,
        images: heldout_sets
            .iter()
            .flat_map(|(_, s)| s.images.clone())
            .collect(),
    };
    let heldout_features = heldout.features();
    let c2st_cfg = C2stConfig {
        l2: args.l2,
        ..C2stConfig::default()
    };
    let swd_cfg = SwdConfig::default();
    // The training scans, interleaved into two halves: A stands in for a perfect generator
    // (fresh scans of the training distribution), B is what every set is told apart from.
    let half = |parity: usize| Images {
        h: level.height,
        w: level.width,
        images: train
            .images
            .iter()
            .skip(parity)
            .step_by(2)
            .cloned()
            .collect(),
    };
    let (train_a, train_b) = (half(0), half(1));
    let train_b_features = train_b.features();
    let blurred = Images {
        h: level.height,
        w: level.width,
        images: train_a
            .images
            .iter()
            .map(|x| blur_returns(x, level.height, level.width))
            .collect(),
    };
    let judge = |label: &str, set: &Images| -> serde_json::Value {
        let features = set.features();
        let vs_training: C2stReport = c2st(&features, &train_b_features, &c2st_cfg);
        let vs_heldout: C2stReport = c2st(&features, &heldout_features, &c2st_cfg);
        let ftd = frechet_distance(&features, &train_b_features, &train_b_features);
        let ftd_heldout = frechet_distance(&features, &heldout_features, &train_b_features);
        let swd_by_set: Vec<serde_json::Value> = heldout_sets
            .iter()
            .map(|(name, held)| {
                let (a, b) = (set.inverse_depth(), held.inverse_depth());
                let d = swd(&slices(&a), &slices(&b), set.h, set.w, &swd_cfg);
                serde_json::json!({ "heldout": name, "swd": d.iter().sum::<f64>() / d.len() as f64 })
            })
            .collect();
        serde_json::json!({
            "label": label, "c2st_vs_training": vs_training, "c2st_vs_heldout": vs_heldout,
            "ftd_vs_training": ftd, "ftd_vs_heldout": ftd_heldout,
            "swd_vs_heldout": swd_by_set, "diversity": diversity(set),
        })
    };
    let mut rows = vec![
        judge("real training scans, other half (reference)", &train_a),
        judge("3x3-blurred training scans (known bad)", &blurred),
        judge(
            "one training scan, copied (known bad: collapsed)",
            &collapsed(
                &train_a.images[0],
                train_a.images.len(),
                level.height,
                level.width,
            ),
        ),
    ];
    // The picture: per model 8 samples, then 4 held-out real scans, rendered the same way.
    let mut picture: Vec<Vec<f32>> = Vec::new();
    for (label, dir) in &args.models {
        let model = Model::load(dir.as_deref(), &device).with_context(|| label.clone())?;
        let source = model.source.clone();
        let set = samples(model, &level, &full_angles, train_a.images.len(), &device)?;
        picture.extend(set.images.iter().take(8).cloned());
        let mut row = judge(label, &set);
        row["model"] = source.into();
        if let Some(dir) = dir
            && let Some(m) = memorisation(dir, &level, [&train, &heldout, &set], &device)?
        {
            row["memorisation"] = m;
        }
        rows.push(row);
    }
    let n = heldout.images.len();
    picture.extend((0..4).map(|i| heldout.images[i * n / 4].clone()));
    if let Some(png) = &args.png {
        let refs: Vec<&[f32]> = picture.iter().map(|p| p.as_slice()).collect();
        write_png(png, &refs, level.height, level.width)?;
    }
    println!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({
            "grid": [level.height, level.width],
            "blocks": level.blocks,
            "heldout_images": heldout.images.len(),
            "training_images_per_half": train_b.images.len(),
            "validation_drives": args.validation_drives,
            "results": rows,
        }))?
    );
    Ok(())
}

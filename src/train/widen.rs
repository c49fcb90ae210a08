//! Function-preserving widening of a trained DUSty v2 generator (Net2Net's "wider" step,
//! with zeros instead of copies): more channels per synthesis block, more Fourier pairs, the
//! same function at the first step, so a run that has stopped improving at one width goes
//! on at a larger one without starting over.
//!
//! Every layer keeps its trained weights for its old inputs and outputs. A new output channel
//! starts with fresh random weights; every old output reads the new inputs through zeros, so
//! nothing it computes changes. Zeros go only where old outputs read new inputs: a new
//! output row of zeros would have no direction to grow in after demodulation. The zeros
//! still get gradients (their inputs are not zero), so the new channels join in as training
//! goes on.
//!
//! [`widen_run`] applies this to a run directory: the widened generator and its EMA, the
//! same discriminator, encoder and training state, and a fresh Adam state for the generator
//! (its shapes changed), so the run resumes at the images it had seen.

use std::path::Path;

use anyhow::{Context, Result, bail, ensure};
use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use crate::model::AnyGenerator;
use crate::model::generator::{Generator, GeneratorConfig, SynthesisBlock};
use crate::model::layers::{EqualLinear, FourierFeatures, ModulatedLinear, fixed_param};
use crate::util::tensor::{tensor_from, tensor_to_vec};

use super::config::{TrainState, load_config};
use super::run_dir::{CHECKPOINT, log_through, read_state, write_checkpoint};

/// How one axis of a weight grows: consecutive segments, each `(old, new)` long, whose first
/// `old` entries are the trained ones.
#[derive(Debug, Clone)]
struct Layout(Vec<(usize, usize)>);

impl Layout {
    fn same(n: usize) -> Self {
        Layout(vec![(n, n)])
    }

    fn grown(old: usize, new: usize) -> Self {
        Layout(vec![(old, new)])
    }

    fn new_len(&self) -> usize {
        self.0.iter().map(|&(_, n)| n).sum()
    }

    /// For each new index, the old index it carries, if any.
    fn sources(&self) -> Vec<Option<usize>> {
        let mut out = Vec::with_capacity(self.new_len());
        let mut old_start = 0;
        for &(old, new) in &self.0 {
            out.extend((0..new).map(|i| (i < old).then_some(old_start + i)));
            old_start += old;
        }
        out
    }
}

/// `[new rows, new cols]`: trained rows keep their trained columns (times `scale`) and read
/// new columns through zeros; new rows are `fresh`'s.
fn widen_matrix(
    old: Tensor<2>,
    fresh: Tensor<2>,
    rows: &Layout,
    cols: &Layout,
    scale: f32,
) -> Tensor<2> {
    let device = fresh.device();
    let [_, old_cols] = old.dims();
    let [n_rows, n_cols] = fresh.dims();
    let (old, mut out) = (tensor_to_vec(old), tensor_to_vec(fresh));
    let col_sources = cols.sources();
    for (r, source) in rows.sources().into_iter().enumerate() {
        let Some(old_r) = source else { continue };
        let row = &mut out[r * n_cols..(r + 1) * n_cols];
        for (value, col) in row.iter_mut().zip(&col_sources) {
            *value = col.map_or(0.0, |c| old[old_r * old_cols + c] * scale);
        }
    }
    tensor_from(out, [n_rows, n_cols], &device)
}

/// Trained entries at their new places, `fresh`'s elsewhere.
fn widen_vector(old: Tensor<1>, fresh: Tensor<1>, layout: &Layout) -> Tensor<1> {
    let device = fresh.device();
    let (old, mut out) = (tensor_to_vec(old), tensor_to_vec(fresh));
    for (value, source) in out.iter_mut().zip(layout.sources()) {
        if let Some(i) = source {
            *value = old[i];
        }
    }
    let n = out.len();
    tensor_from(out, [n], &device)
}

fn trainable<const D: usize>(x: Tensor<D>) -> Param<Tensor<D>> {
    Param::from_tensor(x)
}

/// A style affine (`w -> s`, one row per input channel of its layer).
fn widen_affine(old: EqualLinear, fresh: EqualLinear, inputs: &Layout) -> EqualLinear {
    let styles = Layout::same(fresh.weight.dims()[1]);
    EqualLinear {
        weight: trainable(widen_matrix(
            old.weight.val(),
            fresh.weight.val(),
            inputs,
            &styles,
            1.0,
        )),
        bias: trainable(widen_vector(old.bias.val(), fresh.bias.val(), inputs)),
        ..fresh
    }
}

/// A modulated layer. The stored weight is scaled by `1/sqrt(inputs)` at run time, so the
/// trained entries are rescaled to keep their effective value.
fn widen_modulated(
    old: ModulatedLinear,
    fresh: ModulatedLinear,
    inputs: &Layout,
    outputs: &Layout,
) -> ModulatedLinear {
    let scale = old.weight_gain / fresh.weight_gain;
    ModulatedLinear {
        weight: trainable(widen_matrix(
            old.weight.val(),
            fresh.weight.val(),
            outputs,
            inputs,
            scale,
        )),
        bias: trainable(widen_vector(old.bias.val(), fresh.bias.val(), outputs)),
        affine: widen_affine(old.affine, fresh.affine, inputs),
        ..fresh
    }
}

/// The trained frequencies first, then `fresh`'s new ones.
fn widen_fourier(old: FourierFeatures, fresh: FourierFeatures) -> FourierFeatures {
    let layout = Layout::grown(old.n_freq(), fresh.n_freq());
    let widen = |o: &Param<Tensor<1>>, f: &Param<Tensor<1>>| {
        fixed_param(widen_vector(o.val(), f.val(), &layout))
    };
    FourierFeatures {
        b_phi: widen(&old.b_phi, &fresh.b_phi),
        b_theta: widen(&old.b_theta, &fresh.b_theta),
        phase: widen(&old.phase, &fresh.phase),
    }
}

fn widen_block(old: SynthesisBlock, fresh: SynthesisBlock, prev: (usize, usize)) -> SynthesisBlock {
    let (f_old, f_new) = (old.fourier.n_freq(), fresh.fourier.n_freq());
    let (c_old, c_new) = (old.conv1.weight.dims()[0], fresh.conv1.weight.dims()[0]);
    let conv0_in = Layout(vec![prev, (f_old, f_new), (f_old, f_new)]);
    let channels = Layout::grown(c_old, c_new);
    SynthesisBlock {
        fourier: widen_fourier(old.fourier, fresh.fourier),
        conv0: widen_modulated(old.conv0, fresh.conv0, &conv0_in, &channels),
        conv1: widen_modulated(old.conv1, fresh.conv1, &channels, &channels),
        local: None,
        head: widen_modulated(old.head, fresh.head, &channels, &Layout::same(2)),
    }
}

/// Checks that `wider` only adds channels and Fourier pairs to `narrow`.
pub fn check_widening(narrow: &GeneratorConfig, wider: &GeneratorConfig) -> Result<()> {
    ensure!(
        narrow.channels.len() == wider.channels.len() && narrow.n_freq.len() == wider.n_freq.len(),
        "a widened generator keeps its {} blocks",
        narrow.channels.len()
    );
    let grows = |a: &[usize], b: &[usize]| a.iter().zip(b).all(|(a, b)| b >= a);
    ensure!(
        grows(&narrow.channels, &wider.channels) && grows(&narrow.n_freq, &wider.n_freq),
        "widening cannot remove channels or Fourier pairs: {:?} / {:?} -> {:?} / {:?}",
        narrow.channels,
        narrow.n_freq,
        wider.channels,
        wider.n_freq
    );
    ensure!(
        narrow.local_blocks == 0 && wider.local_blocks == 0,
        "widening a generator with local paths is not supported"
    );
    ensure!(
        narrow.lh == wider.lh
            && narrow.lw == wider.lw
            && narrow.output_gain == wider.output_gain
            && serde_json::to_value(&narrow.mapping).ok()
                == serde_json::to_value(&wider.mapping).ok(),
        "a widened generator keeps its mapping network, bandwidths and output gain"
    );
    Ok(())
}

/// `trained` with `fresh`'s shapes (a wider configuration of the same generator): the same
/// function, with `fresh`'s weights in every new output channel.
pub fn widen_generator(trained: Generator, fresh: Generator) -> Generator {
    let mut prev = (0, 0);
    let blocks = trained
        .blocks
        .into_iter()
        .zip(fresh.blocks)
        .map(|(old, new)| {
            let channels = (old.conv1.weight.dims()[0], new.conv1.weight.dims()[0]);
            let block = widen_block(old, new, prev);
            prev = channels;
            block
        })
        .collect();
    Generator {
        mapping: trained.mapping,
        blocks,
        output_gain: fresh.output_gain,
    }
}

/// Writes a resumable run in `dst` (which must hold no checkpoint) from the run in `src`,
/// its generator widened to `channels` and `n_freq` per block: the same training state,
/// discriminator and encoder, and a fresh Adam state for the generator.
pub fn widen_run(
    src: &Path,
    dst: &Path,
    channels: Vec<usize>,
    n_freq: Vec<usize>,
    device: &Device,
) -> Result<()> {
    let src_ck = src.join(CHECKPOINT);
    ensure!(
        src_ck.join("state.json").exists(),
        "'{}' holds no training checkpoint to widen",
        src.display()
    );
    if dst.join(CHECKPOINT).join("state.json").exists() {
        bail!(
            "'{}' already holds a checkpoint; widening never overwrites a run",
            dst.display()
        );
    }
    let narrow = load_config(&src.join("config.json"))?;
    ensure!(
        narrow.arch == crate::model::Arch::Dusty2,
        "only a dusty2 generator can be widened (the run in '{}' is {:?})",
        src.display(),
        narrow.arch
    );
    let generator = narrow
        .generator
        .clone()
        .with_channels(channels)
        .with_n_freq(n_freq);
    generator.check()?;
    check_widening(&narrow.generator, &generator)?;
    let wider = narrow.clone().with_generator(generator);
    let widen_file = |name: &str| -> Result<Generator> {
        let file = src_ck.join(name);
        let trained = AnyGenerator::Implicit(narrow.generator.init(device))
            .try_load_file(&file)
            .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", file.display()))?;
        let AnyGenerator::Implicit(trained) = trained else {
            bail!("'{}' is not a DUSty v2 generator", file.display())
        };
        Ok(widen_generator(trained, wider.generator.init(device)))
    };
    let (g, g_ema) = (widen_file("g.bpk")?, widen_file("g_ema.bpk")?);
    std::fs::create_dir_all(dst)
        .with_context(|| format!("failed to create '{}'", dst.display()))?;
    // The checkpoint comes last: its atomic swap marks a finished widening, so an
    // interrupted one is simply redone.
    wider
        .save(dst.join("config.json"))
        .with_context(|| format!("failed to write '{}'", dst.join("config.json").display()))?;
    // The widened run's log goes on from the source's, through the checkpoint it widens.
    if let Ok(log) = std::fs::read_to_string(src.join("log.jsonl")) {
        let state: TrainState = read_state(&src_ck)?;
        std::fs::write(dst.join("log.jsonl"), log_through(&log, state.step))
            .with_context(|| format!("failed to write '{}'", dst.join("log.jsonl").display()))?;
    }
    write_checkpoint(dst, |tmp| {
        let save = |m: Generator, name: &str| {
            AnyGenerator::Implicit(m)
                .save_file(tmp.join(name))
                .map_err(|e| anyhow::anyhow!("failed to save {name}: {e}"))
        };
        save(g, "g.bpk")?;
        save(g_ema, "g_ema.bpk")?;
        // Everything else carries over as it is; opt_g does not (its shapes changed).
        for name in ["d.bpk", "opt_d.bpk", "e.bpk", "opt_e.bpk", "state.json"] {
            if src_ck.join(name).exists() {
                std::fs::copy(src_ck.join(name), tmp.join(name))
                    .with_context(|| format!("failed to copy {name}"))?;
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::generator::MappingConfig;
    use crate::model::layers::regular_grid;
    use crate::util::rng::Rng;

    fn config(channels: Vec<usize>, n_freq: Vec<usize>, seed: u64) -> GeneratorConfig {
        GeneratorConfig::new()
            .with_mapping(MappingConfig::new().with_d_z(8).with_d_w(8))
            .with_channels(channels)
            .with_n_freq(n_freq)
            .with_lh(vec![3, 4, 5])
            .with_lw(vec![2, 3, 4])
            .with_seed(seed)
    }

    #[test]
    fn layouts_place_trained_entries_first_in_each_segment() {
        let layout = Layout(vec![(2, 3), (1, 2)]);
        assert_eq!(
            layout.sources(),
            vec![Some(0), Some(1), None, Some(2), None]
        );
        let device = Device::flex();
        let old = tensor_from(vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [2, 3], &device);
        let fresh = tensor_from(vec![9.0; 15], [3, 5], &device);
        let out = widen_matrix(old, fresh, &Layout::grown(2, 3), &layout, 10.0);
        #[rustfmt::skip]
        let expected = vec![
            10.0, 20.0, 0.0, 30.0, 0.0,
            40.0, 50.0, 0.0, 60.0, 0.0,
            9.0, 9.0, 9.0, 9.0, 9.0,
        ];
        assert_eq!(tensor_to_vec(out), expected);
    }

    #[test]
    fn a_widened_generator_renders_what_the_trained_one_rendered() {
        let device = Device::flex();
        let narrow = config(vec![8, 4, 4], vec![4, 4, 2], 1);
        let wide = config(vec![16, 8, 6], vec![8, 4, 5], 2);
        check_widening(&narrow, &wide).expect("a valid widening");
        let trained = narrow.init(&device);
        let widened = widen_generator(trained.clone(), wide.init(&device));
        assert_eq!(widened.blocks[2].conv1.weight.dims(), [6, 6]);
        assert_eq!(widened.blocks[0].fourier.n_freq(), 8);

        let grid_of = |g: &Generator| g.prepare(&regular_grid(8, 16, 0.05, -0.4), &device);
        let mut rng = Rng::new(5);
        let w = trained.mapping.forward(rng.normal_tensor([3, 8], &device));
        let shift = tensor_from(vec![0.1, 0.37, 0.9], [3], &device);
        let render =
            |g: &Generator| tensor_to_vec(g.synthesis(w.clone(), &grid_of(g), Some(shift.clone())));
        let (before, after) = (render(&trained), render(&widened));
        assert_eq!(before.len(), after.len());
        let worst = before
            .iter()
            .zip(&after)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        let scale = before.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
        assert!(scale > 0.1, "a degenerate rendering ({scale})");
        assert!(
            worst < 1e-4 * scale,
            "widening changed the output by {worst}"
        );

        // The new channels are live: a nudge to the zeros that join them changes the output.
        let mut nudged = widened.clone();
        let head = &mut nudged.blocks[2].head;
        let values: Vec<f32> = tensor_to_vec(head.weight.val())
            .chunks(6)
            .flat_map(|row| [&row[..4], &[1.0, 1.0][..]].concat())
            .collect();
        head.weight = Param::from_tensor(tensor_from(values, [2, 6], &device));
        let moved = render(&nudged)
            .iter()
            .zip(&after)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            moved > 1e-3,
            "the new channels do not reach the output ({moved})"
        );
    }

    #[test]
    fn widening_refuses_to_narrow_or_change_the_mapping() {
        let narrow = config(vec![8, 4, 4], vec![4, 4, 2], 1);
        assert!(check_widening(&narrow, &config(vec![8, 2, 4], vec![4, 4, 2], 1)).is_err());
        assert!(check_widening(&narrow, &config(vec![8, 4], vec![4, 4], 1)).is_err());
        let other_mapping = config(vec![8, 4, 4], vec![4, 4, 2], 1)
            .with_mapping(MappingConfig::new().with_d_z(8).with_d_w(16));
        assert!(check_widening(&narrow, &other_mapping).is_err());
    }
}

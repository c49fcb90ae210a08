//! One training step: D's update on the batch in parallel parts (with the lazy R1 and
//! adaptive augmentation), then G's update with its EMA and the in-loop encoder's.

use anyhow::Result;
use burn::module::Module;
use burn::optim::GradientsParams;
use burn::tensor::activation::{sigmoid, softplus};
use burn::tensor::{Device, Tensor};
use rayon::prelude::*;

use crate::model::data::{DROPPED, RangeDataset};
use crate::model::discriminator::{Discriminator, column_azimuths};
use crate::model::generator::{Generator, GridCache};
use crate::model::measurement::MeasurementConfig;
use crate::model::self_decoder::SelfDecoder;
use crate::model::{AnyGenerator, Generated};
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};

use super::Trainer;
use crate::train::config::TrainConfig;
use crate::train::reconstruct::{self, Losses};
use crate::train::regularise::{LecamAnchors, pseudo_reals, translate_cutout};
use crate::train::update::{augment, drop_head_grads, ema_update, mean_grads};

impl Trainer {
    pub(super) fn step(&mut self, data: &RangeDataset) -> Result<StepMetrics> {
        let cfg = self.config.clone();
        let device = self.device.clone();
        let inner = device.clone().inner();
        let parts = batch_parts(cfg.batch_size);

        // ---- D step: fakes come from the generator without autodiff (constants for D).
        let z = self.z(&inner);
        let shift = self.subgrid();
        let windows = self.window_starts();
        let real = self.real_batch(data, windows.as_deref(), &device);
        let azimuth = self.window_azimuths(windows.as_deref(), &device);
        let lazy = cfg.r1_gamma > 0.0 && self.state.step.is_multiple_of(cfg.r1_interval as u64);
        let regularisation = cfg.regularisation.clone();
        let view = DView {
            pixel_drop: self.pixel_drop(),
            ada_p: self.state.ada_p,
            diff_augment: regularisation.diff_augment,
        };
        let apa_p = if regularisation.apa {
            self.state.apa_p
        } else {
            0.0
        };
        let lecam = (regularisation.lecam > 0.0)
            .then_some(self.state.lecam)
            .flatten()
            .map(|anchors| (regularisation.lecam, anchors));
        let n = cfg.batch_size / parts;
        let seeds: Vec<u64> = (0..parts).map(|_| self.state.rng.next_u64()).collect();
        let r1_gamma = self.level.r1_gamma(cfg.r1_gamma);
        let g_inner = self.g.valid();
        let weight = regularisation.self_supervised;
        let decoder = self.self_decoder.as_ref().map(|s| (&s.decoder, weight));
        let d_parts: Vec<(DPart, [BatchStats; 2])> = (0..parts)
            .into_par_iter()
            .map(|k| {
                let mut rng = Rng::new(seeds[k]);
                let z = z.clone().narrow(0, k * n, n);
                let shift = shift.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let windows = windows.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let (fake, _) = self.render(&g_inner, z, self.grid_inner.as_ref(), shift, windows);
                let fake = measure(&cfg.measurement, fake, &mut rng).autodiff();
                let azimuth = azimuth.as_ref().map(|a| a.clone().narrow(0, k * n, n));
                let real = real.clone().narrow(0, k * n, n);
                let seen = [BatchStats::of(&real), BatchStats::of(&fake)];
                let (real, swapped) = pseudo_reals(real, fake.clone(), apa_p, &mut rng);
                let fake = view.apply(fake, &mut rng);
                let real = view.apply(real, &mut rng);
                let v = lazy.then(|| rng.normal_tensor(real.dims(), &device));
                let terms = DTerms { r1_gamma, lecam };
                let inputs = DInputs {
                    fake,
                    real,
                    r1_direction: v,
                    azimuth,
                };
                let mut part = d_part(&self.d, decoder, &device, &cfg, terms, inputs);
                part.swapped = swapped;
                (part, seen)
            })
            .collect();
        let (d_parts, seen): (Vec<DPart>, Vec<[BatchStats; 2]>) = d_parts.into_iter().unzip();
        let seen = [0, 1].map(|i| BatchStats::mean(seen.iter().map(|s| s[i])));
        let mean = |f: &dyn Fn(&DPart) -> f32| d_parts.iter().map(f).sum::<f32>() / parts as f32;
        let (loss_d, d_fake) = (mean(&|p| p.loss_d), mean(&|p| p.d_fake));
        let r1 = lazy.then(|| mean(&|p| p.r1.unwrap_or(0.0)));
        let self_supervised = decoder.map(|_| mean(&|p| p.self_supervised.unwrap_or(0.0)));
        let d_real: Vec<f32> = d_parts.iter().flat_map(|p| p.d_real.clone()).collect();
        // The overfitting heuristic reads the real scans D saw, not APA's pseudo reals.
        let truly_real: Vec<f32> = d_parts
            .iter()
            .flat_map(|p| {
                p.d_real
                    .iter()
                    .zip(&p.swapped)
                    .filter(|(_, s)| !**s)
                    .map(|(v, _)| *v)
            })
            .collect();
        if regularisation.lecam > 0.0 && !truly_real.is_empty() {
            let real_mean = truly_real.iter().sum::<f32>() / truly_real.len() as f32;
            self.state.lecam = Some(LecamAnchors::update(self.state.lecam, real_mean, d_fake));
        }
        if r1.is_some() {
            self.last_r1 = r1;
        }
        let (grads, decoder_grads): (Vec<_>, Vec<_>) = d_parts
            .into_iter()
            .map(|p| (p.grads, p.decoder_grads))
            .unzip();
        let grads = mean_grads(&self.d, grads);
        self.d = self.opt_d.step(cfg.lr, self.d.clone(), grads);
        if let Some(s) = self.self_decoder.as_mut() {
            let grads = mean_grads(&s.decoder, decoder_grads.into_iter().flatten().collect());
            s.decoder = s.opt.step(cfg.lr, s.decoder.clone(), grads);
        }

        // Adaptive augmentation (and APA's probability): move p towards
        // E[sign(D(real))] = target.
        self.state.ada_acc += truly_real.iter().map(|v| v.signum()).sum::<f32>();
        self.state.ada_count += truly_real.len() as u64;
        if self.state.step.is_multiple_of(cfg.ada_interval as u64) && self.state.ada_count > 0 {
            let rt = self.state.ada_acc / self.state.ada_count as f32;
            let delta = (cfg.batch_size * cfg.ada_interval) as f64 / cfg.ada_speed_images;
            let step = (rt - cfg.ada_target).signum() * delta as f32;
            self.state.ada_p = (self.state.ada_p + step).clamp(0.0, 1.0);
            if regularisation.apa {
                self.state.apa_p = (self.state.apa_p + step).clamp(0.0, 1.0);
            }
            self.state.ada_acc = 0.0;
            self.state.ada_count = 0;
        }

        let (loss_g, assisted) =
            if self.d_warming_up() || !self.state.step.is_multiple_of(cfg.g_every.max(1) as u64) {
                (f32::NAN, None)
            } else {
                self.g_step(view, data)
            };
        Ok(StepMetrics {
            loss_d,
            loss_g,
            r1,
            self_supervised,
            d_real: d_real.iter().sum::<f32>() / d_real.len() as f32,
            d_fake,
            pixel_drop: self.pixel_drop(),
            assisted,
            real: seen[0],
            fake: seen[1],
        })
    }

    /// The generator's step (D without autodiff on its weights still passes gradients to
    /// its input), then its EMA; returns G's loss.
    fn g_step(&mut self, view: DView, data: &RangeDataset) -> (f32, Option<Losses>) {
        let cfg = self.config.clone();
        let device = self.device.clone();
        let parts = batch_parts(cfg.batch_size);
        let n = cfg.batch_size / parts;
        let z = self.z(&device);
        let shift = self.subgrid();
        let windows = self.window_starts();
        let azimuth = self.window_azimuths(windows.as_deref(), &device);
        let d_frozen = self.d.valid();
        let view = DView {
            ada_p: self.state.ada_p,
            ..view
        };
        let seeds: Vec<u64> = (0..parts).map(|_| self.state.rng.next_u64()).collect();
        // Reconstruction-assisted runs encode a batch of real scans as well; the ray-drop
        // anchor reads the same batch's drop rate per row.
        let real = (self.encoder.is_some() || cfg.drop_rate_weight > 0.0)
            .then(|| self.real_batch(data, windows.as_deref(), &device));
        let real_row_drop = real
            .as_ref()
            .filter(|_| cfg.drop_rate_weight > 0.0)
            .map(row_drop_rates);
        let rendering = self.rendering_generator();
        let mut g_parts: Vec<GPart> = (0..parts)
            .into_par_iter()
            .map(|k| {
                let g = rendering.clone().fork(&device);
                let z = z.clone().narrow(0, k * n, n);
                let shift = shift.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let windows = windows.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let (fake, w) = self.render(&g, z, self.grid.as_ref(), shift, windows);
                let azimuth = azimuth.as_ref().map(|a| a.clone().narrow(0, k * n, n));
                let anchor = match (&real_row_drop, &fake.keep_logit) {
                    (Some(rows), Some(keep_logit)) => Some(
                        drop_rate_anchor(keep_logit.clone(), rows).mul_scalar(cfg.drop_rate_weight),
                    ),
                    _ => None,
                };
                let mut rng = Rng::new(seeds[k]);
                let fake = measure(&cfg.measurement, fake, &mut rng);
                let logit = d_frozen.forward_at(view.apply(fake.clone(), &mut rng), azimuth);
                let loss_g = softplus(logit.neg(), 1.0).mean();
                let loss = loss_g.clone().inner().into_scalar::<f32>();
                let encoder = self
                    .encoder
                    .as_ref()
                    .map(|e| e.encoder.clone().fork(&device));
                let (total, assisted) = match (&g, &encoder, &real, &w) {
                    (AnyGenerator::Implicit(generator), Some(e), Some(real), Some(w)) => {
                        let grid = self
                            .grid
                            .as_ref()
                            .expect("the implicit generator has a grid");
                        let real = real.clone().narrow(0, k * n, n);
                        let (extra, values) = reconstruct::losses(
                            cfg.reconstruction
                                .as_ref()
                                .expect("an encoder has its config"),
                            generator,
                            e,
                            grid,
                            real,
                            fake,
                            w.clone(),
                        );
                        (loss_g + extra, Some(values))
                    }
                    _ => (loss_g, None),
                };
                let total = match anchor {
                    Some(anchor) => total + anchor,
                    None => total,
                };
                let mut grads = total.backward();
                GPart {
                    grads: GradientsParams::from_module(&mut grads, &g),
                    encoder_grads: encoder
                        .as_ref()
                        .map(|e| GradientsParams::from_module(&mut grads, e)),
                    loss,
                    w: w.map(|w| w.detach()),
                    assisted,
                }
            })
            .collect();
        let loss_g = g_parts.iter().map(|p| p.loss).sum::<f32>() / parts as f32;
        let assisted = self.encoder_step(&mut g_parts);
        let w: Option<Vec<Tensor<2>>> = g_parts.iter().map(|p| p.w.clone()).collect();
        let w = w.map(|w| Tensor::cat(w, 0));
        let grads = mean_grads(&self.g, g_parts.into_iter().map(|p| p.grads).collect());
        let grads = if cfg.drop_head_only {
            drop_head_grads(&self.g, grads)
        } else {
            grads
        };
        let g = self
            .opt_g
            .step(cfg.g_lr.unwrap_or(cfg.lr), self.g.clone(), grads);
        // A frozen mapping keeps its w average too: the decode starts from it.
        let w = w.filter(|_| !cfg.drop_head_only);
        self.g = match (g, w) {
            (AnyGenerator::Implicit(mut generator), Some(w)) => {
                generator.mapping = generator.mapping.track_w_avg(&w);
                AnyGenerator::Implicit(generator)
            }
            (g, _) => g,
        };

        // ---- EMA of the generator (inference model).
        let half_life = cfg
            .ema_half_life_images
            .min(self.state.images as f64 * cfg.ema_rampup)
            .max(1.0);
        let beta = 0.5f64.powf(cfg.batch_size as f64 / half_life) as f32;
        self.g_ema = ema_update(self.g_ema.clone(), &self.g, beta);
        (loss_g, assisted)
    }

    /// A part's generated scans: whole turns at the level's resolution, or the windows
    /// starting at the columns of `windows` (the subgrid shift then is their phase).
    fn render(
        &self,
        g: &AnyGenerator,
        z: Tensor<2>,
        grid: Option<&GridCache>,
        shift: Option<&[f32]>,
        windows: Option<&[usize]>,
    ) -> (Generated, Option<Tensor<2>>) {
        let (Some(start), AnyGenerator::Implicit(generator)) = (windows, g) else {
            return g.generate(z, grid, shift);
        };
        let grid = grid.expect("the implicit generator has a grid");
        let w = generator.mapping.forward(z);
        let phase = shift.map_or_else(|| vec![0.0; start.len()], <[f32]>::to_vec);
        let out = generator.render_window(w.clone(), grid, self.level.width, start, &phase);
        let fake = Generated {
            x_d: out.x_d,
            keep_logit: Some(out.keep_logit),
        };
        (fake, Some(w))
    }

    /// The azimuth of each column of a batch's windows, as the discriminator reads it.
    fn window_azimuths(&self, windows: Option<&[usize]>, device: &Device) -> Option<Tensor<4>> {
        let level = &self.level;
        windows.map(|start| column_azimuths(start, level.trained_width(), level.width, device))
    }

    /// The generator as the current stage renders: the first blocks only. Blocks that take
    /// no part must not enter the autodiff graph either: a tracked parameter that no backward
    /// pass ever consumes stays registered, and every later backward pass walks it again (a
    /// run slowed from 115 to 33 images/s in 1 400 steps that way).
    fn rendering_generator(&self) -> AnyGenerator {
        match &self.g {
            AnyGenerator::Implicit(g) if self.level.blocks < g.blocks.len() => {
                AnyGenerator::Implicit(Generator {
                    mapping: g.mapping.clone(),
                    blocks: g.blocks[..self.level.blocks].to_vec(),
                    output_gain: g.output_gain,
                })
            }
            g => g.clone(),
        }
    }

    /// The in-loop encoder's Adam step on the parts' mean gradient; the parts' mean losses.
    fn encoder_step(&mut self, parts: &mut [GPart]) -> Option<Losses> {
        let lr = self.config.reconstruction.as_ref()?.lr;
        let e = self.encoder.as_mut()?;
        let grads: Vec<GradientsParams> = parts
            .iter_mut()
            .filter_map(|p| p.encoder_grads.take())
            .collect();
        let grads = mean_grads(&e.encoder, grads);
        e.encoder = e.opt.step(lr, e.encoder.clone(), grads);
        let k = parts.len().max(1) as f32;
        let values = parts.iter().filter_map(|p| p.assisted);
        Some(values.fold(Losses::default(), |acc, v| Losses {
            reconstruction: acc.reconstruction + v.reconstruction / k,
            cycle: acc.cycle + v.cycle / k,
            prior: acc.prior + v.prior / k,
        }))
    }
}

pub(super) struct StepMetrics {
    pub(super) loss_d: f32,
    pub(super) loss_g: f32,
    pub(super) r1: Option<f32>,
    /// The self-supervised decoder's reconstruction loss, where the run has one.
    pub(super) self_supervised: Option<f32>,
    pub(super) d_real: f32,
    pub(super) d_fake: f32,
    pub(super) pixel_drop: f32,
    /// Reconstruction-assisted runs: the reconstruction and latent-cycle losses.
    pub(super) assisted: Option<Losses>,
    /// What D was shown, before augmentation: the real batch and the generated one.
    pub(super) real: BatchStats,
    pub(super) fake: BatchStats,
}

/// Summary statistics of a measured batch, logged beside D's outputs so that a generator
/// that fools D by moving a global statistic (the drop share, the mean depth) shows.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct BatchStats {
    /// Share of dropped pixels (-1 in network units).
    pub(super) drop: f32,
    /// Mean and standard deviation of the returns' inverse depth (network units).
    pub(super) mean: f32,
    pub(super) std: f32,
}

impl BatchStats {
    pub(super) fn of(x: &Tensor<4>) -> Self {
        let v = tensor_to_vec(x.clone().inner());
        let returns: Vec<f64> = v
            .iter()
            .filter(|&&x| x > DROPPED)
            .map(|&x| x as f64)
            .collect();
        let n = returns.len().max(1) as f64;
        let mean = returns.iter().sum::<f64>() / n;
        let var = returns.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        BatchStats {
            drop: 1.0 - returns.len() as f32 / v.len().max(1) as f32,
            mean: mean as f32,
            std: var.sqrt() as f32,
        }
    }

    pub(super) fn mean(all: impl Iterator<Item = BatchStats>) -> Self {
        let (mut sum, mut k) = (BatchStats::default(), 0.0f32);
        for s in all {
            sum.drop += s.drop;
            sum.mean += s.mean;
            sum.std += s.std;
            k += 1.0;
        }
        let k = k.max(1.0);
        BatchStats {
            drop: sum.drop / k,
            mean: sum.mean / k,
            std: sum.std / k,
        }
    }

    pub(super) fn json(self) -> serde_json::Value {
        serde_json::json!({"drop": self.drop, "mean": self.mean, "std": self.std})
    }
}

/// One part of a G step: its gradients (and the in-loop encoder's) and numbers.
struct GPart {
    grads: GradientsParams,
    encoder_grads: Option<GradientsParams>,
    loss: f32,
    w: Option<Tensor<2>>,
    assisted: Option<Losses>,
}

/// How many parts a batch is split into: each part runs forward and backward on its own
/// autodiff graph (a fork of the module), in parallel where there are threads, since a
/// step's small convolutions alone leave most of a second core idle. Always two for an
/// even batch, so results do not depend on the thread count.
pub(super) fn batch_parts(batch: usize) -> usize {
    if batch >= 2 && batch.is_multiple_of(2) {
        2
    } else {
        1
    }
}

/// x_G of the generator output (measurement model unless vanilla).
fn measure(measurement: &MeasurementConfig, out: Generated, rng: &mut Rng) -> Tensor<4> {
    match out.keep_logit {
        Some(logit) => measurement.measure(out.x_d, logit, rng).x_measured,
        None => out.x_d,
    }
}

/// The drop rate of each row of a measured batch (`[batch, 1, H, W]`, -1 = dropped).
pub(super) fn row_drop_rates(x: &Tensor<4>) -> Vec<f32> {
    let [b, _, h, w] = x.dims();
    let v = tensor_to_vec(x.clone().inner());
    let per_row = (b * w).max(1) as f32;
    (0..h)
        .map(|r| {
            let dropped = (0..b)
                .flat_map(|i| &v[(i * h + r) * w..][..w])
                .filter(|&&x| x <= DROPPED)
                .count();
            dropped as f32 / per_row
        })
        .collect()
}

/// Mean over rows of the squared difference between the expected drop rate of the generated
/// batch's row (from its keep logits `[batch, 1, H, W]`) and `target` (one rate per row).
pub(super) fn drop_rate_anchor(keep_logit: Tensor<4>, target: &[f32]) -> Tensor<1> {
    let [_, _, h, _] = keep_logit.dims();
    let device = keep_logit.device();
    let drop = sigmoid(keep_logit).neg().add_scalar(1.0); // [batch, 1, H, W]
    let rows = drop.mean_dim(3).mean_dim(0); // [1, 1, H, 1]
    let target = tensor_from(target.to_vec(), [1, 1, h, 1], &device);
    (rows - target).powi_scalar(2).mean()
}

/// What D sees: early pixel dropout, then augmentation, then DiffAugment's translation and
/// cutout where the run has them (the same for real and fake).
#[derive(Debug, Clone, Copy)]
struct DView {
    pixel_drop: f32,
    ada_p: f32,
    diff_augment: bool,
}

impl DView {
    fn apply(self, x: Tensor<4>, rng: &mut Rng) -> Tensor<4> {
        let x = if self.pixel_drop > 0.0 {
            let keep = rng
                .uniform_open_tensor(x.dims(), &x.device())
                .greater_elem(self.pixel_drop)
                .float();
            (x.add_scalar(1.0) * keep).sub_scalar(1.0)
        } else {
            x
        };
        let x = if self.ada_p > 0.0 {
            augment(x, self.ada_p, rng)
        } else {
            x
        };
        if self.diff_augment {
            translate_cutout(x, rng)
        } else {
            x
        }
    }
}

/// One part of a D step: its gradients (and the self-supervised decoder's) and numbers.
struct DPart {
    grads: GradientsParams,
    decoder_grads: Option<GradientsParams>,
    self_supervised: Option<f32>,
    loss_d: f32,
    r1: Option<f32>,
    d_real: Vec<f32>,
    d_fake: f32,
    /// Which of the part's reals were APA's pseudo reals.
    swapped: Vec<bool>,
}

/// What D judges in one part: generated and real scans (or windows, with their columns'
/// azimuths), and the direction of the finite-difference R1 where it is due.
struct DInputs {
    fake: Tensor<4>,
    real: Tensor<4>,
    r1_direction: Option<Tensor<4>>,
    azimuth: Option<Tensor<4>>,
}

/// The terms D's loss adds to its own this step.
#[derive(Debug, Clone, Copy)]
struct DTerms {
    /// Weight of the R1 penalty at this level.
    r1_gamma: f32,
    /// The LeCam term's weight and anchors, where the run has it.
    lecam: Option<(f32, LecamAnchors)>,
}

/// D's loss on one part of the batch (with the lazy finite-difference R1 where a direction
/// is given, and the LeCam term, as `terms` say) and its gradients, on a fork of `d`; with a
/// self-supervised `decoder` (and its weight), also its loss rebuilding the real scans from
/// D's features, and the decoder's gradients.
fn d_part(
    d: &Discriminator,
    decoder: Option<(&SelfDecoder, f32)>,
    device: &Device,
    cfg: &TrainConfig,
    terms: DTerms,
    seen: DInputs,
) -> DPart {
    let DInputs {
        fake,
        real,
        r1_direction: v,
        azimuth,
    } = seen;
    let d = d.clone().fork(device);
    let decoder = decoder.map(|(m, weight)| (m.clone().fork(device), weight));
    let logit_fake = d.forward_at(fake, azimuth.clone()); // [part, 1]
    let features = d.features_at(real.clone(), azimuth.clone()); // [part, c, h, w]
    let reconstruction = (decoder.as_ref()).map(|(m, _)| m.loss(features.clone(), real.clone()));
    let logit_real = d.judge(features); // [part, 1]
    let d_real = tensor_to_vec(logit_real.clone().inner());
    let d_fake = tensor_to_vec(logit_fake.clone().inner());
    let loss_d =
        softplus(logit_fake.clone(), 1.0).mean() + softplus(logit_real.clone().neg(), 1.0).mean();
    let self_supervised = (reconstruction.as_ref()).map(|r| r.clone().inner().into_scalar::<f32>());
    let loss_with = match (reconstruction, &decoder) {
        (Some(r), Some((_, weight))) => loss_d.clone() + r.mul_scalar(*weight),
        _ => loss_d.clone(),
    };
    let regularised = match terms.lecam {
        Some((weight, anchors)) => {
            loss_with
                + anchors
                    .penalty(logit_real.clone(), logit_fake)
                    .mul_scalar(weight)
        }
        None => loss_with,
    };
    let (total, r1) = match v {
        Some(v) => {
            // Finite-difference R1: with v ~ N(0, I), E[(grad D . v)^2] = |grad D|^2, and
            // (D(x + h v) - D(x)) / h estimates grad D . v with first-order autodiff only.
            let h = cfg.r1_fd_step;
            let moved = d.forward_at(real.detach() + v.mul_scalar(h), azimuth); // [part, 1]
            let r1 = (moved - logit_real).div_scalar(h).powi_scalar(2).mean();
            let penalty = r1
                .clone()
                .mul_scalar(terms.r1_gamma * 0.5 * cfg.r1_interval as f32);
            let r1 = r1.inner().into_scalar::<f32>();
            (regularised + penalty, Some(r1))
        }
        None => (regularised, None),
    };
    let mut grads = total.backward();
    DPart {
        decoder_grads: decoder.map(|(m, _)| GradientsParams::from_module(&mut grads, &m)),
        grads: GradientsParams::from_module(&mut grads, &d),
        self_supervised,
        loss_d: loss_d.inner().into_scalar::<f32>(),
        r1,
        d_fake: d_fake.iter().sum::<f32>() / d_fake.len().max(1) as f32,
        d_real,
        swapped: Vec::new(),
    }
}

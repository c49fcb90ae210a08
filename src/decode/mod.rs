//! Auto-decoding (GAN inversion, seed paper section 3.3, reference section 5): turns an
//! observed range image into a tuned generator and its latent, and renders that scene on any
//! angle grid (the model grid, a denser one, another sensor's).
//!
//! - [`Decoder`] (shareable across rayon workers) holds the trained generator, the optional
//!   amortised encoder ([`amortised`]) and the per-grid Fourier caches.
//! - [`Decoder::decode`] reprojects the observation onto the model grid, optionally makes it sparse
//!   ([`Sparsify`], the paper's restoration), predicts or initialises w, and runs
//!   pivotal tuning on a private copy of the weights: by hand in [`pivotal`], or through
//!   [`invert::invert`] where the schedule also has w steps or coarse steps.
//! - [`Decoded`] holds the result: completed depth x_d and drop probability x_n on the model grid,
//!   the reconstruction error, Bernoulli ray-drop masks, and [`Decoded::render`] for other grids.
//! - [`fill`] decides what the upsampled, other-sensor and restored grids hold ([`Fill`]: the
//!   rendering, or the observation interpolated with the decoded scene as a guide).
//! - [`row_fill`] is the learned correction of rows restored between kept beams, and
//!   [`hole_fill`] that of dropped rays in the completed scan (the default fill's last
//!   steps).
//!
//! Every random draw comes from the caller's seed (derive it with [`scan_seed`] from topic and
//! log time) and each decode runs its tensor work on one thread, so results are bit-identical
//! whatever the thread count. Loading and encoding messages is left to `io` and `pipeline`.

pub mod amortised;
pub mod calibrate;
pub mod fill;
pub mod fit;
pub mod hole_fill;
pub mod invert;
pub mod loss;
pub mod pivotal;
pub mod prior_free;
pub mod row_fill;
pub mod sharpen;

use std::sync::Arc;

use anyhow::{Result, bail};
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::lidar::edges::edge_strength;
use crate::lidar::{AngleGrid, Interpolation, RangeImage, SensorProfile, resample_image};
use crate::model::AnyGenerator;
use crate::model::calibration::RaydropCalibration;
use crate::model::data::DepthRange;
use crate::model::generator::{Generator, GridCache};
use crate::model::weights::Model;
use crate::util::pools::Pools;
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};
use amortised::TrainedEncoder;
pub use fill::Fill;
pub use invert::Schedule;
use loss::relative_depth_error;
pub use sharpen::sharpen_drop_prob;

/// How hard to work per scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Quality {
    /// Encoder prediction + a few refinement steps ([`Schedule::fast`]).
    Fast,
    /// Encoder prediction + a long pivotal tuning ([`Schedule::paper`]): seconds per scan.
    Paper,
}

/// Keep only part of the observation before decoding (the paper's restoration experiment).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Sparsify {
    /// `n` evenly spaced rows of the model grid (e.g. 8 of 64).
    Lines(usize),
    /// Each measured pixel kept with this probability (seeded).
    Fraction(f32),
}

impl Sparsify {
    /// The kept rows for [`Sparsify::Lines`]: `round(k H / n)` for k < n.
    pub fn kept_rows(n: usize, height: usize) -> Vec<usize> {
        let n = n.clamp(1, height.max(1));
        (0..n)
            .map(|k| ((k * height) as f64 / n as f64).round() as usize)
            .filter(|r| *r < height)
            .collect()
    }

    /// Apply to a validity mask of a `height x width` grid; `rng` is used by `Fraction`.
    pub fn apply(&self, mask: &mut [f32], height: usize, width: usize, rng: &mut Rng) {
        match *self {
            Sparsify::Lines(n) => {
                let keep = Self::kept_rows(n, height);
                for r in 0..height {
                    if !keep.contains(&r) {
                        mask[r * width..(r + 1) * width].fill(0.0);
                    }
                }
            }
            Sparsify::Fraction(f) => {
                for m in mask.iter_mut() {
                    if *m > 0.0 && rng.uniform() >= f {
                        *m = 0.0;
                    }
                }
            }
        }
    }
}

/// Options of a [`Decoder`].
#[derive(Debug, Clone, PartialEq)]
pub struct DecodeOptions {
    pub quality: Quality,
    /// Steps and learning rates (default: the quality's).
    pub schedule: Schedule,
    /// Decode from a sparse version of each observation.
    pub restore: Option<Sparsify>,
    /// Apply the model's per-beam x_n calibration, when it has one.
    pub calibrate_raydrop: bool,
}

impl DecodeOptions {
    pub fn new(quality: Quality) -> Self {
        DecodeOptions {
            quality,
            schedule: match quality {
                Quality::Fast => Schedule::fast(),
                Quality::Paper => Schedule::paper(),
            },
            restore: None,
            calibrate_raydrop: true,
        }
    }
}

/// A grid with its Fourier cache, ready to render on (compute once, render many scans).
#[derive(Debug, Clone)]
pub struct PreparedGrid {
    /// The grid asked for.
    pub grid: AngleGrid,
    /// The grid actually rendered (`grid`, or the nearest size divisible by the generator's
    /// step, resampled back to `grid` afterwards).
    render_grid: AngleGrid,
    cache: Arc<GridCache>,
    /// Elevations (radians, low, high) the model knows, with a margin; pixels outside are
    /// extrapolations and are left empty.
    elevation_range: (f32, f32),
}

/// How far beyond the training grid's top and bottom beams a rendered pixel may look.
const ELEVATION_MARGIN_RAD: f32 = 0.0175; // 1 degree

fn elevation_range(grid: &AngleGrid) -> (f32, f32) {
    let lo = grid.elevation_rad.iter().cloned().fold(f32::MAX, f32::min);
    let hi = grid.elevation_rad.iter().cloned().fold(f32::MIN, f32::max);
    (lo - ELEVATION_MARGIN_RAD, hi + ELEVATION_MARGIN_RAD)
}

/// A decoded scene rendered on a grid, row-major `H x W`.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    pub grid: AngleGrid,
    /// Completed depth x_d in meters (clamped to 1.45-80 m), before ray drop; 0 where the
    /// pixel looks more than 1 degree above or below the beams the model was trained on.
    pub depth_m: Vec<f32>,
    /// x_n: probability that the ray is DROPPED, 0..1 (1 where `depth_m` is 0).
    pub drop_prob: Vec<f32>,
}

impl Rendered {
    /// Points along each pixel's direction at the completed depth (every pixel).
    pub fn points(&self) -> Vec<[f32; 3]> {
        (0..self.grid.len())
            .map(|k| {
                let [x, y, z] = self.grid.direction(k);
                let d = self.depth_m[k];
                [d * x, d * y, d * z]
            })
            .collect()
    }
}

/// Decoder state shared by all workers (read-only after construction).
pub struct Decoder {
    pools: Pools,
    generator: Generator,
    encoder: Option<TrainedEncoder>,
    opts: DecodeOptions,
    device: Device,
    ad: Device,
    model: PreparedGrid,
    cache_ad: GridCache,
    calibration: Option<Arc<RaydropCalibration>>,
    /// Where the generator came from.
    model_source: String,
    /// The sensor the model was trained for (its grid is `model.grid`).
    sensor: SensorProfile,
    /// The model's network units.
    units: DepthRange,
}

/// The result of decoding one scan.
#[derive(Debug, Clone)]
pub struct Decoded {
    generator: Generator,
    units: DepthRange,
    /// The shared generator before pivotal tuning. x_n comes from it: tuning fits depth
    /// alone and moves the drop head with it (held-out x_n NLL 0.248 tuned, 0.235 here).
    pivot: Generator,
    w: Tensor<2>,
    calibration: Option<Arc<RaydropCalibration>>,
    /// On the model grid.
    pub model: Rendered,
    /// The shared generator's uncalibrated keep logit on the model grid, which x_n on other
    /// grids is resampled from ([`Decoded::render_prepared`]).
    model_keep_logit: Vec<f32>,
    /// The observation used (model grid, meters, 0 = not observed), after [`Sparsify`].
    pub observed_m: Vec<f32>,
    /// The observed scan itself where it was on the model grid: its measured points (xyz,
    /// point index) put each return where it was measured on finer grids.
    observed_points: Option<RangeImage>,
    /// Measured pixels of the full observation that decoding did not see (restoration).
    pub held_out_m: Vec<f32>,
    /// Mean |d - d_obs| / d_obs over the observed pixels.
    pub error: Option<f32>,
    /// The same on the held-out pixels (`None` without [`Sparsify`]).
    pub held_out_error: Option<f32>,
    /// How the observation was made sparse before decoding.
    pub restore: Option<Sparsify>,
    /// Loss after each optimisation step.
    pub losses: Vec<f32>,
    pub seed: u64,
}

/// A seed for one scan from its topic and log time (FNV-1a of the topic mixed with the time),
/// so every random draw is the same whatever the thread count or file order.
pub fn scan_seed(topic: &str, log_time_nanos: u64) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in topic.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    let mut r = Rng::new(h ^ log_time_nanos.rotate_left(17));
    r.next_u64()
}

/// The grid the shipped model was trained on: KITTI HDL-64E at 512 columns. A decoder's own
/// is [`Decoder::model_grid`].
pub fn model_grid() -> AngleGrid {
    crate::model::config::default_sensor().angle_grid()
}

impl Decoder {
    /// A decoder for `model` (must be the implicit DUSty v2 generator). It starts each inversion
    /// from the shipped encoder's prediction (where it reads the model's grid) unless
    /// [`Decoder::with_encoder`] gives another or
    /// [`Decoder::without_encoder`] starts from w_avg.
    pub fn new(model: Model, opts: DecodeOptions) -> Result<Decoder> {
        let AnyGenerator::Implicit(generator) = model.generator else {
            bail!(
                "model '{}' is a fixed-resolution {:?} generator; auto-decoding needs the implicit dusty2 generator",
                model.source,
                model.config.arch
            );
        };
        let coarse_levels = opts.schedule.coarse_steps.len();
        if coarse_levels >= generator.blocks.len() {
            bail!(
                "{coarse_levels} coarse tuning levels asked for; model '{}' has {} blocks, so at most {}",
                model.source,
                generator.blocks.len(),
                generator.blocks.len() - 1
            );
        }
        let device = Device::flex();
        let ad = device.clone().autodiff();
        let generator = generator.to_device(&device);
        let grid = model.config.grid();
        let cache_ad = generator.prepare(&grid, &ad);
        let model_grid = PreparedGrid {
            render_grid: grid.clone(),
            cache: Arc::new(generator.prepare(&grid, &device)),
            elevation_range: elevation_range(&grid),
            grid,
        };
        let encoder = TrainedEncoder::shipped(&device)?;
        let calibration = model
            .calibration
            .filter(|_| opts.calibrate_raydrop)
            .map(Arc::new);
        let d = Decoder {
            pools: Pools::new(rayon::current_num_threads())?,
            model_source: model.source,
            calibration,
            generator,
            encoder: None,
            opts,
            device,
            ad,
            model: model_grid,
            cache_ad,
            units: model.config.depth_range(),
            sensor: model.config.sensor,
        };
        // The shipped encoder reads the shipped model's grid; a model of another sensor
        // starts from w_avg unless given its own encoder (`train-encoder`).
        if encoder.config.height == d.model.grid.height
            && encoder.config.width == d.model.grid.width
        {
            d.with_encoder(encoder)
        } else {
            Ok(d)
        }
    }

    /// Start every inversion from w_avg, as the paper does ([`Schedule::reference`]).
    pub fn without_encoder(mut self) -> Decoder {
        self.encoder = None;
        self
    }

    /// Where the generator and encoder came from.
    pub fn source(&self) -> String {
        match &self.encoder {
            Some(e) => format!("{} + encoder {}", self.model_source, e.source),
            None => self.model_source.clone(),
        }
    }

    /// Start each inversion from this encoder's prediction (e.g. one from `train-encoder`).
    pub fn with_encoder(mut self, encoder: TrainedEncoder) -> Result<Decoder> {
        let d_w = self.generator.d_w();
        if encoder.config.d_w != d_w
            || encoder.config.height != self.model.grid.height
            || encoder.config.width != self.model.grid.width
        {
            bail!(
                "encoder '{}' predicts w of size {} from {}x{} images; the generator needs {} from {}x{}",
                encoder.source,
                encoder.config.d_w,
                encoder.config.height,
                encoder.config.width,
                d_w,
                self.model.grid.height,
                self.model.grid.width
            );
        }
        self.encoder = Some(TrainedEncoder {
            encoder: encoder.encoder.to_device(&self.device),
            ..encoder
        });
        Ok(self)
    }

    pub fn options(&self) -> &DecodeOptions {
        &self.opts
    }

    /// What the x_n calibration in use was fitted on (`None`: x_n as the generator gives it).
    pub fn calibration_source(&self) -> Option<&str> {
        self.calibration.as_deref().map(|c| c.fitted_on.as_str())
    }

    /// The sensor the model was trained for: its beams and columns are the model grid, its
    /// valid range the depths the model knows.
    pub fn model_sensor(&self) -> &SensorProfile {
        &self.sensor
    }

    /// The model grid (the model's sensor at its training columns).
    pub fn model_grid(&self) -> &AngleGrid {
        &self.model.grid
    }

    /// Prepare a grid for [`Decoded::render_prepared`] (host sin/cos; do it once per grid).
    /// Grids whose size does not divide by the generator's step are rendered on the nearest
    /// larger divisible size and resampled back (bilinear).
    pub fn prepare(&self, grid: &AngleGrid) -> PreparedGrid {
        let step = self.generator.resolution_step();
        // At least two rows and columns at the coarsest level (the [1,3,3,1] filters need them).
        let round = |n: usize| n.div_ceil(step).max(2) * step;
        let render_grid = if round(grid.height) == grid.height && round(grid.width) == grid.width {
            grid.clone()
        } else {
            grid.resized(round(grid.height), round(grid.width))
        };
        PreparedGrid {
            cache: Arc::new(self.generator.prepare(&render_grid, &self.device)),
            render_grid,
            grid: grid.clone(),
            elevation_range: self.model.elevation_range,
        }
    }

    /// Observation on the model grid: network units and validity mask.
    fn observe(&self, observed: &RangeImage) -> (Vec<f32>, Vec<f32>, bool) {
        let grid = &self.model.grid;
        let same = observed.height == grid.height
            && observed.width == grid.width
            && observed.angles.len() == grid.len()
            && observed
                .angles
                .elevation_rad
                .iter()
                .zip(&grid.elevation_rad)
                .chain(observed.angles.azimuth_rad.iter().zip(&grid.azimuth_rad))
                .all(|(a, b)| (a - b).abs() < 1e-4);
        let range = if same {
            observed.range_m.clone()
        } else {
            reproject(observed, grid)
        };
        let net = self.units.to_network(&range);
        let mask = net
            .iter()
            .map(|v| if *v > -1.0 { 1.0 } else { 0.0 })
            .collect();
        (net, mask, same)
    }

    /// Decode one observed scan (any grid; its returns are reprojected onto the model grid). `seed` drives
    /// every random draw (use [`scan_seed`]). Runs on one thread; call it from several rayon
    /// workers to decode scans in parallel.
    pub fn decode(&self, observed: &RangeImage, seed: u64) -> Result<Decoded> {
        self.decode_from(observed, seed, None)
    }

    /// [`Decoder::decode`], with pivotal tuning starting from `start`'s weights (for example
    /// the previous scan's tuned generator) instead of the shared generator's.
    pub fn decode_from(
        &self,
        observed: &RangeImage,
        seed: u64,
        start: Option<&Generator>,
    ) -> Result<Decoded> {
        self.pools.run(|| {
            let (_, partial) = self.begin_here(observed, seed, start, None)?;
            Ok(self.finish_here(partial))
        })
    }

    /// The first part of [`Decoder::decode_from`]: everything up to the `hand_off`-th tuning
    /// step. Returns the weights reached there, from which the next scan of a chain can start
    /// while this one goes on ([`Decoder::finish`]); the result is the same as one call to
    /// [`Decoder::decode_from`]. (Schedules that the hand-written tuning does not run hand on
    /// their final weights.)
    pub fn begin(
        &self,
        observed: &RangeImage,
        seed: u64,
        start: Option<&Generator>,
        hand_off: usize,
    ) -> Result<(Generator, PartialDecode)> {
        let (handed, partial) =
            (self.pools).run(|| self.begin_here(observed, seed, start, Some(hand_off)))?;
        Ok((handed.expect("weights asked for"), partial))
    }

    /// The rest of a decode that [`Decoder::begin`] started.
    pub fn finish(&self, partial: PartialDecode) -> Decoded {
        self.pools.run(|| self.finish_here(partial))
    }

    /// [`Decoder::begin`] on the calling thread; without `hand_off`, nothing is handed on and
    /// the tuning has not started.
    fn begin_here(
        &self,
        observed: &RangeImage,
        seed: u64,
        start: Option<&Generator>,
        hand_off: Option<usize>,
    ) -> Result<(Option<Generator>, PartialDecode)> {
        if observed.range_m.len() != observed.len() || observed.angles.len() != observed.len() {
            bail!(
                "range image {}x{} has {} ranges and {} angles",
                observed.height,
                observed.width,
                observed.range_m.len(),
                observed.angles.len()
            );
        }
        let grid = &self.model.grid;
        let (h, w) = (grid.height, grid.width);
        let mut rng = Rng::new(seed);
        let (net, full_mask, on_model_grid) = self.observe(observed);
        let mut mask = full_mask.clone();
        if let Some(s) = &self.opts.restore {
            s.apply(&mut mask, h, w, &mut rng.fork());
        }
        let measured = mask.iter().filter(|m| **m > 0.0).count();
        if measured == 0 {
            bail!(
                "no return of the scan falls on the model grid ({}-{} m); nothing to decode",
                self.units.min_m,
                self.units.max_m
            );
        }
        let target = tensor_from(net.clone(), [1, 1, h, w], &self.device);
        let mask_t = tensor_from(mask.clone(), [1, 1, h, w], &self.device);
        let w_avg = tensor_to_vec(self.generator.mapping.w_avg.val());
        let w0 = match &self.encoder {
            Some(e) => {
                let target_seen = target.clone() * mask_t.clone() - mask_t.clone().sub_scalar(1.0);
                let delta = tensor_to_vec(e.encoder.forward(target_seen, mask_t.clone()));
                w_avg.iter().zip(&delta).map(|(a, d)| a + d).collect()
            }
            None => w_avg,
        };
        let start = start.unwrap_or(&self.generator).clone();
        let schedule = &self.opts.schedule;
        let (handed, tuning) = if pivotal::supports(&start, schedule) {
            let mut tuning =
                pivotal::Tuning::new(&start, &self.cache_ad, &net, &mask, w0, schedule);
            let handed = hand_off.map(|step| {
                tuning.run_to(step);
                tuning.weights(&start)
            });
            (handed, Tuning::Pivotal(Box::new(tuning)))
        } else {
            let (target, mask) = (target.autodiff(), mask_t.autodiff());
            let inv = invert::invert(&start, &self.cache_ad, target, mask, w0, schedule, &self.ad);
            (hand_off.map(|_| inv.generator.clone()), Tuning::Done(inv))
        };
        let partial = PartialDecode {
            start,
            tuning,
            net,
            mask,
            full_mask,
            observed_points: on_model_grid.then(|| observed.clone()),
            seed,
        };
        Ok((handed, partial))
    }

    fn finish_here(&self, partial: PartialDecode) -> Decoded {
        let PartialDecode {
            start,
            tuning,
            net,
            mask,
            full_mask,
            observed_points,
            seed,
        } = partial;
        let inv = match tuning {
            Tuning::Pivotal(tuning) => tuning.finish(&start),
            Tuning::Done(inv) => inv,
        };
        let d_w = inv.w.len();
        let w_t = tensor_from(inv.w, [1, d_w], &self.device);
        let depth_obs = |keep: &dyn Fn(usize) -> bool| -> Vec<f32> {
            net.iter()
                .enumerate()
                .map(|(k, _)| {
                    if keep(k) && net[k] > -1.0 {
                        self.units.depth_of(net[k])
                    } else {
                        0.0
                    }
                })
                .collect()
        };
        let observed_m = depth_obs(&|k| mask[k] > 0.0);
        let held_out_m = depth_obs(&|k| full_mask[k] > 0.0 && mask[k] == 0.0);
        let mut decoded = Decoded {
            generator: inv.generator,
            pivot: self.generator.clone(),
            w: w_t,
            calibration: self.calibration.clone(),
            units: self.units,
            model: Rendered {
                grid: self.model.grid.clone(),
                depth_m: Vec::new(),
                drop_prob: Vec::new(),
            },
            model_keep_logit: Vec::new(),
            observed_m,
            observed_points,
            held_out_m,
            error: None,
            held_out_error: None,
            restore: self.opts.restore,
            losses: inv.losses,
            seed,
        };
        let (depth_m, keep_logit) = decoded.render_raw(&self.model);
        decoded.model = decoded.calibrated(&self.model, depth_m, &keep_logit);
        decoded.model_keep_logit = keep_logit;
        decoded.error = relative_depth_error(&decoded.model.depth_m, &decoded.observed_m);
        decoded.held_out_error = self
            .opts
            .restore
            .and_then(|_| relative_depth_error(&decoded.model.depth_m, &decoded.held_out_m));
        decoded
    }
}

/// A decode between [`Decoder::begin`] and [`Decoder::finish`].
pub struct PartialDecode {
    /// The weights its tuning started from.
    start: Generator,
    tuning: Tuning,
    /// The observation on the model grid (network units) and its masks: what decoding saw,
    /// and every measured pixel.
    net: Vec<f32>,
    mask: Vec<f32>,
    full_mask: Vec<f32>,
    observed_points: Option<RangeImage>,
    seed: u64,
}

enum Tuning {
    Pivotal(Box<pivotal::Tuning>),
    Done(invert::Inverted),
}

/// The returns of `observed` on another grid: each measured pixel goes to the grid pixel of
/// its direction (the measured xyz where stored, else the pixel's angles): row = the nearest
/// beam within half a beam spacing, column by azimuth; the nearest return wins. Unlike
/// resampling, no return is lost when the source is sparser or denser than the grid.
fn reproject(observed: &RangeImage, grid: &AngleGrid) -> Vec<f32> {
    let rows = grid.row_elevations(); // top first, decreasing
    let mut out = vec![0.0f32; grid.len()];
    let h = rows.len();
    if h == 0 || grid.width == 0 {
        return out;
    }
    for k in 0..observed.len() {
        let d = observed.range_m[k];
        if d <= 0.0 {
            continue;
        }
        let [x, y, z] = observed.xyz.get(k).copied().unwrap_or([0.0; 3]);
        let (phi, theta) = if x != 0.0 || y != 0.0 || z != 0.0 {
            (z.atan2((x * x + y * y).sqrt()), y.atan2(x))
        } else {
            (
                observed.angles.elevation_rad[k],
                observed.angles.azimuth_rad[k],
            )
        };
        // Nearest row, accepted within half the spacing to its neighbour (one row: 1 degree).
        let i = rows.partition_point(|&e| e > phi);
        let candidates = [i.checked_sub(1), (i < h).then_some(i)];
        let Some(r) = candidates
            .into_iter()
            .flatten()
            .min_by(|a, b| (rows[*a] - phi).abs().total_cmp(&(rows[*b] - phi).abs()))
        else {
            continue;
        };
        let spacing = if h > 1 {
            let n = if r + 1 < h { r + 1 } else { r - 1 };
            (rows[r] - rows[n]).abs()
        } else {
            ELEVATION_MARGIN_RAD * 2.0
        };
        if (rows[r] - phi).abs() > 0.5 * spacing {
            continue;
        }
        let c = crate::lidar::range_image::azimuth_column(theta, grid.width).round() as usize
            % grid.width;
        let slot = &mut out[r * grid.width + c];
        if *slot == 0.0 || d < *slot {
            *slot = d;
        }
    }
    out
}

impl Decoded {
    /// The generator as tuned for this scan (a start for the next scan's tuning:
    /// [`Decoder::decode_from`]).
    pub fn tuned_generator(&self) -> &Generator {
        &self.generator
    }

    /// Render the tuned scene on a prepared grid (from [`Decoder::prepare`]).
    ///
    /// Depth is rendered on the grid itself. x_n comes from the keep logit on the model grid,
    /// resampled: the generator learnt the drops at the model grid's resolution, and
    /// rendering the shared generator once more on a sensor's full-resolution grid would
    /// cost as much as the depth's rendering.
    pub fn render_prepared(&self, grid: &PreparedGrid) -> Rendered {
        let depth_m = self.units.clamped_depths(&self.x_d_on(grid));
        let keep_logit = self.model_keep_logit_on(&grid.render_grid);
        self.calibrated(grid, depth_m, &keep_logit)
    }

    /// The rendering on `grid.render_grid` (depth in meters, the uncalibrated keep logit)
    /// calibrated into x_n and resampled onto `grid.grid`.
    fn calibrated(&self, grid: &PreparedGrid, depth_m: Vec<f32>, keep_logit: &[f32]) -> Rendered {
        let elevation = &grid.render_grid.elevation_rad;
        // The calibration's edge term needs the rendered depth's edges.
        let calibration = (self.calibration.as_ref())
            .map(|c| (c, edge_strength(&depth_m, grid.render_grid.width)));
        let drop_prob = (0..keep_logit.len())
            .map(|k| {
                let l = match &calibration {
                    Some((c, edges)) => {
                        c.keep_logit(keep_logit[k], depth_m[k], edges[k], elevation[k])
                    }
                    None => keep_logit[k],
                };
                1.0 / (1.0 + l.exp()) // x_n = sigmoid(-l)
            })
            .collect();
        let rendered = Rendered {
            grid: grid.render_grid.clone(),
            depth_m,
            drop_prob,
        };
        let mut r = if grid.render_grid == grid.grid {
            rendered
        } else {
            resample_rendered(&rendered, &grid.grid)
        };
        let (lo, hi) = grid.elevation_range;
        for k in 0..r.grid.len() {
            let e = r.grid.elevation_rad[k];
            if e < lo || e > hi {
                r.depth_m[k] = 0.0;
                r.drop_prob[k] = 1.0;
            }
        }
        r
    }

    /// Depth in meters (the tuned generator) and the uncalibrated keep logit (the generator
    /// before tuning) on `grid.render_grid`.
    fn render_raw(&self, grid: &PreparedGrid) -> (Vec<f32>, Vec<f32>) {
        let depth_m = self.units.clamped_depths(&self.x_d_on(grid));
        (depth_m, self.heads_on(&self.pivot, grid).1)
    }

    /// The tuned generator's x_d (network units) at this scan's latent on `grid.render_grid`.
    fn x_d_on(&self, grid: &PreparedGrid) -> Vec<f32> {
        let w = tensor_to_vec(self.w.clone());
        pivotal::render_x_d(&self.generator, &grid.cache, &w)
            .unwrap_or_else(|| self.heads_on(&self.generator, grid).0)
    }

    /// `generator`'s two heads at this scan's latent on `grid.render_grid`: x_d (network
    /// units) and the uncalibrated keep logit.
    fn heads_on(&self, generator: &Generator, grid: &PreparedGrid) -> (Vec<f32>, Vec<f32>) {
        let w = tensor_to_vec(self.w.clone());
        pivotal::render(generator, &grid.cache, &w).unwrap_or_else(|| {
            let out = generator.render(self.w.clone(), &grid.cache, None);
            (tensor_to_vec(out.x_d), tensor_to_vec(out.keep_logit))
        })
    }

    /// The model grid's keep logit resampled bilinearly onto `target` (0 where no model row
    /// reaches; [`Decoded::calibrated`] drops those rows).
    fn model_keep_logit_on(&self, target: &AngleGrid) -> Vec<f32> {
        if *target == self.model.grid {
            return self.model_keep_logit.clone();
        }
        let mut src = RangeImage::empty(self.model.grid.clone());
        src.range_m = self.model.depth_m.clone();
        src.intensity = self.model_keep_logit.clone();
        resample_image(&src, target, Interpolation::Bilinear).intensity
    }

    /// Depth in meters and the generator's uncalibrated keep logits on the model grid (for
    /// fitting a calibration).
    pub fn depth_and_keep_logits(&self, decoder: &Decoder) -> (Vec<f32>, Vec<f32>) {
        self.render_raw(&decoder.model)
    }

    /// Render on any grid (prepares it; prefer [`Decoder::prepare`] + [`Decoded::render_prepared`]
    /// when rendering many scans on the same grid).
    pub fn render(&self, decoder: &Decoder, grid: &AngleGrid) -> Rendered {
        self.render_prepared(&decoder.prepare(grid))
    }

    /// `k` Bernoulli samples of the ray-drop mask on the model grid (true = return kept),
    /// drawn from this scan's seed.
    pub fn sample_masks(&self, k: usize) -> Vec<Vec<bool>> {
        sample_masks(&self.model.drop_prob, k, self.seed)
    }
}

/// `k` Bernoulli samples of keep = 1 - drop_prob, from `seed`.
pub fn sample_masks(drop_prob: &[f32], k: usize, seed: u64) -> Vec<Vec<bool>> {
    let mut rng = Rng::new(seed ^ 0x6d61_736b); // "mask"
    (0..k)
        .map(|_| drop_prob.iter().map(|p| rng.uniform() >= *p).collect())
        .collect()
}

/// Bilinear resampling of a rendered depth / drop-probability pair onto another grid (both are
/// defined everywhere, so every target pixel inside the source's rows gets a value).
fn resample_rendered(r: &Rendered, target: &AngleGrid) -> Rendered {
    let mut src = RangeImage::empty(r.grid.clone());
    src.range_m = r.depth_m.clone();
    src.intensity = r.drop_prob.clone();
    let out = resample_image(&src, target, Interpolation::Bilinear);
    let drop_prob = out
        .intensity
        .iter()
        .zip(&out.range_m)
        .map(|(p, d)| if *d > 0.0 { *p } else { 1.0 })
        .collect();
    Rendered {
        grid: target.clone(),
        depth_m: out.range_m,
        drop_prob,
    }
}

#[cfg(test)]
mod tests;

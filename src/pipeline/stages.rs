//! The per-scan stages of `convert`: the range image every converted topic gets, and the
//! decoded channels ([`DecodeStage`]) on the sensor's own grid: through the model where it
//! covers the sensor, and prior-free (the scan's own returns completed, the recording's own
//! drop rates) where it does not.

use std::sync::{Arc, Mutex};

use super::{ScanInput, StageOutput, Staged};
use crate::decode::fill::{complete_observed, fill_from};
use crate::decode::prior_free::{
    FillCheck, complete_without_prior, complete_without_prior_but_across, finer_than_returns,
    sparser_beams_than,
};
use crate::decode::{Decoded, Decoder, Fill, PreparedGrid, Rendered, sample_masks, scan_seed};
use crate::io::Family;
use crate::io::encoders::{Kind, encode_f32_image, encode_mask, encode_points};
use crate::lidar::drop_census::{DropCensus, combine_with_rates, row_rates};
use crate::lidar::{
    AngleGrid, Interpolation, RangeImage, SensorProfile, SurfaceRule, resample_by_surface,
    resample_image,
};

/// The range image channel every converted topic gets: range in meters, 32FC1.
pub fn range_stage(input: &ScanInput<'_>) -> anyhow::Result<Staged<'static>> {
    let img = input.image;
    let bytes = encode_f32_image(
        input.family,
        input.cloud.stamp_nanos,
        &input.cloud.frame_id,
        (img.width, img.height),
        &img.range_m,
    );
    Ok(Staged::Done(vec![StageOutput {
        suffix: "range".into(),
        kind: Kind::Image,
        data: bytes,
    }]))
}

/// The auto-decoding stage: for every scan, on the sensor's own grid (its beams, its
/// columns): the completed depth, the rendering x_d, the ray-drop probability x_n, sampled
/// ray-drop masks and the completed point cloud; plus depth and points on extra grids (the
/// sensor's grid upsampled, other sensors'). A scan whose sensor the model does not cover
/// ([`ScanInput::covered`]) is not decoded: its channels are prior-free ([`prior_free`]).
pub struct DecodeStage<'d> {
    decoder: &'d Decoder,
    mask_samples: usize,
    upsample: Vec<usize>,
    /// `(suffix, grid)` of each target sensor: written as `depth_<suffix>`, `points_<suffix>`.
    targets: Vec<(String, AngleGrid)>,
    /// Each sensor grid met, prepared once, with its upsampled grids.
    prepared: Mutex<Vec<Arc<SensorGrids>>>,
    fill: Fill,
    hand_off: Option<usize>,
    x_n_weight: Option<f32>,
}

/// A sensor's grid and its extra grids, prepared for rendering.
struct SensorGrids {
    own: PreparedGrid,
    /// `(suffix, grid)` for every upsampling factor, then every target sensor.
    extra: Vec<(String, PreparedGrid)>,
}

/// At most this many distinct sensor grids are kept prepared (a topic whose angles change
/// from scan to scan prepares each scan's afresh).
const PREPARED_GRIDS: usize = 16;

/// What [`DecodeStage`] adds beyond the sensor-grid channels.
#[derive(Debug, Clone, Default)]
pub struct DecodeOutputs {
    /// Bernoulli ray-drop masks per scan (`raydrop_mask`, `raydrop_mask_1`, ...).
    pub mask_samples: usize,
    /// Upsampling factors of the sensor's grid (2 -> twice its beams and columns).
    pub upsample: Vec<usize>,
    /// Other sensors to render for (their own grids).
    pub target_sensors: Vec<SensorProfile>,
    /// What the extra grids and a restored model grid hold.
    pub fill: Fill,
    /// With chains: the tuning step after which a scan hands its weights on to the chain's
    /// next scan, which starts tuning while this one goes on (`None`: after all of them, so
    /// the next scan starts from this one's final weights).
    pub hand_off: Option<usize>,
    /// Where the recording has other scans, `raydrop_prob` combines x_n with its own drop
    /// rates, this weight on x_n ([`combine_with_rates`]; 0: the rates alone); `None`: x_n
    /// alone.
    pub x_n_weight: Option<f32>,
}

/// A channel-safe name for a sensor (`Ouster OS1-64` -> `ouster_os1_64`).
pub(super) fn suffix_of(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '_'
            }
        })
        .collect()
}

/// The extra grids of a sensor grid: `(suffix, grid)`.
pub(super) fn extra_grids(
    own: &AngleGrid,
    upsample: &[usize],
    targets: &[(String, AngleGrid)],
) -> Vec<(String, AngleGrid)> {
    let up = upsample.iter().map(|&f| {
        let grid = own.resized(own.height * f, own.width * f);
        (format!("{}x{}", grid.height, grid.width), grid)
    });
    up.chain(targets.iter().cloned()).collect()
}

impl<'d> DecodeStage<'d> {
    pub fn new(decoder: &'d Decoder, outputs: &DecodeOutputs) -> anyhow::Result<Self> {
        if let Some(f) = outputs.upsample.iter().find(|f| !(1..=8).contains(*f)) {
            anyhow::bail!("--upsample {f}: factors from 1 to 8 are supported");
        }
        let targets = (outputs.target_sensors.iter())
            .map(|p| (suffix_of(&p.name), p.angle_grid()))
            .collect();
        Ok(DecodeStage {
            decoder,
            mask_samples: outputs.mask_samples,
            upsample: outputs.upsample.clone(),
            targets,
            prepared: Mutex::new(Vec::new()),
            fill: outputs.fill,
            hand_off: outputs.hand_off,
            x_n_weight: outputs.x_n_weight,
        })
    }

    /// The channels (suffixes) [`run`](Self::run) writes; `raydrop_mask` stands for every
    /// mask. The upsampled grids are named by their size on the model grid's sensor (they
    /// follow each sensor's grid: `depth_<beams>x<columns>`).
    pub fn channel_names(&self) -> Vec<String> {
        let mut names: Vec<String> = ["depth", "x_d", "raydrop_prob", "raydrop_mask", "points"]
            .map(String::from)
            .into();
        let model = self.decoder.model_grid();
        for (suffix, _) in extra_grids(model, &self.upsample, &self.targets) {
            names.extend([format!("depth_{suffix}"), format!("points_{suffix}")]);
        }
        names
    }

    /// The prepared grids of the sensor grid `own`.
    fn grids(&self, own: &AngleGrid) -> Arc<SensorGrids> {
        let mut prepared = self.prepared.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(found) = prepared.iter().find(|g| g.own.grid == *own) {
            return found.clone();
        }
        let grids = Arc::new(SensorGrids {
            own: self.decoder.prepare(own),
            extra: (extra_grids(own, &self.upsample, &self.targets).into_iter())
                .map(|(suffix, grid)| (suffix, self.decoder.prepare(&grid)))
                .collect(),
        });
        if prepared.len() < PREPARED_GRIDS {
            prepared.push(grids.clone());
        }
        grids
    }

    /// Decode one scan and encode its channels. A chained scan hands its weights on to the
    /// chain after [`DecodeOutputs::hand_off`] steps and finishes later.
    pub fn run<'s>(&'s self, input: &ScanInput<'_>) -> anyhow::Result<Staged<'s>> {
        let seed = scan_seed(input.topic, input.log_time);
        let out = Encoder {
            family: input.family,
            stamp: input.cloud.stamp_nanos,
            frame: input.cloud.frame_id.clone(),
        };
        if !input.covered
            && let Some(census) = input.census
        {
            return Ok(Staged::Done(self.prior_free(
                input.image,
                (census, input.fill_check),
                seed,
                &out,
            )));
        }
        let rates =
            (self.x_n_weight).and_then(|w| Some((w, input.census?.rates_for(input.image, true)?)));
        let finish = |decoded: &Decoded| self.outputs(decoded, input.image, rates.as_ref(), &out);
        let Some(chain) = input.chain else {
            let decoded = self.decoder.decode(input.image, seed)?;
            return Ok(Staged::Done(finish(&decoded)));
        };
        let mut state = chain.lock().unwrap_or_else(|e| e.into_inner());
        let Some(hand_off) = self.hand_off else {
            let decoded = (self.decoder).decode_from(input.image, seed, state.as_ref())?;
            *state = Some(decoded.tuned_generator().clone());
            drop(state);
            // The outputs (renderings on the sensor's grids, the completion) wait for nothing
            // of the chain's next scan: they run beside its tuning, so a chain that finishes
            // its batch first lends its core to the other's outputs.
            let image = input.image.clone();
            return Ok(Staged::Later(Box::new(move || {
                Ok(self.outputs(&decoded, &image, rates.as_ref(), &out))
            })));
        };
        let (handed, partial) =
            (self.decoder).begin(input.image, seed, state.as_ref(), hand_off)?;
        *state = Some(handed);
        // The rest runs after this scan's input is gone: it keeps its own copy of the image.
        let image = input.image.clone();
        Ok(Staged::Later(Box::new(move || {
            let decoded = self.decoder.finish(partial);
            Ok(self.outputs(&decoded, &image, rates.as_ref(), &out))
        })))
    }

    /// The channels of one decoded scan, on the grid of `observed` (the scan as projected).
    /// With `rates` (the recording's own drop rates fitted on its other scans, and the weight
    /// of x_n against them) `raydrop_prob` and the masks combine the two. A decode from a
    /// restored (sparse) model grid writes the model grid, where the restoration is defined.
    fn outputs(
        &self,
        decoded: &Decoded,
        observed: &RangeImage,
        rates: Option<&(f32, Vec<f32>)>,
        out: &Encoder,
    ) -> Vec<StageOutput> {
        let (mut main, x_d, extra) = if decoded.restore.is_some() {
            let extra = self.grids(self.decoder.model_grid());
            let main = decoded.model_output(self.fill);
            let extra: Vec<_> = (extra.extra.iter())
                .map(|(suffix, grid)| (suffix.clone(), decoded.render_output(grid, self.fill)))
                .collect();
            (main, decoded.model.depth_m.clone(), extra)
        } else {
            let grids = self.grids(&observed.angles);
            // On the model grid (or one within a fraction of a degree of it, as an estimated
            // HDL-64E table is) the decode has rendered it already.
            let rendered = match near_grid(&grids.own.grid, &decoded.model.grid) {
                true => Rendered {
                    grid: grids.own.grid.clone(),
                    ..decoded.model.clone()
                },
                false => decoded.render_prepared(&grids.own),
            };
            let x_d = rendered.depth_m.clone();
            let extra = (grids.extra.iter())
                .map(|(suffix, grid)| {
                    let r = decoded.render_prepared(grid);
                    (suffix.clone(), fill_from(observed, &x_d, r, self.fill))
                })
                .collect();
            let model_grid = self.decoder.model_grid();
            let main = complete(observed, rendered, self.fill, model_grid, decoded.seed);
            (main, x_d, extra)
        };
        if let Some((weight, rates)) = rates.filter(|(_, r)| r.len() == main.drop_prob.len()) {
            combine_with_rates(&mut main.drop_prob, rates, *weight);
            // Rows outside the model's view have no x_n: the rates alone there.
            for k in (0..x_d.len()).filter(|&k| x_d[k] == 0.0) {
                main.drop_prob[k] = rates[k];
            }
        }
        let mut channels = vec![
            out.image("depth", &main.grid, &main.depth_m),
            out.image("x_d", &main.grid, &x_d),
        ];
        channels.extend(out.drop_channels(&main, self.mask_samples, decoded.seed));
        for (suffix, r) in &extra {
            channels.push(out.image(&format!("depth_{suffix}"), &r.grid, &r.depth_m));
            channels.push(out.points(&format!("points_{suffix}"), r));
        }
        channels
    }

    /// The channels of a scan no model covers, without a prior: `depth` the completion of
    /// its returns on its own grid ([`complete_without_prior`], with the topic's `check` of
    /// the prior-free hole fill), `raydrop_prob` the
    /// recording's own drop rates fitted on its other scans, the masks drawn from them, and
    /// no `x_d`. Extra grids are the returns interpolated edge-aware onto them.
    fn prior_free(
        &self,
        image: &RangeImage,
        (census, check): (&DropCensus, Option<&FillCheck>),
        seed: u64,
        out: &Encoder,
    ) -> Vec<StageOutput> {
        let rule = SurfaceRule::default();
        // A topic the first pass did not check (no scan of it projected there) is checked on
        // this scan alone.
        let own;
        let check = match check {
            Some(c) => c,
            None => {
                own = FillCheck::on(image, seed);
                &own
            }
        };
        let drop_prob = census
            .rates_for(image, true)
            .unwrap_or_else(|| row_rates(image));
        let main = Rendered {
            grid: image.angles.clone(),
            depth_m: complete_without_prior(image, self.fill, check),
            drop_prob,
        };
        let mut channels = vec![out.image("depth", &main.grid, &main.depth_m)];
        channels.extend(out.drop_channels(&main, self.mask_samples, seed));
        for (suffix, grid) in extra_grids(&image.angles, &self.upsample, &self.targets) {
            let depth_m = resample_by_surface(image, &grid, &rule, None).range_m;
            let r = Rendered {
                drop_prob: nearest_on(&main, &grid),
                grid,
                depth_m,
            };
            channels.push(out.image(&format!("depth_{suffix}"), &r.grid, &r.depth_m));
            channels.push(out.points(&format!("points_{suffix}"), &r));
        }
        channels
    }
}

/// The completed scan on `observed`'s own grid from the decoded scene `rendered` there
/// ([`complete_observed`]). The decoded hole fill misleads on a grid much finer than the
/// scan's returns, and on beams much sparser than `model_grid`'s, where the completion
/// without a prior does better (measured on held-out KITTI, `tests/completion.rs`); across a
/// sector without returns the decoded scene still knows more.
pub(super) fn complete(
    observed: &RangeImage,
    rendered: Rendered,
    fill: Fill,
    model_grid: &AngleGrid,
    seed: u64,
) -> Rendered {
    let mut main = complete_observed(observed, rendered, fill);
    let sparse = sparser_beams_than(&observed.angles, model_grid);
    if fill == Fill::Learned && (sparse || finer_than_returns(observed)) {
        let check = FillCheck::on(observed, seed);
        match sparse {
            true => complete_without_prior_but_across(observed, fill, &check, &mut main.depth_m),
            false => main.depth_m = complete_without_prior(observed, fill, &check),
        }
    }
    main
}

/// How far (radians) a pixel of a sensor's grid may look from the model grid's pixel for the
/// model's rendering to stand for a rendering of its own: a quarter of the HDL-64E's beam
/// spacing (an HDL-64E table estimated from a scan is within 0.06 deg of the model's).
const NEAR_GRID_RAD: f32 = 0.1 * std::f32::consts::PI / 180.0;

/// Whether grids `a` and `b` have the same size and every pixel of `a` looks within
/// [`NEAR_GRID_RAD`] of `b`'s.
fn near_grid(a: &AngleGrid, b: &AngleGrid) -> bool {
    let close = |x: &[f32], y: &[f32]| x.iter().zip(y).all(|(p, q)| (p - q).abs() <= NEAR_GRID_RAD);
    (a.height, a.width) == (b.height, b.width)
        && a.len() == b.len()
        && close(&a.elevation_rad, &b.elevation_rad)
        && close(&a.azimuth_rad, &b.azimuth_rad)
}

/// `r`'s drop probability on another grid (nearest pixel; 1 outside its rows).
fn nearest_on(r: &Rendered, grid: &AngleGrid) -> Vec<f32> {
    let mut source = RangeImage::empty(r.grid.clone());
    source.range_m = r.drop_prob.clone();
    let out = resample_image(&source, grid, Interpolation::Nearest).range_m;
    out.into_iter()
        .map(|p| if p > 0.0 { p } else { 1.0 })
        .collect()
}

/// Encodes one scan's channels with its family, stamp and frame.
pub(super) struct Encoder {
    pub family: Family,
    pub stamp: u64,
    pub frame: String,
}

impl Encoder {
    pub fn image(&self, suffix: &str, grid: &AngleGrid, values: &[f32]) -> StageOutput {
        StageOutput {
            suffix: suffix.to_string(),
            kind: Kind::Image,
            data: encode_f32_image(
                self.family,
                self.stamp,
                &self.frame,
                (grid.width, grid.height),
                values,
            ),
        }
    }

    /// `raydrop_prob`, `samples` masks drawn from it with `seed`, and `points` of the
    /// sensor-grid result `main`.
    pub fn drop_channels(&self, main: &Rendered, samples: usize, seed: u64) -> Vec<StageOutput> {
        let mut channels = vec![self.image("raydrop_prob", &main.grid, &main.drop_prob)];
        for (i, mask) in sample_masks(&main.drop_prob, samples, seed)
            .iter()
            .enumerate()
        {
            let suffix = match i {
                0 => "raydrop_mask".to_string(),
                i => format!("raydrop_mask_{i}"),
            };
            channels.push(self.mask(&suffix, &main.grid, mask));
        }
        channels.push(self.points("points", main));
        channels
    }

    pub fn mask(&self, suffix: &str, grid: &AngleGrid, mask: &[bool]) -> StageOutput {
        StageOutput {
            suffix: suffix.to_string(),
            kind: Kind::Image,
            data: encode_mask(
                self.family,
                self.stamp,
                &self.frame,
                (grid.width, grid.height),
                mask,
            ),
        }
    }

    /// The completed cloud: a point wherever `r` has a depth, with its range and x_n.
    pub fn points(&self, suffix: &str, r: &Rendered) -> StageOutput {
        let keep: Vec<usize> = (0..r.grid.len()).filter(|&k| r.depth_m[k] > 0.0).collect();
        let all = r.points();
        let xyz = keep.iter().map(|&k| all[k]).collect();
        let range: Vec<f32> = keep.iter().map(|&k| r.depth_m[k]).collect();
        let drop: Vec<f32> = keep.iter().map(|&k| r.drop_prob[k]).collect();
        StageOutput {
            suffix: suffix.to_string(),
            kind: Kind::Cloud,
            data: encode_points(
                self.family,
                self.stamp,
                &self.frame,
                xyz,
                &[("range", &range), ("raydrop_prob", &drop)],
            ),
        }
    }
}

//! The decoding stage through the spatial-latent model ([`crate::model::spatial`]): every
//! scan, of any sensor, decoded on its own grid in one forward pass.
//!
//! Channels: `x_d` the model's depth at every ray, `depth` the measured returns with the dropped
//! rays completed from the returns around them (where x_d still loses to that, measured), `raydrop_prob` x_n (rendered for each ray from an encoding that did
//! not see it), masks drawn from x_n, the completed cloud, and `depth_*`/`points_*` on the
//! extra grids (the sensor's grid upsampled, other sensors'), rendered from the same latent.
//! A restoration (`--restore-lines`, `--restore-fraction`) marks the rays it leaves out as
//! unknown and writes the scan's own grid.

use std::sync::{Arc, Mutex};

use super::stages::{Encoder, complete, extra_grids, suffix_of};
use super::{ScanInput, Staged};
use crate::decode::prior_free::{FillCheck, complete_without_prior};
use crate::decode::{Fill, Rendered, Sparsify, scan_seed};
use crate::lidar::{AngleGrid, RangeImage, SensorProfile};
use crate::model::spatial::decode::{
    Decoded, GridQueries, HostModel, blend_with_row_rates, checked_weight, encode, onto_queries,
    own_queries, render,
};
use crate::model::spatial::{Ray, SpatialModel};
use crate::util::rng::Rng;

/// A sensor grid's queries and those of its extra grids, prepared once.
struct SensorGrids {
    grid: AngleGrid,
    own: GridQueries,
    /// `(suffix, grid, queries)` per upsampling factor, then per target sensor.
    extra: Vec<(String, AngleGrid, GridQueries)>,
}

/// At most this many sensor grids are kept prepared (a topic whose angles change from scan
/// to scan prepares each scan's afresh).
const PREPARED_GRIDS: usize = 16;

pub struct SpatialStage {
    /// The model prepared for decoding on the host: one scan per thread, no tensor library.
    model: HostModel,
    mask_samples: usize,
    upsample: Vec<usize>,
    /// `(suffix, grid)` of each target sensor.
    targets: Vec<(String, AngleGrid)>,
    restore: Option<Sparsify>,
    fill: Fill,
    /// The grid whose beam spacing tells a sparse scan ([`complete`]): KITTI's 64 x 512.
    reference_grid: AngleGrid,
    prepared: Mutex<Vec<Arc<SensorGrids>>>,
}

/// What the stage writes besides the sensor-grid channels.
#[derive(Debug, Clone, Default)]
pub struct SpatialOutputs {
    pub mask_samples: usize,
    pub upsample: Vec<usize>,
    pub target_sensors: Vec<SensorProfile>,
    pub restore: Option<Sparsify>,
    /// What the dropped rays of `depth` hold: near returns a fill from the returns around
    /// them, x_d farther in ([`complete`]); [`Fill::Gan`]: x_d everywhere.
    pub fill: Fill,
}

impl SpatialStage {
    pub fn new(model: SpatialModel, outputs: &SpatialOutputs) -> anyhow::Result<Self> {
        if let Some(f) = outputs.upsample.iter().find(|f| !(1..=8).contains(*f)) {
            anyhow::bail!("--upsample {f}: factors from 1 to 8 are supported");
        }
        Ok(SpatialStage {
            model: HostModel::new(&model.net, &model.config),
            mask_samples: outputs.mask_samples,
            upsample: outputs.upsample.clone(),
            targets: (outputs.target_sensors.iter())
                .map(|p| (suffix_of(&p.name), p.angle_grid()))
                .collect(),
            restore: outputs.restore,
            fill: outputs.fill,
            reference_grid: SensorProfile::kitti_hdl64e().with_columns(512).angle_grid(),
            prepared: Mutex::new(Vec::new()),
        })
    }

    /// The channels [`run`](Self::run) writes (`raydrop_mask` stands for every mask; the
    /// upsampled grids, named by their size, follow each sensor's grid).
    pub fn channel_names(&self) -> Vec<String> {
        let mut names: Vec<String> = ["depth", "x_d", "raydrop_prob", "raydrop_mask", "points"]
            .map(String::from)
            .into();
        for (suffix, _) in &self.targets {
            names.extend([format!("depth_{suffix}"), format!("points_{suffix}")]);
        }
        names
    }

    pub fn run(&self, input: &ScanInput<'_>) -> anyhow::Result<Staged<'static>> {
        let seed = scan_seed(input.topic, input.log_time);
        let image = input.image;
        let grid = &image.angles;
        let rays = self.observed_rays(&image.range_m, grid, seed);
        let grids = self.grids(grid);
        let encoded = encode(&self.model, &rays, grid);
        let own = render(&self.model, &encoded, &grids.own);
        let on_extra: Vec<Decoded> = (grids.extra.iter())
            .map(|(_, _, q)| render(&self.model, &encoded, q))
            .collect();
        let out = Encoder {
            family: input.family,
            stamp: input.cloud.stamp_nanos,
            frame: input.cloud.frame_id.clone(),
        };
        // What the model saw as returns: a restoration's left-out rays are not among them.
        let mut observed = RangeImage::empty(grid.clone());
        for (k, r) in rays.iter().enumerate() {
            if let Ray::Return(m) = r {
                observed.range_m[k] = *m;
            }
        }
        let x_d = own.depth_m.clone();
        let mut own = own;
        let max_weight = self.model.config.x_n_weight;
        let weight = checked_weight(&own.drop_prob, &rays, grid.width, max_weight);
        blend_with_row_rates(&mut own.drop_prob, &rays, grid.width, weight);
        let rendered = Rendered {
            grid: grid.clone(),
            depth_m: own.depth_m,
            drop_prob: own.drop_prob,
        };
        // Measured on held-out KITTI at full resolution and on eight recordings of other
        // makes, x_d in the holes still loses to the completion of the scan's own returns,
        // so `depth` falls back to that completion; x_d stays in its own channel, and
        // `--upsample-method gan` puts it into `depth` instead.
        let main = match self.fill {
            Fill::Gan => complete(&observed, rendered, self.fill, &self.reference_grid, seed),
            fill => Rendered {
                depth_m: match input.fill_check {
                    // The topic's first scans checked where the learned fill helps.
                    Some(check) => complete_without_prior(&observed, fill, check),
                    None => {
                        complete_without_prior(&observed, fill, &FillCheck::on(&observed, seed))
                    }
                },
                ..rendered
            },
        };
        let mut channels = vec![
            out.image("depth", grid, &main.depth_m),
            out.image("x_d", grid, &x_d),
        ];
        channels.extend(out.drop_channels(&main, self.mask_samples, seed));
        for ((suffix, g, _), d) in grids.extra.iter().zip(on_extra) {
            let r = Rendered {
                grid: g.clone(),
                depth_m: d.depth_m,
                drop_prob: d.drop_prob,
            };
            channels.push(out.image(&format!("depth_{suffix}"), &r.grid, &r.depth_m));
            channels.push(out.points(&format!("points_{suffix}"), &r));
        }
        Ok(Staged::Done(channels))
    }

    /// The prepared queries of the sensor grid `own` and its extra grids.
    fn grids(&self, own: &AngleGrid) -> Arc<SensorGrids> {
        let mut prepared = self.prepared.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(found) = prepared.iter().find(|g| g.grid == *own) {
            return found.clone();
        }
        let grids = Arc::new(SensorGrids {
            grid: own.clone(),
            own: own_queries(&self.model, own),
            extra: (extra_grids(own, &self.upsample, &self.targets).into_iter())
                .map(|(suffix, g)| {
                    let q = onto_queries(&self.model, own, &g);
                    (suffix, g, q)
                })
                .collect(),
        });
        if prepared.len() < PREPARED_GRIDS {
            prepared.push(grids.clone());
        }
        grids
    }

    /// The scan's rays as the model sees them: returns and drops, with the rays a
    /// restoration leaves out unknown (seeded by the scan, so reruns agree).
    fn observed_rays(&self, range_m: &[f32], grid: &AngleGrid, seed: u64) -> Vec<Ray> {
        let mut rays = crate::model::spatial::decode::rays_of(range_m);
        match self.restore {
            Some(Sparsify::Lines(n)) => {
                let kept = Sparsify::kept_rows(n, grid.height);
                for (k, r) in rays.iter_mut().enumerate() {
                    if !kept.contains(&(k / grid.width.max(1))) {
                        *r = Ray::Unknown;
                    }
                }
            }
            Some(Sparsify::Fraction(f)) => {
                let mut rng = Rng::new(seed ^ 0x7265_7374); // "rest"
                for r in rays.iter_mut() {
                    if rng.uniform() >= f {
                        *r = Ray::Unknown;
                    }
                }
            }
            None => {}
        }
        rays
    }
}

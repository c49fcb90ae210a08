//! What a run writes as it trains: the checkpoint (replaced atomically) and the PNG
//! snapshots.

use std::path::Path;

use anyhow::{Context, Result};
use burn::module::Module;

use crate::model::data::RangeDataset;
use crate::util::rng::Rng;
use crate::util::tensor::tensor_to_vec;

use super::Trainer;
use super::start::{SELF_DECODER, SELF_DECODER_OPT};
use crate::train::config::TrainOptions;
use crate::train::run_dir::write_checkpoint;

impl Trainer {
    /// Write the checkpoint (a kill never leaves half a one).
    pub(super) fn checkpoint(&self, run_dir: &Path) -> Result<()> {
        write_checkpoint(run_dir, |tmp| {
            let save_err = |what: &str, e: burn::store::RecordError| {
                anyhow::anyhow!("failed to save {what}: {e}")
            };
            self.g
                .clone()
                .save_file(tmp.join("g.bpk"))
                .map_err(|e| save_err("g", e))?;
            self.g_ema
                .clone()
                .save_file(tmp.join("g_ema.bpk"))
                .map_err(|e| save_err("g_ema", e))?;
            self.d
                .clone()
                .save_file(tmp.join("d.bpk"))
                .map_err(|e| save_err("d", e))?;
            self.opt_g
                .save(tmp.join("opt_g.bpk"))
                .map_err(|e| save_err("opt_g", e))?;
            self.opt_d
                .save(tmp.join("opt_d.bpk"))
                .map_err(|e| save_err("opt_d", e))?;
            if let Some(s) = &self.self_decoder {
                s.decoder
                    .clone()
                    .save_file(tmp.join(SELF_DECODER))
                    .map_err(|e| save_err("the self-supervised decoder", e))?;
                s.opt
                    .save(tmp.join(SELF_DECODER_OPT))
                    .map_err(|e| save_err("the self-supervised decoder's optimiser", e))?;
            }
            if let Some(w) = &self.whole {
                w.save(tmp)?;
            }
            if let Some(e) = &self.encoder {
                e.encoder
                    .clone()
                    .save_file(tmp.join("e.bpk"))
                    .map_err(|err| save_err("e", err))?;
                e.opt
                    .save(tmp.join("opt_e.bpk"))
                    .map_err(|err| save_err("opt_e", err))?;
            }
            std::fs::write(
                tmp.join("state.json"),
                serde_json::to_string_pretty(&self.state)?,
            )?;
            Ok(())
        })
    }

    /// PNG: for 4 fixed latents (EMA generator) the rows x_d | x_n (drop prob) | x_G, then
    /// 2 real scans.
    pub(super) fn snapshot(&mut self, opts: &TrainOptions, data: &RangeDataset) -> Result<()> {
        let (h, w) = (self.level.height, self.level.width);
        // Whole turns, also where the level trains on windows.
        let grid = (self.full_grid.as_ref()).map(|(_, inner)| self.level.grid(inner));
        let (out, _) = self
            .g_ema
            .generate(self.snapshot_z.clone(), grid.as_ref(), None);
        let x_d = tensor_to_vec(out.x_d.clone());
        let (x_n, x_g) = match out.keep_logit.clone() {
            Some(logit) => {
                let keep = tensor_to_vec(burn::tensor::activation::sigmoid(logit.clone()));
                let x_n: Vec<f32> = keep.iter().map(|k| 2.0 * (1.0 - k) - 1.0).collect();
                let mut rng = Rng::new(self.state.step);
                let m = self.config.measurement.measure(out.x_d, logit, &mut rng);
                (x_n, tensor_to_vec(m.x_measured))
            }
            None => (vec![-1.0; x_d.len()], x_d.clone()),
        };
        let n = h * w;
        let mut rows: Vec<&[f32]> = Vec::new();
        for i in 0..4 {
            rows.push(&x_d[i * n..(i + 1) * n]);
            rows.push(&x_n[i * n..(i + 1) * n]);
            rows.push(&x_g[i * n..(i + 1) * n]);
        }
        let reals =
            [0, data.len() / 2].map(|i| self.level.sample(data.image(i), data.width, (0, 0)));
        rows.extend(reals.iter().map(|r| r.as_slice()));
        let path = opts
            .run_dir
            .join("snapshots")
            .join(format!("{:09}.png", self.state.images));
        write_png(&path, &rows, h, w)
    }
}

/// Stack `[H, W]` images (network units, -1 = black) vertically into one grayscale PNG,
/// with a gamma that keeps far (small inverse depth) pixels visible.
pub fn write_png(path: &Path, images: &[&[f32]], h: usize, w: usize) -> Result<()> {
    let mut pixels = Vec::with_capacity(images.len() * (h + 2) * w);
    for img in images {
        for v in img.iter() {
            let x = ((v + 1.0) * 0.5).clamp(0.0, 1.0).sqrt();
            pixels.push((x * 255.0).round() as u8);
        }
        pixels.extend(std::iter::repeat_n(128u8, 2 * w)); // separator
    }
    let png = crate::util::png::encode_gray(w as u32, (images.len() * (h + 2)) as u32, &pixels)?;
    crate::util::fs::write_atomic(path, &png)
        .with_context(|| format!("failed to write '{}'", path.display()))
}

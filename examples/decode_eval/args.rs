//! The example's command line.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use rangegan_mcap::decode::Schedule;

pub(crate) struct Args {
    pub(crate) data: PathBuf,
    pub(crate) paper_scans: usize,
    pub(crate) fast_scans: usize,
    pub(crate) encoder: Option<PathBuf>,
    pub(crate) model: Option<PathBuf>,
    pub(crate) out: Option<PathBuf>,
    /// `w_steps,w_lr,tune_steps,tune_lr,tune_decay,tune_w_lr[,coarse_steps]` of the fast path
    /// (default: `Schedule::fast()`); coarse steps `..:quarter:half` (coarsest first) bring the full-resolution
    /// steps' rate decay to 0.
    pub(crate) fast_schedule: Option<Schedule>,
    /// Stop after the reconstruction numbers (for tuning the fast schedule).
    pub(crate) only_reconstruction: bool,
    pub(crate) only_raydrop: bool,
    /// Write the ray-drop reliability curves here (PNG).
    pub(crate) png: Option<PathBuf>,
    /// Also run the row upsampling / restoration cases with `paper` decodes on this many scans.
    pub(crate) sparse_paper_scans: usize,
    /// Also decode this many scans with the paper's own schedule from w_avg (`Schedule::reference`).
    pub(crate) reference_scans: usize,
    /// Only the upsampling and restoration cases (skip reconstruction and calibration).
    pub(crate) only_sparse: bool,
    /// Tune the surface rule of the guided and edge-aware fills on this many TRAINING scans
    /// (never the held-out ones) and stop.
    pub(crate) tune: Option<usize>,
    /// Measure on every third scan of this folder of `--data` instead of the held-out scans:
    /// a drive left out of training, for choosing settings without the held-out scans.
    pub(crate) validation: Option<String>,
}

pub(crate) fn parse_args() -> Result<Args> {
    let mut a = Args {
        data: PathBuf::from("../shared/real_lidar"),
        paper_scans: 2,
        fast_scans: usize::MAX,
        encoder: None,
        model: None,
        out: None,
        fast_schedule: None,
        only_reconstruction: false,
        only_raydrop: false,
        png: None,
        sparse_paper_scans: 0,
        reference_scans: 0,
        only_sparse: false,
        validation: None,
        tune: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--data" => a.data = PathBuf::from(value()?),
            "--paper-scans" => a.paper_scans = value()?.parse()?,
            "--fast-scans" => a.fast_scans = value()?.parse()?,
            "--encoder" => a.encoder = Some(PathBuf::from(value()?)),
            "--model" => a.model = Some(PathBuf::from(value()?)),
            "--out" => a.out = Some(PathBuf::from(value()?)),
            "--png" => a.png = Some(PathBuf::from(value()?)),
            "--sparse-paper-scans" => a.sparse_paper_scans = value()?.parse()?,
            "--reference-scans" => a.reference_scans = value()?.parse()?,
            "--only-reconstruction" => a.only_reconstruction = true,
            "--only-raydrop" => a.only_raydrop = true,
            "--only-sparse" => a.only_sparse = true,
            "--validation" => a.validation = Some(value()?),
            "--tune" => a.tune = Some(value()?.parse()?),
            "--fast-schedule" => {
                let v = value()?;
                let p: Vec<&str> = v.split(',').collect();
                if p.len() != 6 && p.len() != 7 {
                    bail!(
                        "--fast-schedule w_steps,w_lr,tune_steps,tune_lr,tune_decay(0|1),tune_w_lr[,coarse_steps[:coarser..]]"
                    );
                }
                let coarse_steps: Vec<usize> = p
                    .get(6)
                    .map(|c| c.split(':').map(str::parse).collect::<Result<_, _>>())
                    .transpose()?
                    .unwrap_or_default();
                a.fast_schedule = Some(Schedule {
                    w_steps: p[0].parse()?,
                    w_lr: p[1].parse()?,
                    tune_steps: p[2].parse()?,
                    tune_lr: p[3].parse()?,
                    tune_decay: p[4] == "1",
                    tune_w_lr: p[5].parse()?,
                    pyramid_levels: 2,
                    coarse_steps,
                    ..Schedule::fast()
                });
            }
            other => bail!("unknown flag {other}"),
        }
    }
    Ok(a)
}

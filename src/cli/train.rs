//! `rangegan-mcap train RUN_DIR`: train the range-image GAN (DUSty v2 or a baseline) on the
//! scans of one sensor (MCAP recordings, or KITTI's folders) or on simulated scans of its
//! beam layout; an existing run directory resumes from its checkpoint.

use std::path::{Path, PathBuf};

use anyhow::Context;
use std::time::Duration;

use super::{GlobalArgs, Outcome};
use crate::lidar::{SensorProfile, Strategy};
use crate::model::Arch;
use crate::model::discriminator::DiscriminatorConfig;
use crate::model::generator::GeneratorConfig;
use crate::physics::pretraining::PretrainingSet;
use crate::pipeline::SensorChoice;
use crate::train::growth::{Stage, parse_stage};
use crate::train::reconstruct::ReconstructionConfig;
use crate::train::regularise::DRegularisation;
use crate::train::scans::{Layout, ScanSource, load_dataset};
use crate::train::widen::widen_run;
use crate::train::{
    Backend, CHECKPOINT, SIMULATED_SCANS, TrainConfig, TrainOptions, load_config, run,
};

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum ArchArg {
    /// Implicit generator + ray-drop measurement model (the paper's method).
    Dusty2,
    /// Transposed-conv generator + measurement model.
    Dusty1,
    /// Transposed-conv generator on raw images.
    Vanilla,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum BackendArg {
    /// burn-flex on the CPU cores (the default; fastest on CPU here).
    Flex,
    /// burn-ndarray on the CPU cores.
    Ndarray,
    /// An NVIDIA GPU through CUDA (a build with `--features cuda`).
    Cuda,
    /// A GPU through wgpu: Vulkan, Metal or DirectX (a build with `--features wgpu`).
    Wgpu,
}

impl From<BackendArg> for Backend {
    fn from(arg: BackendArg) -> Self {
        match arg {
            BackendArg::Flex => Backend::Flex,
            BackendArg::Ndarray => Backend::Ndarray,
            BackendArg::Cuda => Backend::Cuda,
            BackendArg::Wgpu => Backend::Wgpu,
        }
    }
}

/// How recordings' clouds become range images: the `convert` flags of the same names.
#[derive(Debug, Clone, clap::Args)]
pub struct LayoutArgs {
    /// The point-cloud topic of the recordings (default: each one's only or first).
    #[arg(long)]
    pub topic: Option<String>,
    #[arg(long, default_value = "auto", help = super::convert::SENSOR_HELP)]
    pub sensor: String,
    /// Range-image columns (default: the profile's; KITTI folders: 512).
    #[arg(long)]
    pub columns: Option<usize>,
    /// How each point finds its row.
    #[arg(long, value_enum, default_value = "auto")]
    pub projection: Strategy,
}

impl LayoutArgs {
    pub(crate) fn layout(&self) -> anyhow::Result<Layout> {
        let sensor = match super::convert::sensor_choice(&self.sensor)? {
            SensorChoice::Auto => None,
            SensorChoice::Fixed(p) => Some(p),
        };
        if let Some(c) = self.columns {
            crate::lidar::profile::check_columns(c)
                .map_err(|e| anyhow::anyhow!("--columns: {e}"))?;
        }
        Ok(Layout {
            topic: self.topic.clone(),
            sensor,
            columns: self.columns,
            strategy: self.projection,
        })
    }
}

/// What every resumable training run takes: where it lives, its data, when to stop, its seed.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Run directory (config.json, checkpoint/, log.jsonl, ...). Resumes if it exists.
    pub run_dir: PathBuf,
    /// The real scans (repeatable): MCAP recordings and folders of them, all of one sensor;
    /// or one KITTI folder of kitti_raw_* drives and semantickitti_mini/ (sequences 00 and
    /// 07 held out). Not needed once the dataset cache exists.
    #[arg(long, value_name = "PATH")]
    pub data: Vec<PathBuf>,
    #[command(flatten)]
    pub layout: LayoutArgs,
    /// Projected-dataset cache (default: RUN_DIR/dataset.bin).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Stop (with a checkpoint) after this many minutes.
    #[arg(long)]
    pub max_minutes: Option<f64>,
    /// Seed of a new run.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Set this KITTI raw drive (a folder name such as `kitti_raw_drive_d`) or recording
    /// (its file name, with or without `.mcap`) aside for validation: it is left out of the
    /// training scans when the dataset cache is built. Repeatable.
    #[arg(
        long,
        value_name = "DRIVE|RECORDING",
        visible_alias = "validation-recording"
    )]
    pub validation_drive: Vec<String>,
    /// Backend to compute on; a run may resume on another one.
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendArg,
}

impl RunArgs {
    pub(crate) fn cache_path(&self) -> PathBuf {
        self.cache
            .clone()
            .unwrap_or_else(|| self.run_dir.join("dataset.bin"))
    }

    /// The real scans to build the dataset cache from: every training scan but the
    /// validation drives or recordings. None where the cache exists already, so a machine
    /// that holds only the cache (a GPU host, say) needs no scans.
    pub(crate) fn source(&self) -> anyhow::Result<Option<ScanSource>> {
        if self.cache_path().exists() {
            return Ok(None);
        }
        Ok(Some(ScanSource {
            data: self.data.clone(),
            validation: self.validation_drive.clone(),
            layout: self.layout.layout()?,
        }))
    }

    pub(crate) fn max_duration(&self) -> Option<Duration> {
        self.max_minutes.map(|m| Duration::from_secs_f64(m * 60.0))
    }
}

#[derive(Debug, clap::Args)]
pub struct TrainArgs {
    #[command(flatten)]
    pub run: RunArgs,
    /// Architecture of a new run.
    #[arg(long, value_enum, default_value = "dusty2")]
    pub arch: ArchArg,
    /// Batch size of a new run (1 to 4096).
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=4096))]
    pub batch: Option<usize>,
    /// Stop after this many real images (also extends a resumed run).
    #[arg(long)]
    pub total_images: Option<u64>,
    /// Use the paper's network widths instead of the CPU ones.
    #[arg(long)]
    pub reference_size: bool,
    /// Pretrain on this many simulated scans (many procedural scenes, `realistic` physics
    /// with randomised strengths) instead of real ones, ray-cast with the sensor of
    /// `--sensor` at `--columns` (default: KITTI's HDL-64E at 512 columns); then fine-tune
    /// on that sensor's recordings with `--init-from`.
    #[arg(long, value_name = "N")]
    pub sim_scans: Option<usize>,
    /// Start a new run from a pretrained run (or model directory) and fine-tune it: its
    /// architecture and settings are taken over, the image count starts at 0 and the early
    /// pixel dropout is off.
    #[arg(long, value_name = "DIR")]
    pub init_from: Option<PathBuf>,
    /// A new run's discriminator folds each 2 x 2 block of pixels into channels and leaves
    /// out the full-resolution block (the CPU widths from 16 channels): about two thirds
    /// of the time per training image.
    #[arg(long, conflicts_with = "reference_size")]
    pub half_resolution_discriminator: bool,
    /// With `--init-from`: train only the generator's ray-drop logit (starting from its EMA
    /// weights); its depth x_d, and so an encoder trained for it, stays as it was.
    #[arg(long, requires = "init_from")]
    pub drop_head_only: bool,
    /// Continue the training run in DIR at a larger generator width: its generator (and
    /// EMA) widened to `--channels` and `--fourier` without changing what it renders, with
    /// its discriminator, encoder and image count, in the new run directory. A resumed
    /// widened run ignores it.
    #[arg(
        long,
        value_name = "DIR",
        requires = "channels",
        conflicts_with = "init_from"
    )]
    pub widen_from: Option<PathBuf>,
    /// With `--widen-from`: channels per synthesis block, coarsest first (comma-separated).
    #[arg(long, value_delimiter = ',', requires = "widen_from")]
    pub channels: Vec<usize>,
    /// With `--widen-from`: Fourier frequency pairs per block (default: the run's).
    #[arg(long, value_delimiter = ',', requires = "widen_from")]
    pub fourier: Vec<usize>,
    /// A coarse-to-fine stage of a new run, `BLOCKS:IMAGES` (repeatable, in order): only the
    /// first BLOCKS synthesis blocks render, on a grid halved per block left out, for IMAGES
    /// real images, against a discriminator of that size; after the last stage every block
    /// renders the full grid. E.g. `--stage 3:300k --stage 4:300k` (dusty2).
    #[arg(long = "stage", value_name = "BLOCKS:IMAGES", value_parser = parse_stage)]
    pub stages: Vec<Stage>,
    /// Reconstruction-assisted training of a new run (dusty2) with this weight: an encoder
    /// in the generator's loop renders every real batch back, and the generator learns from
    /// the reconstruction beside the discriminator. 0 turns off what `--init-from`'s run had.
    #[arg(long, value_name = "WEIGHT")]
    pub reconstruction: Option<f32>,
    /// Train a new run (dusty2) at full resolution on windows of this many columns of the
    /// turn, at random azimuths: the generator renders only the window (about W/COLS times
    /// the images per second), the discriminator sees where each window is. With
    /// `--init-from`, a trained generator goes on learning detail this way.
    #[arg(long, value_name = "COLS", conflicts_with = "widen_from")]
    pub window: Option<usize>,
    /// With `--window`: every N steps, one step on whole turns against a discriminator of
    /// whole turns (started from `--init-from`'s where that run trained on whole turns), so
    /// the layout of the turn keeps a judge while the windows teach detail.
    #[arg(long, value_name = "N", requires = "window")]
    pub whole_every: Option<usize>,
    /// Show the discriminator simulated scans of the run's sensor as a share of its real
    /// ones, `SCANS:SHARE` (e.g. `4000:0.25`): SCANS are simulated once into
    /// `RUN_DIR/sim.bin` (as `--sim-scans` does). On a resumed run it replaces the saved
    /// share, so one checkpoint can be branched with and without them; `0:0` turns it off.
    #[arg(long, value_name = "SCANS:SHARE", value_parser = parse_sim_mix)]
    pub sim_mix: Option<(usize, f32)>,
    /// The discriminator's LeCam regulariser with this weight (0.1-0.3 for small data):
    /// D's logits on real and generated scans are kept from drifting apart. Any of
    /// `--lecam`, `--diff-augment`, `--apa` and `--self-supervised` on a resumed run replaces its saved
    /// regularisers with exactly those given, so one checkpoint can be branched into runs
    /// that compare them.
    #[arg(long, value_name = "WEIGHT")]
    pub lecam: Option<f32>,
    /// DiffAugment-style translation and cutout of every scan the discriminator sees.
    #[arg(long)]
    pub diff_augment: bool,
    /// Adaptive pseudo augmentation: the discriminator is shown some generated scans as
    /// real, as often as it overfits (the same measure as adaptive augmentation).
    #[arg(long)]
    pub apa: bool,
    /// A self-supervised discriminator (FastGAN): a small decoder rebuilds each real scan
    /// from the discriminator's last features, and this weight puts that loss into the
    /// discriminator's (1 is FastGAN's). Branches a resumed run as `--lecam` does.
    #[arg(long, value_name = "WEIGHT")]
    pub self_supervised: Option<f32>,
}

pub fn run_train(global: &GlobalArgs, args: TrainArgs) -> anyhow::Result<Outcome> {
    // Before any data is read or written: a backend this build lacks is a usage error.
    Backend::from(args.run.backend).device()?;
    // A resumed run's settings are checked before any data is read or anything is sized.
    let saved = args.run.run_dir.join("config.json");
    if saved.exists() {
        let run = load_config(&saved)?;
        anyhow::ensure!(
            args.window.is_none() || args.window == run.window,
            "'{}' trains on {}: a run keeps its windows (start a branch with --init-from)",
            args.run.run_dir.display(),
            run.window.map_or("whole turns".to_string(), |c| format!(
                "windows of {c} columns"
            ))
        );
        anyhow::ensure!(
            args.whole_every.is_none() || args.whole_every == run.whole_every,
            "'{}' keeps the whole-turn steps it started with (start a branch with --init-from)",
            args.run.run_dir.display()
        );
    }
    let mut config = match &args.init_from {
        // A fine-tuning run keeps the pretrained network's shapes and recipe; it is past the
        // early pixel-dropout phase, and its image budget is its own.
        // Its source trained every block: it starts at full resolution.
        Some(src) => load_config(&src.join("config.json"))?
            .with_pixel_drop_start(0.0)
            .with_total_images(TrainConfig::new().total_images)
            .with_stages(Vec::new())
            .with_stage_discriminators(Vec::new()),
        None => TrainConfig::new().with_arch(match args.arch {
            ArchArg::Dusty2 => Arch::Dusty2,
            ArchArg::Dusty1 => Arch::Dusty1,
            ArchArg::Vanilla => Arch::Vanilla,
        }),
    };
    if args.reference_size {
        config = config
            .with_generator(GeneratorConfig::new())
            .with_discriminator(DiscriminatorConfig::new());
    }
    if args.half_resolution_discriminator {
        config = config.with_discriminator(DiscriminatorConfig::cpu_half_resolution());
    }
    if let Some(b) = args.batch {
        config = config.with_batch_size(b);
    }
    if args.drop_head_only {
        anyhow::ensure!(
            config.arch == Arch::Dusty2,
            "--drop-head-only needs a dusty2 generator (the run in --init-from is {:?})",
            config.arch
        );
        config = config.with_drop_head_only(true);
    }
    if let Some(weight) = args.reconstruction {
        anyhow::ensure!(
            weight.is_finite() && weight >= 0.0,
            "--reconstruction must be a weight >= 0 (0: off)"
        );
        config = config.with_reconstruction(
            (weight > 0.0).then(|| ReconstructionConfig::new().with_weight(weight)),
        );
    }
    if let Some(columns) = args.window {
        config = config
            .with_window(Some(columns))
            .with_whole_every(args.whole_every);
    }
    let any = args.lecam.is_some() || args.diff_augment || args.apa;
    let regularisation = (any || args.self_supervised.is_some()).then(|| {
        DRegularisation::new()
            .with_lecam(args.lecam.unwrap_or(0.0))
            .with_diff_augment(args.diff_augment)
            .with_apa(args.apa)
            .with_self_supervised(args.self_supervised.unwrap_or(0.0))
    });
    for (flag, weight) in [
        ("--lecam", args.lecam),
        ("--self-supervised", args.self_supervised),
    ] {
        if let Some(w) = weight {
            anyhow::ensure!(w.is_finite() && w >= 0.0, "{flag} must be a weight >= 0");
        }
    }
    if let Some(r) = &regularisation {
        config = config.with_regularisation(r.clone());
    }
    if !args.stages.is_empty() {
        config = config.with_stages(args.stages.clone());
    }
    if let Some(s) = args.run.seed {
        config = config.with_seed(s);
    }
    if let Some(src) = &args.widen_from {
        widen_once(src, &args)?;
    }
    let dataset_cache = args.run.cache_path();
    if let Some(n) = args.sim_scans {
        anyhow::ensure!(
            args.run.data.is_empty(),
            "--sim-scans trains on simulated scans only: drop --data (fine-tune on real ones with --init-from)"
        );
        let layout = args.run.layout.layout()?;
        let profile = layout
            .sensor
            .unwrap_or_else(SensorProfile::kitti_hdl64e)
            .with_columns(layout.columns.unwrap_or(crate::train::scans::KITTI_COLUMNS));
        build_simulated_cache(global, &dataset_cache, n, profile)?;
    }
    let source = match args.sim_scans {
        Some(_) => None,
        None => args.run.source()?,
    };
    config.check().context("the run's settings")?;
    if let Some((scans, share)) = args.sim_mix.filter(|&(_, share)| share > 0.0) {
        // The run's sensor; a new run learns it from its scans (the cache built here).
        let sensor = if saved.exists() {
            load_config(&saved)?.sensor
        } else {
            load_dataset(&dataset_cache, source.as_ref())?.profile
        };
        let cache = args.run.run_dir.join(SIMULATED_SCANS);
        build_simulated_cache(global, &cache, scans, sensor)?;
        config = config.with_sim_share(share);
    }
    let opts = TrainOptions {
        dataset_cache,
        max_duration: args.run.max_duration(),
        source,
        run_dir: args.run.run_dir,
        config,
        backend: args.run.backend.into(),
        total_images: args.total_images,
        progress: !global.quiet,
        init_from: args.init_from,
        regularisation,
        sim_share: args.sim_mix.map(|(_, share)| share),
    };
    run(&opts)?;
    Ok(Outcome::Success)
}

/// Parses `--sim-mix SCANS:SHARE`.
fn parse_sim_mix(text: &str) -> Result<(usize, f32), String> {
    let (scans, share) = text
        .split_once(':')
        .ok_or_else(|| format!("'{text}': expected SCANS:SHARE, e.g. 4000:0.25"))?;
    let scans = scans
        .parse::<usize>()
        .map_err(|e| format!("'{scans}': {e}"))?;
    let share = share
        .parse::<f32>()
        .map_err(|e| format!("'{share}': {e}"))?;
    if !(0.0..=1.0).contains(&share) || (share > 0.0 && scans == 0) {
        return Err(format!(
            "'{text}': the share is between 0 and 1, and a share above 0 needs scans"
        ));
    }
    Ok((scans, share))
}

/// Writes the widened run into the run directory, unless it holds a checkpoint (a resumed
/// widened run).
fn widen_once(src: &Path, args: &TrainArgs) -> anyhow::Result<()> {
    let dst = &args.run.run_dir;
    if dst.join(CHECKPOINT).join("state.json").exists() {
        return Ok(());
    }
    let n_freq = if args.fourier.is_empty() {
        load_config(&src.join("config.json"))?.generator.n_freq
    } else {
        args.fourier.clone()
    };
    let device = Backend::from(args.run.backend).device()?;
    widen_run(src, dst, args.channels.clone(), n_freq, &device)
}

/// Simulates the pretraining set into `cache` unless it is there already (a resumed run).
fn build_simulated_cache(
    global: &GlobalArgs,
    cache: &Path,
    scans: usize,
    profile: SensorProfile,
) -> anyhow::Result<()> {
    anyhow::ensure!(scans > 0, "--sim-scans must be > 0");
    if cache.exists() {
        return Ok(());
    }
    let bar = super::progress_bar(global, scans as u64);
    let set = PretrainingSet {
        scans,
        profile,
        ..Default::default()
    };
    let data = set.build(|n| bar.inc(n as u64));
    bar.finish_and_clear();
    if let Some(dir) = cache.parent() {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("failed to create '{}'", dir.display()))?;
    }
    data.save(cache)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sim_mix_takes_scans_and_a_share() {
        assert_eq!(parse_sim_mix("4000:0.25"), Ok((4000, 0.25)));
        assert_eq!(parse_sim_mix("0:0"), Ok((0, 0.0)));
        for bad in ["4000", "4000:1.5", "0:0.5", "x:0.1", "10:-0.1"] {
            assert!(parse_sim_mix(bad).is_err(), "{bad}");
        }
    }

    fn run_args(dir: &Path) -> RunArgs {
        RunArgs {
            run_dir: dir.join("run"),
            data: vec![dir.join("no-such-scans")],
            layout: LayoutArgs {
                topic: None,
                sensor: "auto".into(),
                columns: None,
                projection: Strategy::Auto,
            },
            cache: Some(dir.join("dataset.bin")),
            max_minutes: None,
            seed: None,
            validation_drive: vec!["kitti_raw_drive_d".into()],
            backend: BackendArg::Flex,
        }
    }

    #[test]
    fn an_existing_cache_needs_no_scan_folder() {
        let dir = tempfile::tempdir().unwrap();
        let args = run_args(dir.path());
        let source = args.source().unwrap().expect("no cache yet");
        let err = source.training().unwrap_err().to_string();
        assert!(err.contains("no-such-scans"), "{err}");
        std::fs::write(dir.path().join("dataset.bin"), b"cache").unwrap();
        assert!(args.source().unwrap().is_none());
    }
}

//! `rangegan-mcap render (--physics FITTED.json | --raydrop global|pixel --real REAL.mcap | --raydrop gan) SIM.mcap OUT.mcap`:
//! applies physics (typically what `diagnose` fitted) or a baseline ray-drop
//! model to every scan of a simulated recording: the Sim2Real use, realistic
//! ray drops on simulated training data. Every other record is copied unchanged.
//!
//! Baselines (the paper's Sim2Real configurations): `global` drops every ray
//! with the real data's global drop frequency (config B), `pixel` with its
//! per-pixel frequency (config C), `gan` (config E) with the GAN's drop
//! probability x_n of each scan: the scan is auto-decoded (`fast`), x_n rendered on
//! its grid and every ray dropped by a Bernoulli draw seeded from (topic, log time);
//! `--drop-sharpness` first concentrates x_n's drops where it is highest (`decode::sharpen`).

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::{Path, PathBuf};

use anyhow::Context;
use mcap::records::Record;

use super::{GlobalArgs, Outcome};
use crate::decode::{sample_masks, scan_seed, sharpen_drop_prob};
use crate::diagnose::completion::par_gan_render;
use crate::diagnose::real_scan::as_sim_scan;
use crate::io::encoders::encode_scan;
use crate::io::{ChannelTable, DecodedCloud, McapOutput, OnError, decode_cloud, read_records};
use crate::lidar::projection::choose_strategy;
use crate::lidar::{SensorProfile, project};
use crate::physics::dropout::DropMap;
use crate::physics::{Physics, PhysicsConfig};
use crate::recording::{self, Grid};
use crate::sim::SimScan;

/// A baseline ray-drop model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum RayDrop {
    /// The real data's global drop frequency (paper config B).
    Global,
    /// The real data's per-pixel drop frequency (paper config C).
    Pixel,
    /// The GAN's auto-decoded drop probability x_n per scan (paper config E).
    Gan,
}

#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// Physics to apply: a physics JSON file (e.g. DIR/fitted_physics.json from
    /// `diagnose`) or a preset (ideal, carla-like, realistic).
    #[arg(long, conflicts_with = "raydrop")]
    pub physics: Option<String>,
    /// A baseline ray-drop model instead of physics.
    #[arg(long, value_enum)]
    pub raydrop: Option<RayDrop>,
    /// The real recording whose drop frequencies `--raydrop global|pixel` use.
    #[arg(long)]
    pub real: Option<PathBuf>,
    #[command(flatten)]
    pub gan: super::diagnose::GanArgs,
    /// With `--raydrop gan`: sharpen each scan's x_n by this factor on the logit scale
    /// before drawing, keeping the scan's mean drop probability (1: draw from x_n as it is).
    /// Above 1, drops gather where x_n is highest instead of speckling whole surfaces.
    #[arg(long, default_value_t = 1.0)]
    pub drop_sharpness: f32,
    /// Point-cloud topic (default: the first point-cloud topic).
    #[arg(long)]
    pub topic: Option<String>,
    /// Sensor profile of the projection (default: the recording's `simulate`
    /// metadata, else estimated).
    #[arg(long)]
    pub sensor: Option<String>,
    /// Range-image columns (default: the profile's).
    #[arg(long)]
    pub columns: Option<usize>,
    /// Seed of the random draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Overwrite an existing OUT.
    #[arg(long)]
    pub force: bool,
    /// Leave no OUT and exit 3 if any scan had to be skipped (otherwise each is a warning
    /// and the record is copied unchanged).
    #[arg(long)]
    pub strict: bool,
    /// Simulated input recording.
    pub input: PathBuf,
    /// Output recording.
    pub output: PathBuf,
}

/// Drop probability per pixel of the grid (row-major), from real data.
/// Drops each return of `scan` with its probability in `drop_prob` (row-major on
/// the scan's grid): one Bernoulli draw per pixel from `seed`.
fn drop_bernoulli(scan: &mut SimScan, drop_prob: &[f32], seed: u64) {
    let Some(keep) = sample_masks(drop_prob, 1, seed).pop() else {
        return;
    };
    for (k, keep) in keep.into_iter().enumerate().take(scan.len()) {
        if !keep && scan.is_return(k) {
            scan.drop_return(k);
        }
    }
}

/// The physics to apply, and words for the summary.
fn resolve_physics(
    args: &RenderArgs,
    profile: &SensorProfile,
) -> anyhow::Result<(Physics, String)> {
    match (&args.physics, args.raydrop) {
        (Some(p), None) => {
            let config = PhysicsConfig::resolve_for_beams(p, profile.beams())
                .with_context(|| format!("--physics {p}"))?;
            config
                .validate(p, Some(profile.beams()))
                .with_context(|| format!("--physics {p} for sensor {}", profile.name))?;
            let physics = config.effects();
            let words = format!("physics [{}]", physics.ids().join(", "));
            Ok((physics, words))
        }
        (None, Some(RayDrop::Gan)) => Ok((Physics { effects: vec![] }, String::new())),
        (None, Some(mode)) => {
            let real_path = args.real.as_ref().context(
                "--raydrop global|pixel needs --real REAL.mcap (the recording whose drop frequencies to use)",
            )?;
            let real = recording::read(
                real_path,
                args.topic.as_deref(),
                &Grid::Fixed(profile.clone()),
            )
            .with_context(|| format!("reading --real {}", real_path.display()))?;
            let n = profile.beams() * profile.columns;
            let mut dropped = vec![0f64; n];
            for img in &real.images {
                for (k, d) in dropped.iter_mut().enumerate() {
                    *d += f64::from(u8::from(!img.is_valid(k)));
                }
            }
            let scans = real.images.len() as f64;
            let (id, prob) = if mode == RayDrop::Global {
                let rate = dropped.iter().sum::<f64>() / (scans * n as f64);
                ("raydrop_global", vec![rate as f32; n])
            } else {
                (
                    "raydrop_pixel",
                    dropped.iter().map(|d| (d / scans) as f32).collect(),
                )
            };
            let mean = prob.iter().map(|p| f64::from(*p)).sum::<f64>() / n.max(1) as f64;
            let words = format!(
                "{id} from {} scans of {} (mean drop probability {:.1} %)",
                real.images.len(),
                real_path.display(),
                100.0 * mean
            );
            Ok((
                Physics {
                    effects: vec![Box::new(DropMap {
                        id,
                        width: profile.columns,
                        prob,
                    })],
                },
                words,
            ))
        }
        (None, None) => anyhow::bail!("give --physics FILE or --raydrop global|pixel|gan"),
        (Some(_), Some(_)) => anyhow::bail!("--physics and --raydrop exclude each other"),
    }
}

pub fn run(global: &GlobalArgs, args: RenderArgs) -> anyhow::Result<Outcome> {
    check_args(&args)?;
    let gan = args.raydrop == Some(RayDrop::Gan);
    let grid = grid(&args)?;
    let input = recording::read(&args.input, args.topic.as_deref(), &grid)
        .with_context(|| format!("reading {}", args.input.display()))?;
    let profile = input.profile.clone();
    let (physics, mut words) = resolve_physics(&args, &profile)?;
    // --raydrop gan: x_n of every scan, decoded up front (rayon over scans), by log time.
    let mut gan_drop = HashMap::new();
    if gan {
        (gan_drop, words) = gan_drop_probabilities(&args, &input)?;
    }
    let speed = input.speed_mps().unwrap_or(0.0) as f32;

    let mut out = McapOutput::create(&args.output, args.force)?;
    out.write_metadata(
        "rangegan.render",
        BTreeMap::from([
            ("tool".to_string(), "rangegan-mcap render".to_string()),
            ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
            ("topic".to_string(), input.topic.clone()),
            ("applied".to_string(), words.clone()),
            ("seed".to_string(), args.seed.to_string()),
        ]),
    )?;
    let mut table = ChannelTable::default();
    let mut strategy = None;
    let (mut scans, mut kept, mut pixels, mut skipped) = (0u64, 0u64, 0u64, Vec::new());
    let file = std::fs::File::open(&args.input)
        .with_context(|| format!("cannot open {}", args.input.display()))?;
    let len = file.metadata().ok().map(|m| m.len());
    read_records(
        std::io::BufReader::new(file),
        len,
        OnError::Fail,
        |record| {
            table.observe(record);
            let ours = |id: u16| {
                table
                    .get(id)
                    .filter(|c| c.topic == input.topic)
                    .and_then(|c| c.cloud)
            };
            if let Record::Message { header, data } = record
                && let Some(format) = ours(header.channel_id)
            {
                let rendered = decode_cloud(format, data)
                    .map_err(|e| e.to_string())
                    .and_then(|cloud| {
                        let s =
                            *strategy.get_or_insert_with(|| choose_strategy(&cloud.scan, &profile));
                        let image = project(&cloud.scan, &profile, s).map_err(|e| e.to_string())?;
                        let mut scan = as_sim_scan(image, scans as u32, &profile, speed);
                        physics.apply(&mut scan, args.seed);
                        if gan {
                            let prob = gan_drop
                                .get_mut(&header.log_time)
                                .and_then(VecDeque::pop_front)
                                .unwrap_or_else(|| Err("not among the decoded scans".into()))
                                .map_err(|e| format!("auto-decoding: {e}"))?;
                            let seed = scan_seed(&input.topic, header.log_time)
                                ^ args.seed.wrapping_mul(0x9e37_79b9_7f4a_7c15);
                            let prob = sharpen_drop_prob(&prob, args.drop_sharpness);
                            drop_bernoulli(&mut scan, &prob, seed);
                        }
                        kept += scan.image.valid_count() as u64;
                        pixels += scan.len() as u64;
                        let out_cloud = DecodedCloud {
                            scan: scan.to_scan(cloud.scan.is_organized()),
                            stamp_nanos: cloud.stamp_nanos,
                            frame_id: cloud.frame_id,
                            notes: Vec::new(),
                        };
                        Ok(encode_scan(format.family(), &out_cloud, &[]))
                    });
                match rendered {
                    Ok(bytes) => {
                        scans += 1;
                        out.copy_record(&Record::Message {
                            header: *header,
                            data: Cow::Owned(bytes),
                        })?;
                        return Ok(());
                    }
                    Err(e) => skipped.push(format!(
                        "{}: {e}; message copied unchanged",
                        crate::error::Location::message(&args.input, &input.topic, header.log_time)
                    )),
                }
            }
            out.copy_record(record)?;
            Ok(())
        },
        |_| {},
    )
    .map_err(|e| e.for_strict_reader(&args.input))?;
    finish(
        global,
        &args,
        &input.topic,
        out,
        (scans, kept as f64 / pixels.max(1) as f64),
        &words,
        &skipped,
    )
}

/// Refuses arguments that cannot work before anything is read: an output that would replace
/// an input, a bad column count, GAN options without `--raydrop gan`, and `--real` with it.
fn check_args(args: &RenderArgs) -> anyhow::Result<()> {
    let physics_file = args
        .physics
        .as_deref()
        .map(Path::new)
        .filter(|p| p.is_file());
    let sensor_file = args
        .sensor
        .as_deref()
        .map(Path::new)
        .filter(|p| p.is_file());
    let inputs: Vec<&Path> = std::iter::once(args.input.as_path())
        .chain(args.real.as_deref())
        .chain(physics_file)
        .chain(args.gan.model.as_deref())
        .chain(args.gan.encoder.as_deref())
        .chain(sensor_file)
        .collect();
    crate::io::writer::refuse_overwriting_inputs(&args.output, &inputs)?;
    if let Some(c) = args.columns {
        crate::lidar::profile::check_columns(c).map_err(anyhow::Error::msg)?;
    }
    let gan = args.raydrop == Some(RayDrop::Gan);
    anyhow::ensure!(
        gan || (!args.gan.given() && args.drop_sharpness == 1.0),
        "--model, --encoder, --tune-steps and --drop-sharpness are for --raydrop gan"
    );
    anyhow::ensure!(
        args.drop_sharpness.is_finite() && args.drop_sharpness > 0.0,
        "--drop-sharpness must be a factor > 0 (1: x_n as it is)"
    );
    anyhow::ensure!(
        !gan || args.real.is_none(),
        "--raydrop gan takes no --real (the drop probability comes from each simulated scan)"
    );
    Ok(())
}

/// The grid to project on: `--sensor` (with `--columns`), else estimated from the recording.
fn grid(args: &RenderArgs) -> anyhow::Result<Grid> {
    Ok(match &args.sensor {
        Some(s) => {
            let p = SensorProfile::resolve(s).with_context(|| format!("--sensor {s}"))?;
            Grid::Fixed(match args.columns {
                Some(c) => p.with_columns(c),
                None => p,
            })
        }
        None => Grid::FromRecording {
            columns: args.columns,
        },
    })
}

/// Each scan's x_n (or why it could not be decoded), queued by log time.
type DropQueues = HashMap<u64, VecDeque<Result<Vec<f32>, String>>>;

/// `--raydrop gan`: x_n of every scan, auto-decoded up front (rayon over scans), queued by log
/// time; and the words that describe what was applied.
fn gan_drop_probabilities(
    args: &RenderArgs,
    input: &recording::Recording,
) -> anyhow::Result<(DropQueues, String)> {
    let mut gan_drop = DropQueues::new();
    let decoder = args.gan.decoder(None).context("--raydrop gan")?;
    let seeds: Vec<u64> = input
        .log_times
        .iter()
        .map(|t| scan_seed(&input.topic, *t))
        .collect();
    let probs = par_gan_render(&decoder, &input.images, &seeds, |_, r| r.drop_prob);
    let (mut sum, mut n) = (0f64, 0usize);
    for p in probs.iter().flatten() {
        sum += p.iter().map(|v| f64::from(*v)).sum::<f64>();
        n += p.len();
    }
    let sharpened = if args.drop_sharpness == 1.0 {
        String::new()
    } else {
        format!(", sharpened {}x with its mean kept", args.drop_sharpness)
    };
    let words = format!(
        "raydrop_gan: x_n of each scan from {} (fast auto-decoding; mean drop probability {:.1} %{sharpened})",
        decoder.source(),
        100.0 * sum / n.max(1) as f64
    );
    for (t, p) in input.log_times.iter().zip(probs) {
        gan_drop.entry(*t).or_default().push_back(p);
    }
    Ok((gan_drop, words))
}

/// Warns of every skipped scan, then finishes the output (or, under `--strict` with scans
/// skipped, drops it unwritten) and prints the summary.
fn finish(
    global: &GlobalArgs,
    args: &RenderArgs,
    topic: &str,
    out: McapOutput,
    (scans, keep): (u64, f64),
    words: &str,
    skipped: &[String],
) -> anyhow::Result<Outcome> {
    for s in skipped {
        if !global.quiet {
            eprintln!("warning: {s}");
        }
    }
    if args.strict && !skipped.is_empty() {
        // Dropping the unfinished output removes its temporary file.
        drop(out);
        eprintln!(
            "{}: not written (--strict: {} scans were skipped)",
            args.output.display(),
            skipped.len()
        );
        return Ok(Outcome::DataSkipped);
    }
    out.finish()?;
    if global.json {
        println!(
            "{}",
            serde_json::json!({"output": args.output.display().to_string(), "scans": scans, "keep_rate": keep, "applied": words, "skipped": skipped.len()})
        );
    } else if !global.quiet {
        eprintln!(
            "{}: {scans} scans of {} rendered with {words}; {:.1} % of pixels keep a return",
            args.output.display(),
            topic,
            100.0 * keep
        );
    }
    Ok(Outcome::Success)
}

//! `rangegan-mcap sample --n 16 OUT.mcap`: draw scans from the trained generator and write
//! them as channels to look at in Foxglove: the pre-drop depth x_d, the drop probability x_n,
//! a sampled ray-drop mask, the measured range x_G and the point cloud of the returns.

use std::collections::BTreeMap;
use std::path::PathBuf;

use super::{GlobalArgs, Outcome};
use crate::io::encoders::{Kind, encode_f32_image, encode_mask, encode_points};
use crate::io::{Family, McapOutput};
use crate::lidar::SensorProfile;
use crate::model::layers::AngleGridExt;
use crate::model::sample::{SampleOptions, SampledScan, sample};
use crate::model::weights::Model;

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum FamilyArg {
    /// ROS 2 (CDR): sensor_msgs/Image and PointCloud2.
    Ros2,
    /// ROS 1: sensor_msgs/Image and PointCloud2.
    Ros1,
    /// Foxglove protobuf: foxglove.RawImage and foxglove.PointCloud.
    Foxglove,
}

/// The most scans one `sample` run draws (a bound, so a typo cannot ask for 2^64).
pub const MAX_SAMPLES: u64 = 100_000;

#[derive(Debug, clap::Args)]
pub struct SampleArgs {
    /// Number of scans to draw (written 10 per second), 1 to 100 000.
    #[arg(long, default_value_t = 16,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=MAX_SAMPLES))]
    pub n: usize,
    /// Seed of the latent codes and ray-drop masks.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Truncation psi towards the mean latent (1 = none, 0 = the mean scan).
    #[arg(long, default_value_t = 1.0)]
    pub truncation: f32,
    /// Render on a grid this many times denser in rows and columns than the training grid
    /// (KITTI HDL-64E, 64 x 512); the implicit generator needs no retraining for it.
    #[arg(long, default_value_t = 1)]
    pub scale: usize,
    /// Trained model: a model directory (config.json + g_ema.bpk) or a training run
    /// directory (default: the shipped weights).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Message family of the output channels.
    #[arg(long, value_enum, default_value = "ros2")]
    pub format: FamilyArg,
    /// Prefix of the output topics.
    #[arg(long, default_value = "/rangegan/sample")]
    pub topic_prefix: String,
    /// Frame id of the images and clouds.
    #[arg(long, default_value = "lidar")]
    pub frame_id: String,
    /// Overwrite an existing OUT.
    #[arg(long)]
    pub force: bool,
    /// Output MCAP.
    pub output: PathBuf,
}

/// One generated scan as the messages of its channels, `(channel suffix, kind, payload)`.
fn scan_messages(
    family: Family,
    stamp: u64,
    frame_id: &str,
    s: &SampledScan,
) -> Vec<(&'static str, Kind, Vec<u8>)> {
    let size = (s.angles.width, s.angles.height);
    let depth_m = &s.depth_m;
    let image = |values: &[f32]| encode_f32_image(family, stamp, frame_id, size, values);
    let returns: Vec<usize> = (0..s.range_m.len()).filter(|&k| s.mask[k]).collect();
    let range: Vec<f32> = returns.iter().map(|&k| s.range_m[k]).collect();
    let drop_prob: Vec<f32> = returns.iter().map(|&k| s.drop_prob[k]).collect();
    let cloud_msg = encode_points(
        family,
        stamp,
        frame_id,
        s.points(),
        &[("range", &range), ("raydrop_prob", &drop_prob)],
    );
    vec![
        ("depth", Kind::Image, image(depth_m)),
        ("raydrop_prob", Kind::Image, image(&s.drop_prob)),
        (
            "raydrop_mask",
            Kind::Image,
            encode_mask(family, stamp, frame_id, size, &s.mask),
        ),
        ("range", Kind::Image, image(&s.range_m)),
        ("points", Kind::Cloud, cloud_msg),
    ]
}

pub fn run(global: &GlobalArgs, args: SampleArgs) -> anyhow::Result<Outcome> {
    anyhow::ensure!(
        (1..=8).contains(&args.scale),
        "--scale must be 1..=8 (got {})",
        args.scale
    );
    anyhow::ensure!(
        args.truncation.is_finite() && (0.0..=1.0).contains(&args.truncation),
        "--truncation must be in 0..=1 (got {})",
        args.truncation
    );
    let family = match args.format {
        FamilyArg::Ros2 => Family::Ros2,
        FamilyArg::Ros1 => Family::Ros1,
        FamilyArg::Foxglove => Family::Foxglove,
    };
    let device = burn::tensor::Device::flex();
    let model = Model::load(args.model.as_deref(), &device)?;
    let base = SensorProfile::kitti_hdl64e().with_columns(512).angle_grid();
    let grid = base.resample(base.height * args.scale, base.width * args.scale);
    let opts = SampleOptions {
        n: args.n,
        seed: args.seed,
        truncation: args.truncation,
        grid: Some(grid),
    };
    let scans = sample(&model, &opts, &device)?;

    if let Some(dir) = &args.model {
        crate::io::writer::refuse_overwriting_inputs(&args.output, &[dir.as_path()])?;
    }
    let mut out = McapOutput::create(&args.output, args.force)?;
    out.write_metadata(
        "rangegan.sample",
        BTreeMap::from([
            ("tool".to_string(), "rangegan-mcap sample".to_string()),
            ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
            ("model".to_string(), model.source.clone()),
            (
                "arch".to_string(),
                serde_json::to_string(&model.config.arch)?,
            ),
            ("seed".to_string(), args.seed.to_string()),
            ("truncation".to_string(), args.truncation.to_string()),
        ]),
    )?;
    let mut channels = BTreeMap::new();
    for (i, s) in scans.iter().enumerate() {
        let stamp = i as u64 * 100_000_000;
        for (suffix, kind, msg) in scan_messages(family, stamp, &args.frame_id, s) {
            let id = match channels.get(suffix) {
                Some(&id) => id,
                None => {
                    let id =
                        out.own_channel(&format!("{}/{suffix}", args.topic_prefix), family, kind)?;
                    channels.insert(suffix, id);
                    id
                }
            };
            out.write_own(id, stamp, stamp, &msg)?;
        }
    }
    out.finish()?;
    let keep = scans
        .iter()
        .map(|s| s.mask.iter().filter(|m| **m).count())
        .sum::<usize>() as f64
        / scans.iter().map(|s| s.mask.len()).sum::<usize>().max(1) as f64;
    let (h, w) = (scans[0].angles.height, scans[0].angles.width);
    if global.json {
        println!(
            "{}",
            serde_json::json!({ "output": args.output.display().to_string(), "scans": scans.len(), "rows": h, "columns": w,
                "keep_rate": keep, "model": model.source, "topic_prefix": args.topic_prefix })
        );
    } else if !global.quiet {
        eprintln!(
            "{}: {} generated {h}x{w} scans from the {} model, {:.1} % of rays kept, on {}/{{depth,raydrop_prob,raydrop_mask,range,points}}",
            args.output.display(),
            scans.len(),
            model.source,
            100.0 * keep,
            args.topic_prefix
        );
    }
    Ok(Outcome::Success)
}

//! `rangegan-mcap simulate --scene SEED --sensor PROFILE --scans N --physics P OUT.mcap`:
//! a procedural street drive ray-cast with a sensor profile and sensor physics,
//! written as ROS 2 PointCloud2 (x, y, z, intensity, ring, time, label) at 10 Hz
//! with the ego pose on `/tf` so Foxglove shows the drive.

use std::collections::BTreeMap;

use anyhow::Context;

use super::{GlobalArgs, Outcome};
use crate::io::Family;
use crate::io::encoders::{Kind, Payload, Transform, encode, encode_cloud};
use crate::lidar::SensorProfile;
use crate::physics::PhysicsConfig;
use crate::sim::{SceneConfig, Simulator};

#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Scene seed: the street layout, objects, route and every random draw.
    #[arg(long, default_value_t = 0)]
    pub scene: u64,
    /// Sensor profile: a built-in name (hdl64e, vlp16, os1-64, ...) or a profile /
    /// Ouster metadata JSON file.
    #[arg(long, default_value = "hdl64e")]
    pub sensor: String,
    /// Columns per revolution (default: the profile's).
    #[arg(long)]
    pub columns: Option<usize>,
    /// Number of scans, 10 per second.
    #[arg(long, default_value_t = 100)]
    pub scans: u32,
    /// Sensor physics: a preset (ideal, carla-like, realistic) or a physics JSON
    /// file (schemas/physics.schema.json).
    #[arg(long, default_value = "ideal")]
    pub physics: String,
    /// Write organized clouds (beams x columns, NaN where no return) instead of
    /// the returns only.
    #[arg(long)]
    pub organized: bool,
    /// Ego speed along the route, m/s (0 to 100).
    #[arg(long, default_value_t = 10.0, value_parser = super::parse_speed_mps_f32)]
    pub speed_mps: f32,
    #[command(flatten)]
    pub out: super::CloudOutputArgs,
}

/// What the user typed, resolved into library objects.
struct Resolved {
    profile: SensorProfile,
    physics: PhysicsConfig,
}

fn resolve(args: &SimulateArgs) -> anyhow::Result<Resolved> {
    let mut profile = SensorProfile::resolve(&args.sensor)
        .with_context(|| format!("--sensor {}", args.sensor))?;
    if let Some(c) = args.columns {
        crate::lidar::profile::check_columns(c).map_err(anyhow::Error::msg)?;
        profile = profile.with_columns(c);
    }
    // Built-in profiles and loaded files are checked already; --columns is checked again
    // with the rest, before anything (the scene, the ray caster) is sized by the profile.
    profile
        .validate()
        .map_err(|why| anyhow::anyhow!("--sensor {}: {why}", args.sensor))?;
    let physics = PhysicsConfig::resolve_for_beams(&args.physics, profile.beams())
        .with_context(|| format!("--physics {}", args.physics))?;
    physics
        .validate(&args.physics, Some(profile.beams()))
        .with_context(|| format!("--physics {} for sensor {}", args.physics, profile.name))?;
    anyhow::ensure!(
        args.speed_mps.is_finite() && args.speed_mps >= 0.0,
        "--speed-mps must be >= 0 (got {})",
        args.speed_mps
    );
    anyhow::ensure!(args.scans > 0, "--scans must be > 0");
    Ok(Resolved { profile, physics })
}

pub fn run(global: &GlobalArgs, args: SimulateArgs) -> anyhow::Result<Outcome> {
    let Resolved { profile, physics } = resolve(&args)?;
    let sensor_height_m = 1.73;
    let config = SceneConfig {
        seed: args.scene,
        speed_mps: args.speed_mps,
        duration_s: args.scans as f32 * 0.1 + 1.0,
        sensor_height_m,
        ..Default::default()
    };
    let sim = Simulator::new(config, profile.clone());
    let effects = physics.effects();

    let physics_file = std::path::Path::new(&args.physics);
    if physics_file.is_file() {
        crate::io::writer::refuse_overwriting_inputs(&args.out.output, &[physics_file])?;
    }
    let start_nanos = args.out.start_nanos(args.scans as u64, None)?;
    let mut out = args.out.create()?;
    out.write_metadata(
        "rangegan.simulate",
        BTreeMap::from([
            ("tool".to_string(), "rangegan-mcap simulate".to_string()),
            ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
            ("scene_seed".to_string(), args.scene.to_string()),
            ("sensor".to_string(), serde_json::to_string(&profile)?),
            ("physics".to_string(), serde_json::to_string(&physics)?),
            ("physics_effects".to_string(), effects.ids().join(",")),
            ("organized".to_string(), args.organized.to_string()),
            ("speed_mps".to_string(), args.speed_mps.to_string()),
        ]),
    )?;
    let cloud_channel = out.own_channel(&args.out.topic, Family::Ros2, Kind::Cloud)?;
    let tf_channel = out.own_channel("/tf", Family::Ros2, Kind::Transforms)?;
    let tf_static_channel = out.own_channel("/tf_static", Family::Ros2, Kind::Transforms)?;
    let mount = Transform {
        parent_frame_id: "base_link".into(),
        child_frame_id: args.out.frame_id.clone(),
        translation: [0.0, 0.0, sensor_height_m as f64],
        rotation: [0.0, 0.0, 0.0, 1.0],
    };
    let msg = encode(
        Family::Ros2,
        start_nanos,
        "",
        &Payload::Transforms(std::slice::from_ref(&mount)),
    );
    out.write_own(tf_static_channel, start_nanos, start_nanos, &msg)?;

    let bar = super::progress_bar(global, args.scans as u64);
    let (mut points, mut pixels) = (0u64, 0u64);
    for index in 0..args.scans {
        let mut scan = sim.scan(index);
        effects.apply(&mut scan, args.scene);
        let cloud = scan.to_scan(args.organized);
        points += cloud.returns() as u64;
        pixels += scan.len() as u64;
        let stamp = start_nanos + (sim.scan_time(index) * 1e9).round() as u64;
        let msg = encode_cloud(Family::Ros2, stamp, &args.out.frame_id, &cloud, &[]);
        out.write_own(cloud_channel, stamp, stamp, &msg)?;
        // Ego pose at the scan start: base_link on the road under the sensor.
        let pose = scan.pose;
        let base = pose.origin - pose.axes[2] * sensor_height_m;
        let ego = Transform {
            parent_frame_id: "world".into(),
            child_frame_id: "base_link".into(),
            translation: [base.x as f64, base.y as f64, base.z as f64],
            rotation: pose.quaternion(),
        };
        let msg = encode(
            Family::Ros2,
            stamp,
            "",
            &Payload::Transforms(std::slice::from_ref(&ego)),
        );
        out.write_own(tf_channel, stamp, stamp, &msg)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    out.finish()?;
    let keep = points as f64 / pixels.max(1) as f64;
    if global.json {
        println!(
            "{}",
            serde_json::json!({ "output": args.out.output.display().to_string(), "scans": args.scans, "points": points, "keep_rate": keep,
                "sensor": profile.name, "physics": effects.ids(), "topic": args.out.topic })
        );
    } else if !global.quiet {
        eprintln!(
            "{}: {} scans of {} ({}x{}), physics [{}], {:.1} % of rays kept, on {} + /tf",
            args.out.output.display(),
            args.scans,
            profile.name,
            profile.beams(),
            profile.columns,
            effects.ids().join(", "),
            100.0 * keep,
            args.out.topic
        );
    }
    Ok(Outcome::Success)
}

#[cfg(test)]
mod tests {
    use super::super::{Args, Command};
    use super::*;
    use crate::io::decoders::{CloudFormat, decode_cloud};
    use clap::Parser;

    #[test]
    fn arguments_parse_and_resolve() {
        let a = Args::try_parse_from([
            "rangegan-mcap",
            "simulate",
            "--scene",
            "7",
            "--sensor",
            "vlp16",
            "--scans",
            "3",
            "--physics",
            "realistic",
            "--organized",
            "o.mcap",
        ])
        .unwrap();
        let Command::Simulate(s) = a.command else {
            panic!("not simulate")
        };
        assert_eq!((s.scene, s.scans, s.organized), (7, 3, true));
        let r = resolve(&s).unwrap();
        assert_eq!(r.profile.beams(), 16);
        assert!(r.physics.range_noise.is_some());
        let bad =
            Args::try_parse_from(["rangegan-mcap", "simulate", "--physics", "foggy", "o.mcap"])
                .unwrap();
        let Command::Simulate(s) = bad.command else {
            panic!("not simulate")
        };
        let err = format!("{:#}", resolve(&s).err().unwrap());
        assert!(
            err.contains("--physics foggy") && err.contains("realistic"),
            "{err}"
        );
    }

    #[test]
    fn writes_clouds_and_poses_readable_by_the_reader() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sim.mcap");
        let global = GlobalArgs {
            quiet: true,
            json: false,
            threads: None,
        };
        for organized in [false, true] {
            let args = SimulateArgs {
                scene: 3,
                sensor: "vlp16".into(),
                columns: Some(360),
                scans: 3,
                physics: "realistic".into(),
                organized,
                speed_mps: 10.0,
                out: crate::cli::CloudOutputArgs {
                    topic: "/points".into(),
                    frame_id: "velodyne".into(),
                    start_secs: None,
                    force: true,
                    output: path.clone(),
                },
            };
            run(&global, args).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let (mut clouds, mut tfs) = (0, 0);
            for msg in mcap::MessageStream::new(&bytes).unwrap() {
                let msg = msg.unwrap();
                match msg.channel.topic.as_str() {
                    "/points" => {
                        let schema = msg.channel.schema.as_ref().unwrap();
                        let format =
                            CloudFormat::detect(&msg.channel.message_encoding, &schema.name)
                                .unwrap();
                        let cloud = decode_cloud(format, &msg.data).unwrap();
                        let scan = cloud.scan;
                        assert_eq!(cloud.frame_id, "velodyne");
                        assert!(
                            scan.ring.is_some()
                                && scan.time_s.is_some()
                                && scan.label.is_some()
                                && scan.intensity.is_some()
                        );
                        if organized {
                            assert_eq!((scan.height, scan.width), (16, 360));
                            assert!(scan.returns() < scan.len(), "no NaN for dropped rays");
                        } else {
                            assert_eq!(scan.height, 1);
                            assert_eq!(scan.returns(), scan.len());
                        }
                        assert!(scan.returns() > 1000);
                        clouds += 1;
                    }
                    "/tf" => tfs += 1,
                    _ => {}
                }
            }
            assert_eq!((clouds, tfs), (3, 3));
        }
    }
}

//! End-to-end auto-decoding through `convert`: the new channels open in Foxglove's
//! own readers, outputs do not depend on the thread count, and bad decoding flags are clear
//! errors. The test recordings hold 16-beam scans, which the shipped model does not cover:
//! these tests name the model (`--model`) to decode them through it anyway, except where the
//! prior-free channels are the point. Few optimisation steps keep these fast; the quality is
//! measured by `examples/decode_eval/` (BENCHMARKS.md).

mod common;

use std::path::Path;

use common::*;
use rangegan_mcap::decode::{DecodeOptions, Decoder, Quality, scan_seed};
use rangegan_mcap::io::Family;
use rangegan_mcap::lidar::{SensorProfile, Strategy, kitti, project};
use rangegan_mcap::model::calibration::bernoulli_nll;
use rangegan_mcap::model::weights::Model;

const FAMILIES: [Family; 3] = [Family::Ros2, Family::Ros1, Family::Foxglove];

/// Quick decoding flags: 2 + 2 optimisation steps.
const QUICK: [&str; 6] = ["--decoder", "gan", "--w-steps", "2", "--tune-steps", "2"];

/// The shipped model's directory: naming it decodes every topic through it.
const MODEL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/models/dusty2");

fn convert(input: &Path, output: &Path, extra: &[&str], threads: &str) -> serde_json::Value {
    convert_with(input, output, &["--model", MODEL], extra, threads)
}

fn convert_with(
    input: &Path,
    output: &Path,
    model: &[&str],
    extra: &[&str],
    threads: &str,
) -> serde_json::Value {
    let mut args = vec![
        "convert",
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--json",
        "--quiet",
        "--force",
    ];
    args.extend_from_slice(model);
    args.extend_from_slice(&QUICK);
    args.extend_from_slice(extra);
    let o = bin()
        .args(&args)
        .env("RAYON_NUM_THREADS", threads)
        .output()
        .expect("binary runs");
    assert!(o.status.success(), "{}", stderr(&o));
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn decoded_channels_open_in_foxglove_readers() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let messages = write_recording(&input, &FAMILIES, 2, None);
    let summary = convert(
        &input,
        &output,
        &[
            "--mask-samples",
            "2",
            "--upsample",
            "2",
            "--target-sensor",
            "vlp16",
        ],
        "2",
    );
    // Per scan, on the scans' own 16 x 360 grid: range, depth, x_d, raydrop_prob, 2 masks,
    // points, depth/points at twice the grid (32 x 720) and for the VLP-16.
    let per_scan = 11;
    let scans = 2 * FAMILIES.len() as u64;
    assert_eq!(summary["report"]["outputs_written"], scans * per_scan);
    let Some(node) = node() else { return };
    let r = node_read(&node, &output);
    assert_eq!(r["decoded"], messages + scans * per_scan, "{r}");
    for family in FAMILIES {
        let t = format!("/lidar_{family:?}/rangegan").to_lowercase();
        let image = |s: &str| r["images"][format!("{t}/{s}")].clone();
        assert_eq!(
            image("depth"),
            serde_json::json!([16, 360, "32FC1", 1440, 16 * 1440])
        );
        assert_eq!(image("range"), image("depth"));
        assert_eq!(image("raydrop_prob"), image("depth"));
        assert_eq!(image("x_d"), image("depth"));
        assert_eq!(
            image("raydrop_mask_1"),
            serde_json::json!([16, 360, "mono8", 360, 16 * 360])
        );
        assert_eq!(
            image("depth_32x720"),
            serde_json::json!([32, 720, "32FC1", 2880, 32 * 2880])
        );
        assert_eq!(image("depth_vlp16")[0], 16);
        let values = |s: &str| r["values"][format!("{t}/{s}")].clone();
        let [lo, hi] = [0, 1].map(|i| values("raydrop_prob")[i].as_f64().unwrap());
        assert!(lo >= 0.0 && hi <= 1.0, "x_n in 0..1: {lo}..{hi}");
        let [lo, hi] = [0, 1].map(|i| values("depth")[i].as_f64().unwrap());
        assert!(lo >= 1.44 && hi <= 80.01, "depth in meters: {lo}..{hi}");
        assert_eq!(values("raydrop_mask"), serde_json::json!([0, 255]));
        for cloud in ["points", "points_32x720", "points_vlp16"] {
            assert_eq!(
                r["clouds"][format!("{t}/{cloud}")],
                serde_json::json!(["x", "y", "z", "range", "raydrop_prob"]),
                "{t}/{cloud}"
            );
        }
    }
    // Without a model named, the 16-beam scans get the prior-free channels (no x_d): they
    // open in the same readers.
    let summary = convert_with(&input, &output, &[], &["--upsample", "2"], "2");
    assert_eq!(summary["report"]["outputs_written"], scans * 7);
    let r = node_read(&node, &output);
    assert_eq!(r["decoded"], messages + scans * 7, "{r}");
    for family in FAMILIES {
        let t = format!("/lidar_{family:?}/rangegan").to_lowercase();
        let image = |s: &str| r["images"][format!("{t}/{s}")].clone();
        assert_eq!(image("depth"), image("range"));
        assert_eq!(image("raydrop_prob"), image("range"));
        assert!(image("x_d").is_null());
        assert_eq!(image("depth_32x720")[0], 32);
    }
}

#[test]
fn decoding_is_identical_with_one_and_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.mcap");
    write_recording(&input, &[Family::Ros2, Family::Foxglove], 3, None);
    // Same command line (the metadata record holds it), only the thread count differs.
    let out = dir.path().join("out.mcap");
    let outs: Vec<Vec<u8>> = ["1", "2"]
        .iter()
        .map(|threads| {
            // A restoration decodes through the model on any sensor.
            convert_with(&input, &out, &[], &["--restore-fraction", "0.5"], threads);
            std::fs::read(&out).unwrap()
        })
        .collect();
    assert!(outs[0].len() > 100_000);
    assert!(
        outs[0] == outs[1],
        "1 and 2 threads must give the same bytes"
    );
    // The output says what made its decoded channels.
    let ours = mcap::read::LinearReader::new(&outs[0])
        .unwrap()
        .find_map(|r| match r.unwrap() {
            mcap::records::Record::Metadata(m) if m.name == "rangegan" => Some(m.metadata),
            _ => None,
        })
        .expect("rangegan metadata record");
    assert_eq!(ours["decode_model"], "shipped + encoder shipped");
    assert_eq!(ours["decode_steps"], "2 w + 2 tuning");
    assert!(
        ours["raydrop_calibration"].contains("KITTI training scans"),
        "{ours:?}"
    );
}

/// The depth channel's messages of `/lidar_ros2`, in log order.
fn depth_messages(path: &Path) -> Vec<Vec<u8>> {
    let bytes = std::fs::read(path).unwrap();
    let mut out: Vec<(u64, Vec<u8>)> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.channel.topic == "/lidar_ros2/rangegan/depth")
        .map(|m| (m.log_time, m.data.into_owned()))
        .collect();
    out.sort_by_key(|(t, _)| *t);
    out.into_iter().map(|(_, d)| d).collect()
}

/// Chained scans (the default, 2 chains per topic) start from their chain's last tuned
/// weights: the first scan of each chain decodes as on its own, the later ones do not, and
/// the bytes do not depend on the thread count. Tuning steps alone, so the hand-written path.
#[test]
fn chained_scans_continue_their_chain_whatever_the_threads() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.mcap");
    write_recording(&input, &[Family::Ros2], 5, None);
    let run_with = |name: &str, chain: &[&str], threads: &str| {
        let output = dir.path().join(name);
        let o = bin()
            .args([
                "convert",
                input.to_str().unwrap(),
                output.to_str().unwrap(),
                "--quiet",
                "--decoder",
                "gan",
                "--model",
                MODEL,
                "--tune-steps",
                "4",
                "--upsample-method",
                "gan",
            ])
            .args(chain)
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .expect("binary runs");
        assert!(o.status.success(), "{}", stderr(&o));
        depth_messages(&output)
    };
    let stride2 = ["--chain-stride", "2"];
    let chained = run_with("chained1.mcap", &stride2, "1");
    let alone = run_with("alone.mcap", &["--chain-stride", "0"], "2");
    assert_eq!(chained.len(), 5);
    assert_eq!(
        chained,
        run_with("chained2.mcap", &stride2, "2"),
        "1 and 2 threads, same chains"
    );
    assert_eq!(
        chained[..2],
        alone[..2],
        "each chain's first scan starts from the shared weights"
    );
    for k in 2..5 {
        assert_ne!(chained[k], alone[k], "scan {k} continues its chain");
    }
    // One chain, each scan handed on half-way through its tuning.
    let half = ["--chain-stride", "1", "--hand-off", "2"];
    let relay = run_with("relay1.mcap", &half, "1");
    assert_eq!(
        relay,
        run_with("relay2.mcap", &half, "2"),
        "1 and 2 threads, same relay"
    );
    let after_all = run_with("after_all.mcap", &["--chain-stride", "1"], "2");
    assert_eq!(
        relay[0], alone[0],
        "the chain's first scan starts from the shared weights"
    );
    assert_eq!(after_all[0], alone[0]);
    for k in 1..5 {
        assert_ne!(
            relay[k],
            alone[k],
            "scan {k} starts from what scan {} handed on",
            k - 1
        );
        assert_ne!(
            relay[k], after_all[k],
            "scan {k}: handed on after 2 steps, not 4"
        );
    }
}

/// Two point-cloud topics make four chains in one batch, each started on a thread of its own:
/// the output is the same bytes for 1 and 2 threads, and a topic's channels are what they are
/// when the topic is converted alone.
#[test]
fn the_chains_of_two_topics_run_side_by_side_and_apart() {
    let dir = tempfile::tempdir().unwrap();
    let convert = |input: &Path, name: &str, threads: &str| {
        let output = dir.path().join(name);
        let o = bin()
            .args(["convert", input.to_str().unwrap(), output.to_str().unwrap()])
            .args([
                "--quiet",
                "--decoder",
                "gan",
                "--tune-steps",
                "4",
                "--channels",
                "depth",
            ])
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .expect("binary runs");
        assert!(o.status.success(), "{}", stderr(&o));
        output
    };
    let (both, alone) = (dir.path().join("both.mcap"), dir.path().join("alone.mcap"));
    write_recording(&both, &[Family::Ros2, Family::Ros1], 5, None);
    write_recording(&alone, &[Family::Ros2], 5, None);
    let one_thread = std::fs::read(convert(&both, "both1.mcap", "1")).unwrap();
    let two_threads = convert(&both, "both2.mcap", "2");
    assert_eq!(one_thread, std::fs::read(&two_threads).unwrap());
    let depth = depth_messages(&two_threads);
    assert_eq!(depth.len(), 5);
    assert_eq!(
        depth,
        depth_messages(&convert(&alone, "alone_out.mcap", "2"))
    );
}

#[test]
fn bad_decoding_flags_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    write_recording(&input, &[Family::Ros2], 1, None);
    let (i, o) = (input.to_str().unwrap(), output.to_str().unwrap());
    for (args, expected) in [
        (vec!["--quality", "off", "--upsample", "2"], "need decoding"),
        (vec!["--restore-lines", "0"], "--restore-lines 0"),
        (vec!["--tune-steps", "4"], "--decoder gan"),
        (vec!["--prior-free", "--channels", "x_d"], "--channels x_d"),
        (
            vec!["--target-sensor", "vlp16", "--target-sensor", "vlp16"],
            "both named 'vlp16'",
        ),
        (vec!["--restore-fraction", "1.5"], "fraction in (0, 1]"),
        (vec!["--model", "/nonexistent/model"], "/nonexistent/model"),
        (vec!["--target-sensor", "nosuchlidar"], "nosuchlidar"),
        (vec!["--upsample", "16"], "factors from 1 to 8"),
    ] {
        let mut all = vec!["convert", i, o, "--force"];
        all.extend(args.iter().copied());
        let out = run(&all);
        assert_eq!(out.status.code(), Some(1), "{args:?}");
        let e = stderr(&out);
        assert!(e.contains(expected), "{args:?}: {e}");
        assert!(!e.contains("panicked"), "{e}");
    }
    assert!(!output.exists(), "no partial output");
}

/// Each shipped Foxglove layout, with the `convert` flags of the recording it is made for:
/// every panel names a topic, and that command writes every topic named.
#[test]
fn every_panel_of_the_foxglove_layouts_is_filled_by_its_command() {
    let layouts: [(&str, &[&str]); 2] = [
        ("layouts/rangegan.foxglove-layout.json", &[]),
        (
            "layouts/rangegan-resampled.foxglove-layout.json",
            &["--upsample", "2", "--target-sensor", "vlp32c"],
        ),
    ];
    let dir = tempfile::tempdir().unwrap();
    for (k, (file, flags)) in layouts.iter().enumerate() {
        let layout: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(file).unwrap()).unwrap();
        let mut wanted = std::collections::BTreeSet::new();
        for (id, panel) in layout["configById"].as_object().unwrap() {
            let mut topics: Vec<String> = panel["imageMode"]["imageTopic"]
                .as_str()
                .map(String::from)
                .into_iter()
                .collect();
            if let Some(t) = panel["topics"].as_object() {
                topics.extend(t.keys().cloned());
            }
            assert!(!topics.is_empty(), "{file}: panel {id} names no topic");
            wanted.extend(topics);
        }
        assert!(wanted.len() >= 3, "{file}: {wanted:?}");
        let output = dir.path().join(format!("out{k}.mcap"));
        convert(
            Path::new("sample_logs/drive_realistic.mcap"),
            &output,
            flags,
            "2",
        );
        let bytes = std::fs::read(&output).unwrap();
        let written: std::collections::BTreeSet<String> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .map(|m| m.unwrap().channel.topic.clone())
            .collect();
        let missing: Vec<_> = wanted.difference(&written).collect();
        assert!(
            missing.is_empty(),
            "{file}: topics not written: {missing:?}"
        );
    }
}

/// A scan with nothing to decode (every return beyond the model's 80 m) still gets its range
/// image; only its decoded channels are missing, with a warning naming file, topic and time,
/// and `--strict` turns that into exit code 3. The scans around it decode normally.
#[test]
fn a_scan_with_nothing_to_decode_keeps_its_range_channel_and_is_reported() {
    use rangegan_mcap::io::decoders::DecodedCloud;
    use rangegan_mcap::io::encoders::{self, Kind};
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("far.mcap"), dir.path().join("out.mcap"));
    {
        let file = std::io::BufWriter::new(std::fs::File::create(&input).unwrap());
        let mut w = mcap::Writer::new(file).unwrap();
        let s = encoders::schema(Family::Ros2, Kind::Cloud);
        let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
        let channel = w
            .add_channel(schema, "/lidar", "cdr", &Default::default())
            .unwrap();
        for (i, range_m) in [5.0f32, 120.0, 6.0].into_iter().enumerate() {
            let t = 1_000_000_000 + i as u64 * 100_000_000;
            let cloud = DecodedCloud {
                scan: synthetic_scan(range_m, i as u32),
                stamp_nanos: t,
                frame_id: "lidar".into(),
                notes: Vec::new(),
            };
            let header = mcap::records::MessageHeader {
                channel_id: channel,
                sequence: i as u32,
                log_time: t,
                publish_time: t,
            };
            let data = encoders::encode_scan(Family::Ros2, &cloud, &[]);
            w.write_to_known_channel(&header, &data).unwrap();
        }
        w.finish().unwrap();
    }
    let summary = convert(&input, &output, &[], "1");
    let report = &summary["report"];
    assert_eq!(report["topics"]["/lidar"]["scans"], 3, "{report:#}");
    assert_eq!(report["topics"]["/lidar"]["malformed"], 0);
    assert_eq!(report["topics"]["/lidar"]["stage_failures"], 1);
    let warnings = report["warnings"].as_array().unwrap();
    assert_eq!(warnings.len(), 1, "{warnings:#?}");
    let message = warnings[0]["message"].as_str().unwrap();
    assert!(
        message.contains("far.mcap")
            && message.contains("/lidar")
            && message.contains("nothing to decode"),
        "{message}"
    );
    // 3 range images, 2 scans with their depth
    let bytes = std::fs::read(&output).unwrap();
    let count = |topic: &str| {
        mcap::MessageStream::new(&bytes)
            .unwrap()
            .filter(|m| m.as_ref().unwrap().channel.topic == topic)
            .count()
    };
    assert_eq!(count("/lidar/rangegan/range"), 3);
    assert_eq!(count("/lidar/rangegan/depth"), 2);
    assert_eq!(count("/lidar"), 3);
    // --strict: done, but the exit code says something was skipped
    let o = bin()
        .args([
            "convert",
            input.to_str().unwrap(),
            dir.path().join("strict.mcap").to_str().unwrap(),
            "--strict",
            "--quiet",
            "--model",
            MODEL,
        ])
        .args(QUICK)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
}

/// The shipped x_n calibration on real held-out KITTI scans (sequence 00, never trained on):
/// the mean calibrated x_n matches the scans' actual drop rate and scores a lower NLL than the
/// generator's raw x_n, which is far too sure that rays return.
#[test]
fn calibrated_raydrop_matches_real_held_out_drops() {
    let Some(real) = real_data("calibrated_raydrop_matches_real_held_out_drops") else {
        return;
    };
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let device = burn::tensor::Device::flex();
    let decoder = |calibrate: bool| {
        // The shipped schedule: the calibration was fitted on its decodes.
        let mut opts = DecodeOptions::new(Quality::Fast);
        opts.calibrate_raydrop = calibrate;
        Decoder::new(Model::shipped(&device).unwrap(), opts).unwrap()
    };
    let (calibrated, raw) = (decoder(true), decoder(false));
    assert!(calibrated.calibration_source().is_some() && raw.calibration_source().is_none());
    let seq = real.join("semantickitti_mini/00/velodyne");
    let mut bins: Vec<_> = std::fs::read_dir(&seq)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    bins.sort();
    let (mut dropped, mut sums, mut nll, mut n) = (0.0f64, [0.0f64; 2], [0.0f64; 2], 0.0f64);
    for (i, bin) in bins.iter().take(2).enumerate() {
        let image = project(&kitti::read_bin(bin).unwrap(), &profile, Strategy::Auto).unwrap();
        let seed = scan_seed("/velodyne_points", i as u64);
        for (j, d) in [&calibrated, &raw].into_iter().enumerate() {
            let x_n = d.decode(&image, seed).unwrap().model.drop_prob;
            for (k, p) in x_n.iter().enumerate() {
                let kept = (1.45..=80.0).contains(&image.range_m[k]);
                let keep = f64::from(1.0 - p).clamp(1e-6, 1.0 - 1e-6);
                sums[j] += f64::from(*p);
                nll[j] += bernoulli_nll((keep / (1.0 - keep)).ln(), kept);
                if j == 0 {
                    dropped += f64::from(u8::from(!kept));
                    n += 1.0;
                }
            }
        }
    }
    let (rate, mean_cal, mean_raw) = (dropped / n, sums[0] / n, sums[1] / n);
    eprintln!(
        "drop rate {rate:.3}; mean x_n calibrated {mean_cal:.3}, raw {mean_raw:.3}; NLL {:.3} vs {:.3}",
        nll[0] / n,
        nll[1] / n
    );
    assert!(
        (mean_cal - rate).abs() < 0.03,
        "calibrated {mean_cal} vs {rate}"
    );
    assert!(
        nll[0] < 0.8 * nll[1],
        "NLL calibrated {} raw {}",
        nll[0] / n,
        nll[1] / n
    );
}

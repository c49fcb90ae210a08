//! Real scans of several makes through what tells one sensor from another: the warning
//! that a sensor is far from the decoding model's view (nuScenes HDL-32E, an indoor VLP-16,
//! KITTI), the Ouster built-ins against a real gen-1 OS1-64, and ring fields that keep
//! every beam on its row (real KITTI, with and without dead beams). Skipped with a message
//! where `../shared/real_lidar` is absent.

mod common;

use common::{first_file, real_data};
use rangegan_mcap::io::{CloudFormat, decode_cloud};
use rangegan_mcap::lidar::{
    Scan, SensorProfile, Strategy, estimate_profile, kitti, nuscenes, pcd, project,
};

/// The warning that a sensor is far from the decoding model's view fires on real scans of
/// other makes and names their beam tables: nuScenes' HDL-32E (+10.7 to -30.7 deg, most
/// returns inside the model's view but a third of its beams outside) and an indoor VLP-16.
/// KITTI's own HDL-64E gets none.
#[test]
fn the_model_fit_warning_names_the_beam_table_of_other_makes() {
    let Some(root) = real_data("the_model_fit_warning_names_the_beam_table_of_other_makes") else {
        return;
    };
    use rangegan_mcap::decode::fit::model_fit;
    let first = |dir: &str, suffix: &str| first_file(&root.join(dir), suffix);
    let hdl32 = SensorProfile::builtin("hdl32e").unwrap();
    let nus = nuscenes::read_bin(&first("nuscenes", ".pcd.bin")).unwrap();
    let shipped = rangegan_mcap::model::config::default_sensor();
    let fit = model_fit(&nus, &hdl32, &shipped).unwrap();
    let w = fit
        .warning("hdl32e")
        .expect("a third of the HDL-32E's beams lie outside");
    assert!(w.contains("beams +10.7 to -30.7 deg"), "{w}");
    assert_eq!(fit.beams_outside, 12, "{fit:?}");
    let vlp = SensorProfile::builtin("vlp16").unwrap();
    let room = pcd::read_pcd(&first("nebula", ".pcd")).unwrap();
    let w = model_fit(&room, &vlp, &shipped)
        .unwrap()
        .warning("vlp16")
        .expect("an indoor VLP-16");
    assert!(w.contains("beams +15.0 to -15.0 deg"), "{w}");
    let kitti = kitti::read_bin(&first_file(&root.join("kitti_raw_drive_a"), ".bin")).unwrap();
    let fit = model_fit(&kitti, &SensorProfile::kitti_hdl64e(), &shipped).unwrap();
    assert!(fit.warning("hdl64e").is_none(), "{fit:?}");
}

/// The real OS1-64 of the Ouster recording is a gen 1 unit (33.2 deg of view): its beams,
/// estimated from the cloud's ring field, sit on `os1-64-gen1`'s table (uniform, +16.6 to
/// -16.6 deg) and not on the gen 2 `os1-64`'s (+-22.5 deg).
#[test]
fn the_ouster_recording_matches_the_gen1_profile() {
    let Some(root) = real_data("the_ouster_recording_matches_the_gen1_profile") else {
        return;
    };
    let bytes = std::fs::read(root.join("mcap/pointcloudset_test.mcap")).unwrap();
    let mut scans = Vec::new();
    for msg in mcap::MessageStream::new(&bytes).unwrap() {
        let msg = msg.unwrap();
        let Some(schema) = msg.channel.schema.as_ref() else {
            continue;
        };
        if let Some(format) = CloudFormat::detect(&msg.channel.message_encoding, &schema.name) {
            scans.push(decode_cloud(format, &msg.data).unwrap().scan);
        }
    }
    let est = estimate_profile(&scans).unwrap();
    assert_eq!(est.beams.len(), 64, "{est}");
    let off = |name: &str| {
        let table = SensorProfile::builtin(name).unwrap().elevation_deg;
        est.beams
            .iter()
            .zip(&table)
            .map(|(b, e)| (b.elevation_deg - e).abs())
            .fold(0.0f32, f32::max)
    };
    let (gen1, gen2) = (off("os1-64-gen1"), off("os1-64"));
    eprintln!("OS1-64: largest beam offset {gen1:.2} deg from os1-64-gen1, {gen2:.2} from os1-64");
    assert!(gen1 < 0.35, "{gen1}");
    assert!(gen2 > 5.0, "{gen2}");
}

/// A ring field numbering the beams in elevation order keeps every beam on its own row,
/// even where parallax swaps two neighbouring rings' median elevations (near returns) and
/// where beams have no return at all (a dead laser): real KITTI scans projected, written
/// back as clouds with their rows as the ring field (all 64, then 60 with 4 beams
/// removed), project onto exactly the same pixels.
#[test]
fn a_ring_field_in_elevation_order_keeps_every_beam_on_its_row() {
    let Some(root) = real_data("a_ring_field_in_elevation_order_keeps_every_beam_on_its_row")
    else {
        return;
    };
    let (_, files) = rangegan_mcap::model::data::kitti_validation_split(
        &root,
        &["kitti_raw_drive_d".to_string()],
    )
    .unwrap();
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    for removed in [vec![], vec![5usize, 20, 21, 40]] {
        let mut wrong = 0;
        for f in files.iter().step_by(3).take(10) {
            let img = project(&kitti::read_bin(f).unwrap(), &profile, Strategy::Auto).unwrap();
            let keep: Vec<usize> = (0..img.range_m.len())
                .filter(|&k| img.range_m[k] > 0.0 && !removed.contains(&(k / 512)))
                .collect();
            let mut cloud = Scan::from_xyz(keep.iter().map(|&k| img.xyz[k]).collect());
            cloud.ring = Some(keep.iter().map(|&k| (k / 512) as u16).collect());
            let back = project(&cloud, &profile, Strategy::Auto).unwrap();
            wrong += (0..img.range_m.len())
                .filter(|k| !removed.contains(&(k / 512)))
                .filter(|&k| back.range_m[k] != img.range_m[k])
                .count();
        }
        assert_eq!(wrong, 0, "beams {removed:?} removed: {wrong} pixels moved");
    }
}

/// The built-in Hesai PandarXT32 and Velodyne VLS-128 beam tables match the real units'
/// calibration files in `../shared/real_lidar/other_sensors` (nebula's decoder tests): every
/// beam within 0.1 deg (XT32: 1 deg apart) and 0.01 deg (VLS-128: the maker's table).
#[test]
fn the_hesai_and_vls128_built_ins_match_real_calibrations() {
    let Some(root) = real_data("the_hesai_and_vls128_built_ins_match_real_calibrations") else {
        return;
    };
    let dir = root.join("other_sensors");
    let sorted = |mut v: Vec<f32>| {
        v.sort_by(|a, b| b.total_cmp(a));
        v
    };
    let csv = std::fs::read_to_string(dir.join("nebula_hesai_xt32/PandarXT32.csv")).unwrap();
    let xt32: Vec<f32> = (csv.lines().skip(1))
        .filter_map(|l| l.split(',').nth(1)?.trim().parse().ok())
        .collect();
    let yaml = std::fs::read_to_string(dir.join("nebula_velodyne_vls128/VLS128.yaml")).unwrap();
    let vls: Vec<f32> = (yaml.lines())
        .filter_map(|l| l.trim().strip_prefix("vert_correction:"))
        .filter_map(|v| v.trim().trim_end_matches(',').parse::<f32>().ok())
        .map(f32::to_degrees)
        .collect();
    for (name, real, tolerance) in [("pandarxt32", xt32, 0.1), ("vls128", vls, 0.01)] {
        let table = SensorProfile::builtin(name).unwrap().elevation_deg;
        let real = sorted(real);
        assert_eq!(table.len(), real.len(), "{name}");
        for (t, r) in table.iter().zip(&real) {
            assert!((t - r).abs() < tolerance, "{name}: {t} vs {r}");
        }
    }
    let pandar64 = SensorProfile::builtin("pandar64").unwrap();
    assert_eq!(pandar64.beams(), 64);
    pandar64.validate().unwrap();
}

/// The rotations of real Ouster PCAP captures (an OS-1-128 in the low-bandwidth eUDP
/// profile, three moving frames, and a legacy-format OS-1-32) import as organized clouds
/// whose beams are the unit's own (its metadata JSON, also a `--sensor` profile), every
/// return on a pixel of that profile. A capture cut off mid-packet keeps the rotations
/// before the cut and the one in progress there, with a warning that names the byte offset.
#[test]
fn ouster_pcap_captures_import_as_the_units_own_beams() {
    let Some(root) = real_data("ouster_pcap_captures_import_as_the_units_own_beams") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let captures = [
        (
            "other_sensors/ouster_os1_128_lb_3frames/OS-1-128_v2.3.0_1024x10_lb_n3.pcap",
            "other_sensors/ouster_os1_128_lb_3frames/OS-1-128_v2.3.0_1024x10.json",
            3,
            128,
        ),
        (
            "ouster/OS-1-32-G_v2.1.1_1024x10.pcap",
            "ouster/OS-1-32-G_v2.1.1_1024x10.json",
            1,
            32,
        ),
    ];
    for (pcap, json, frames, beams) in captures {
        let out = dir.path().join("ouster.mcap");
        let o = common::run(&[
            "--json",
            "import",
            root.join(pcap).to_str().unwrap(),
            out.to_str().unwrap(),
            "--force",
        ]);
        assert!(o.status.success(), "{pcap}: {}", common::stderr(&o));
        let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(summary["scans"], frames, "{pcap}: {summary}");
        let bytes = std::fs::read(&out).unwrap();
        let scans: Vec<Scan> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .map(|m| m.unwrap())
            .filter(|m| m.channel.topic == "/velodyne_points")
            .map(|m| decode_cloud(CloudFormat::Ros2Cdr, &m.data).unwrap().scan)
            .collect();
        let unit = SensorProfile::load(&root.join(json)).unwrap();
        assert_eq!(unit.beams(), beams);
        for scan in &scans {
            assert_eq!(
                (scan.height, scan.width),
                (beams, 1024),
                "{pcap}: organized"
            );
            assert!(
                scan.returns() > scan.len() / 2,
                "{pcap}: {} returns",
                scan.returns()
            );
            let image = project(scan, &unit, Strategy::Auto).unwrap();
            let pixels = image.range_m.iter().filter(|&&r| r > 0.0).count();
            assert!(
                pixels as f64 >= 0.99 * scan.returns() as f64,
                "{pcap}: {pixels} pixels for {} returns",
                scan.returns()
            );
        }
        let est = estimate_profile(&scans).unwrap();
        assert_eq!(est.beams.len(), beams, "{pcap}: {est}");
        let worst = est
            .beams
            .iter()
            .zip(&unit.elevation_deg)
            .map(|(b, e)| (b.elevation_deg - e).abs())
            .fold(0.0f32, f32::max);
        // Beams sit 15-27 mm off the lidar's axis: near returns tilt their elevation a little.
        assert!(
            worst < 0.5,
            "{pcap}: a beam {worst:.2} deg off the unit's table"
        );
    }
    let (pcap, json, _, _) = captures[0];
    let cut = dir.path().join("cut.pcap");
    let whole = std::fs::read(root.join(pcap)).unwrap();
    std::fs::write(&cut, &whole[..1_000_000]).unwrap();
    let out = dir.path().join("cut.mcap");
    let o = common::run(&[
        "--json",
        "import",
        cut.to_str().unwrap(),
        out.to_str().unwrap(),
        "--metadata",
        root.join(json).to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", common::stderr(&o));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // The rotation before the cut, and the one in progress there as a partial rotation.
    assert_eq!(summary["scans"], 2, "{summary}");
    let err = common::stderr(&o);
    assert!(
        err.contains("truncated") && err.contains("byte offset") && err.contains("partial"),
        "{err}"
    );
    // Without --metadata, a folder without the capture's JSON is asked for one.
    let o = common::run(&[
        "import",
        cut.to_str().unwrap(),
        out.to_str().unwrap(),
        "--force",
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        common::stderr(&o).contains("give --metadata"),
        "{}",
        common::stderr(&o)
    );
}

/// (offset, captured length) of every record of a pcap file.
fn pcap_records(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut records = Vec::new();
    let mut at = 24;
    while at + 16 <= bytes.len() {
        let len = u32::from_le_bytes(bytes[at + 8..at + 12].try_into().unwrap()) as usize;
        records.push((at, len));
        at += 16 + len;
    }
    records
}

/// Damage to a real Ouster capture costs no more than it touches: a capture cut a few bytes
/// into its last packet keeps every rotation (the last one partial); one short packet in the
/// first rotation loses that packet, not the rotation; `--strict` refuses both; metadata that
/// names another UDP port says which ports the packets use; and metadata of half the columns
/// says the returns it cannot place are lost.
#[test]
fn ouster_capture_damage_costs_no_more_than_it_touches() {
    let Some(root) = real_data("ouster_capture_damage_costs_no_more_than_it_touches") else {
        return;
    };
    let folder = root.join("other_sensors/ouster_os1_128_lb_3frames");
    let whole = std::fs::read(folder.join("OS-1-128_v2.3.0_1024x10_lb_n3.pcap")).unwrap();
    let meta_text = std::fs::read_to_string(folder.join("OS-1-128_v2.3.0_1024x10.json")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let import = |capture: &[u8], meta: &str, strict: bool| {
        let (pcap, json) = (dir.path().join("c.pcap"), dir.path().join("c.json"));
        let out = dir.path().join("c.mcap");
        std::fs::write(&pcap, capture).unwrap();
        std::fs::write(&json, meta).unwrap();
        let _ = std::fs::remove_file(&out);
        let mut args = vec![
            "--json",
            "import",
            pcap.to_str().unwrap(),
            out.to_str().unwrap(),
        ];
        args.extend(["--metadata", json.to_str().unwrap()]);
        if strict {
            args.push("--strict");
        }
        let o = common::run(&args);
        let scans = serde_json::from_slice::<serde_json::Value>(&o.stdout)
            .map(|v| v["scans"].as_u64().unwrap_or(0))
            .unwrap_or(0);
        (o.status.code(), scans, common::stderr(&o), out.exists())
    };
    let (code, intact, _, _) = import(&whole, &meta_text, false);
    assert_eq!((code, intact), (Some(0), 3));
    let records = pcap_records(&whole);
    let (last, _) = *records.last().unwrap();
    let cut = &whole[..last + 16 + 40];
    let (code, scans, err, _) = import(cut, &meta_text, false);
    assert_eq!((code, scans), (Some(0), 3), "{err}");
    assert!(err.contains("partial"), "{err}");
    let (code, _, err, written) = import(cut, &meta_text, true);
    assert_eq!(code, Some(3), "{err}");
    assert!(!written, "--strict left an output");
    // Record 10 lies in the first rotation: 100 bytes short of a whole packet.
    let (at, len) = records[10];
    let mut short = whole[..at].to_vec();
    let mut header = whole[at..at + 16].to_vec();
    header[8..12].copy_from_slice(&((len - 100) as u32).to_le_bytes());
    short.extend(&header);
    short.extend(&whole[at + 16..at + 16 + len - 100]);
    short.extend(&whole[at + 16 + len..]);
    let (code, scans, err, _) = import(&short, &meta_text, false);
    assert_eq!((code, scans), (Some(0), 3), "{err}");
    assert!(err.contains("the packet is skipped"), "{err}");
    let other_port = meta_text.replace("7502", "7777");
    let (code, _, err, _) = import(&whole, &other_port, false);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("port 7777") && err.contains("went to port 7502"),
        "{err}"
    );
    let mut half: serde_json::Value = serde_json::from_str(&meta_text).unwrap();
    half["data_format"]["columns_per_frame"] = 512.into();
    half["lidar_mode"] = "512x10".into();
    let (code, scans, err, _) = import(&whole, &half.to_string(), false);
    assert!(
        err.contains("past the metadata's columns_per_frame 512"),
        "{code:?} {scans}: {err}"
    );
}

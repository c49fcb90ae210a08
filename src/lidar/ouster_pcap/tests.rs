//! Unit tests on synthetic captures: every byte is written here, so each
//! layout assumption is pinned down independently of the real-data test.

use super::*;

const W: usize = 16;
const H: usize = 4;
const CPP: usize = 4;

fn flat_json(profile: &str) -> String {
    format!(
        r#"{{
        "beam_altitude_angles": [10.0, 3.0, -3.0, -10.0],
        "beam_azimuth_angles": [3.0, 1.0, -1.0, -3.0],
        "lidar_origin_to_beam_origin_mm": 15.0,
        "lidar_to_sensor_transform": [-1,0,0,0, 0,-1,0,0, 0,0,1,36.0, 0,0,0,1],
        "lidar_mode": "16x10",
        "udp_port_lidar": 7502,
        "data_format": {{
            "columns_per_frame": {W}, "columns_per_packet": {CPP},
            "pixels_per_column": {H}, "pixel_shift_by_row": [2, 1, 0, -1],
            "udp_profile_lidar": "{profile}"
        }}
    }}"#
    )
}

fn nested_json(profile: &str) -> String {
    format!(
        r#"{{
        "sensor_info": {{"prod_line": "OS-1-4"}},
        "beam_intrinsics": {{
            "beam_altitude_angles": [10.0, 3.0, -3.0, -10.0],
            "beam_azimuth_angles": [3.0, 1.0, -1.0, -3.0],
            "lidar_origin_to_beam_origin_mm": 15.0,
            "beam_to_lidar_transform": [1,0,0,15.0, 0,1,0,0, 0,0,1,0, 0,0,0,1]
        }},
        "lidar_intrinsics": {{
            "lidar_to_sensor_transform": [-1,0,0,0, 0,-1,0,0, 0,0,1,36.0, 0,0,0,1]
        }},
        "config_params": {{"lidar_mode": "16x10", "udp_port_lidar": 7502}},
        "lidar_data_format": {{
            "columns_per_frame": {W}, "columns_per_packet": {CPP},
            "pixels_per_column": {H}, "pixel_shift_by_row": [2, 1, 0, -1],
            "udp_profile_lidar": "{profile}"
        }}
    }}"#
    )
}

fn meta(profile: &str) -> OusterMetadata {
    OusterMetadata::from_json(&flat_json(profile)).unwrap()
}

/// Synthetic range in millimetres for (row, measurement id); 0 = no return.
fn range_of(row: usize, m: usize) -> u32 {
    if (row + m).is_multiple_of(5) {
        0
    } else {
        1000 + 80 * (row * W + m) as u32
    }
}

fn put(buf: &mut [u8], at: usize, bytes: &[u8]) {
    buf[at..at + bytes.len()].copy_from_slice(bytes);
}

/// Encodes one pixel of `profile` with range `mm` and reflectivity `refl`.
fn put_pixel(px: &mut [u8], profile: UdpProfile, mm: u32, refl: u8) {
    match profile {
        UdpProfile::Legacy => {
            put(px, 0, &(mm | 0xFFF0_0000).to_le_bytes());
            put(px, 4, &u16::from(refl).to_le_bytes());
        }
        UdpProfile::Rng19Rfl8Sig16Nir16 => {
            put(px, 0, &(mm | 0xFFF8_0000).to_le_bytes());
            px[4] = refl;
            put(px, 6, &0xBEEFu16.to_le_bytes());
        }
        UdpProfile::Rng15Rfl8Nir8 => {
            // flag bit 15 set to check it is masked off
            put(px, 0, &((mm / 8) as u16 | 0x8000).to_le_bytes());
            px[2] = refl;
            px[3] = 0xAA;
        }
        UdpProfile::Rng19Rfl8Sig16Nir16Dual => {
            put(px, 0, &(mm | 0xFFF8_0000).to_le_bytes());
            px[3] = refl;
            put(px, 4, &12345u32.to_le_bytes());
        }
    }
}

/// One lidar packet with columns `first_m ..` of frame `frame_id`.
fn packet(meta: &OusterMetadata, frame_id: u16, first_m: usize, valid: bool) -> Vec<u8> {
    let layout = PacketLayout::new(meta);
    let mut buf = vec![0u8; layout.size];
    if meta.udp_profile_lidar != UdpProfile::Legacy {
        put(&mut buf, 0, &1u16.to_le_bytes());
        put(&mut buf, 2, &frame_id.to_le_bytes());
    }
    for i in 0..CPP {
        let m = first_m + i;
        let start = layout.packet_header + i * layout.col_size;
        let col = &mut buf[start..start + layout.col_size];
        put(col, 0, &(1_000_000 + 1000 * m as u64).to_le_bytes());
        put(col, 8, &(m as u16).to_le_bytes());
        if meta.udp_profile_lidar == UdpProfile::Legacy {
            put(col, 10, &frame_id.to_le_bytes());
            let status: u32 = if valid { 0xFFFF_FFFF } else { 0 };
            put(col, layout.col_size - 4, &status.to_le_bytes());
        } else {
            put(col, 10, &u16::from(valid).to_le_bytes());
        }
        for row in 0..H {
            let at = layout.col_header + row * layout.bytes_per_pixel;
            let px = &mut col[at..at + layout.bytes_per_pixel];
            put_pixel(
                px,
                meta.udp_profile_lidar,
                range_of(row, m),
                (row + m) as u8,
            );
        }
    }
    buf
}

fn ipv4_udp(payload: &[u8], id: u16, frag: Option<(usize, bool)>) -> Vec<u8> {
    let (offset, more) = frag.unwrap_or((0, false));
    let mut ip = vec![0u8; 20];
    ip[0] = 0x45;
    ip[8] = 64;
    ip[9] = 17;
    put(&mut ip, 4, &id.to_be_bytes());
    let flags = (offset / 8) as u16 | if more { 0x2000 } else { 0 };
    put(&mut ip, 6, &flags.to_be_bytes());
    put(&mut ip, 12, &[10, 5, 5, 87]);
    put(&mut ip, 16, &[10, 5, 5, 1]);
    ip.extend_from_slice(payload);
    let total = ip.len() as u16;
    put(&mut ip, 2, &total.to_be_bytes());
    ip
}

fn udp(dst_port: u16, payload: &[u8]) -> Vec<u8> {
    let mut u = vec![0u8; 8];
    put(&mut u, 0, &7502u16.to_be_bytes());
    put(&mut u, 2, &dst_port.to_be_bytes());
    put(&mut u, 4, &((payload.len() + 8) as u16).to_be_bytes());
    u.extend_from_slice(payload);
    u
}

fn ethernet(ip: &[u8]) -> Vec<u8> {
    let mut f = vec![0u8; 12];
    f.extend_from_slice(&0x0800u16.to_be_bytes());
    f.extend_from_slice(ip);
    f
}

/// Classic little-endian microsecond pcap with the given link-layer frames.
fn pcap_file(linktype: u32, frames: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&0xA1B2_C3D4u32.to_le_bytes());
    out.extend_from_slice(&2u16.to_le_bytes());
    out.extend_from_slice(&4u16.to_le_bytes());
    out.extend_from_slice(&[0; 8]);
    out.extend_from_slice(&65535u32.to_le_bytes());
    out.extend_from_slice(&linktype.to_le_bytes());
    for (i, f) in frames.iter().enumerate() {
        out.extend_from_slice(&(i as u32).to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        out.extend_from_slice(&(f.len() as u32).to_le_bytes());
        out.extend_from_slice(&(f.len() as u32).to_le_bytes());
        out.extend_from_slice(f);
    }
    out
}

fn eth_udp(port: u16, payload: &[u8]) -> Vec<u8> {
    ethernet(&ipv4_udp(&udp(port, payload), 1, None))
}

/// Two frames: frame 7 complete, frame 8 with only its first packet.
fn capture(meta: &OusterMetadata) -> Vec<Vec<u8>> {
    let mut frames: Vec<Vec<u8>> = (0..W / CPP)
        .map(|p| eth_udp(7502, &packet(meta, 7, p * CPP, true)))
        .collect();
    frames.push(eth_udp(7502, &packet(meta, 8, 0, true)));
    frames
}

fn check_frames(meta: &OusterMetadata, frames: &[OusterFrame]) {
    assert_eq!(frames.len(), 2);
    assert_eq!((frames[0].frame_id, frames[1].frame_id), (7, 8));
    assert_eq!((frames[0].columns_seen, frames[1].columns_seen), (W, CPP));
    assert!(frames[0].is_complete() && !frames[1].is_complete());
    assert_eq!(frames[0].timestamp_ns, 1_000_000);
    let scan = &frames[0].scan;
    assert_eq!((scan.height, scan.width, scan.xyz.len()), (H, W, H * W));
    let lut = Lut::new(meta);
    for row in 0..H {
        for m in 0..W {
            let col = destaggered_column(m, meta.pixel_shift_by_row[row], W);
            let i = row * W + col;
            let expect = lut.point(row * W + m, range_of(row, m));
            assert_eq!(scan.xyz[i], expect, "row {row} m {m}");
            assert_eq!(scan.ring.as_ref().unwrap()[i], row as u16);
            assert_eq!(scan.intensity.as_ref().unwrap()[i], (row + m) as f32);
            let t = scan.time_s.as_ref().unwrap()[i];
            assert!((t - m as f32 * 1e-6).abs() < 1e-9, "time {t}");
        }
    }
    // Partial frame: missing columns are zero.
    let partial = &frames[1].scan;
    let col = destaggered_column(W - 1, meta.pixel_shift_by_row[0], W);
    assert_eq!(partial.xyz[col], [0.0; 3]);
}

#[test]
fn decodes_every_profile() {
    for profile in [
        "LEGACY",
        "RNG19_RFL8_SIG16_NIR16",
        "RNG15_RFL8_NIR8",
        "RNG19_RFL8_SIG16_NIR16_DUAL",
    ] {
        let meta = meta(profile);
        let frames = read_pcap(&pcap_file(1, &capture(&meta)), &meta).unwrap();
        check_frames(&meta, &frames);
    }
}

#[test]
fn packet_sizes_match_ouster_formula() {
    let size = |p: &str, ppc: usize| {
        let mut m = meta(p);
        m.pixels_per_column = ppc;
        m.columns_per_packet = 16;
        m.lidar_packet_size()
    };
    assert_eq!(size("LEGACY", 64), 12608);
    assert_eq!(size("RNG19_RFL8_SIG16_NIR16", 128), 24832);
    assert_eq!(size("RNG15_RFL8_NIR8", 128), 8448);
    assert_eq!(
        size("RNG19_RFL8_SIG16_NIR16_DUAL", 128),
        32 + 16 * (12 + 128 * 16) + 32
    );
}

#[test]
fn xyz_matches_manual_formula() {
    let meta = meta("RNG19_RFL8_SIG16_NIR16");
    let lut = Lut::new(&meta);
    let (row, m, r) = (1usize, 5usize, 10_000.0f64);
    let n = 15.0;
    let enc = 2.0 * std::f64::consts::PI * (1.0 - m as f64 / W as f64);
    let az = -(1.0f64).to_radians();
    let phi = (3.0f64).to_radians();
    let x = (r - n) * (enc + az).cos() * phi.cos() + n * enc.cos();
    let y = (r - n) * (enc + az).sin() * phi.cos() + n * enc.sin();
    let z = (r - n) * phi.sin();
    // lidar_to_sensor: rotate 180 deg about z, lift 36 mm.
    let expect = [-x * 1e-3, -y * 1e-3, (z + 36.0) * 1e-3];
    let got = lut.point(row * W + m, r as u32);
    for i in 0..3 {
        assert!(
            (f64::from(got[i]) - expect[i]).abs() < 1e-5,
            "{got:?} vs {expect:?}"
        );
    }
}

#[test]
fn flat_and_nested_metadata_agree() {
    let flat = meta("RNG15_RFL8_NIR8");
    let nested = OusterMetadata::from_json(&nested_json("RNG15_RFL8_NIR8")).unwrap();
    assert_eq!(flat, nested);
    assert_eq!(flat.lidar_mode.as_deref(), Some("16x10"));
}

#[test]
fn metadata_defaults_and_errors() {
    let mut v: serde_json::Value = serde_json::from_str(&flat_json("LEGACY")).unwrap();
    let df = v["data_format"].as_object_mut().unwrap();
    for key in [
        "udp_profile_lidar",
        "pixel_shift_by_row",
        "columns_per_frame",
    ] {
        df.remove(key);
    }
    v.as_object_mut().unwrap().remove("udp_port_lidar");
    let m = OusterMetadata::from_json(&v.to_string()).unwrap();
    assert_eq!(m.udp_profile_lidar, UdpProfile::Legacy);
    assert_eq!(m.udp_port_lidar, 7502);
    // columns_per_frame falls back to lidar_mode.
    assert_eq!(m.columns_per_frame, 16);
    // 6 deg of azimuth spread over 16 columns: shifts 0.27 per degree.
    assert_eq!(m.pixel_shift_by_row, vec![0, 0, 0, 0]);

    let bad = flat_json("LEGACY").replace("[2, 1, 0, -1]", "[2, 1, 0]");
    assert!(matches!(
        OusterMetadata::from_json(&bad),
        Err(OusterError::Metadata(_))
    ));
    let bad = flat_json("NOPE");
    assert!(matches!(
        OusterMetadata::from_json(&bad),
        Err(OusterError::Metadata(_))
    ));
    assert!(matches!(
        OusterMetadata::from_json("{"),
        Err(OusterError::Json(_))
    ));
    assert!(OusterMetadata::from_json("[]").is_err());
    // Geometry no sensor has is refused, naming the field.
    let good = flat_json("LEGACY");
    for (from, to, field) in [
        ("[10.0, 3.0,", "[1000.0, 3.0,", "beam_altitude_angles[0]"),
        ("[10.0, 3.0,", "[1e308, 3.0,", "beam_altitude_angles[0]"),
        ("[3.0, 1.0,", "[3.0, 400.0,", "beam_azimuth_angles[1]"),
        (
            "_mm\": 15.0",
            "_mm\": -1e6",
            "lidar_origin_to_beam_origin_mm",
        ),
    ] {
        let bad = good.replacen(from, to, 1);
        assert_ne!(bad, good);
        match OusterMetadata::from_json(&bad) {
            Err(OusterError::Metadata(m)) => assert!(m.contains(field), "{m}"),
            other => panic!("{field}: {other:?}"),
        }
    }
}

#[test]
fn truncated_pcap_is_an_error_with_offset() {
    let meta = meta("RNG15_RFL8_NIR8");
    let file = pcap_file(1, &capture(&meta));
    let record_len = 16 + capture(&meta)[0].len();
    // Cut inside the second record's body.
    let cut = &file[..24 + record_len + 100];
    match read_pcap(cut, &meta) {
        Err(OusterError::Pcap { offset, msg }) => {
            assert_eq!(offset, 24 + record_len);
            assert!(msg.contains("record 1 truncated"), "{msg}");
        }
        other => panic!("expected truncation error, got {other:?}"),
    }
    // Cut inside a record header.
    let cut = &file[..24 + record_len + 5];
    assert!(matches!(
        read_pcap(cut, &meta),
        Err(OusterError::Pcap { .. })
    ));
    // Shorter than the global header.
    assert!(matches!(
        read_pcap(&file[..10], &meta),
        Err(OusterError::Pcap { offset: 0, .. })
    ));
}

#[test]
fn every_truncation_fails_cleanly() {
    let meta = meta("RNG15_RFL8_NIR8");
    let file = pcap_file(1, &capture(&meta));
    for len in 0..file.len() {
        let _ = read_pcap(&file[..len], &meta);
    }
    // Corrupting any single byte never panics either.
    for at in 0..file.len().min(400) {
        let mut f = file.clone();
        f[at] ^= 0xFF;
        let _ = read_pcap(&f, &meta);
    }
}

#[test]
fn absurd_record_length_is_refused() {
    let meta = meta("RNG15_RFL8_NIR8");
    let mut file = pcap_file(1, &capture(&meta));
    put(&mut file, 24 + 8, &(10u32 << 20).to_le_bytes());
    match read_pcap(&file, &meta) {
        Err(OusterError::Pcap { offset: 24, msg }) => assert!(msg.contains("limit"), "{msg}"),
        other => panic!("expected length error, got {other:?}"),
    }
}

#[test]
fn wrong_packet_size_is_an_error() {
    let meta = meta("RNG15_RFL8_NIR8");
    let mut frames = capture(&meta);
    frames.insert(1, eth_udp(7502, &[0u8; 100]));
    match read_pcap(&pcap_file(1, &frames), &meta) {
        Err(e @ OusterError::PacketSize { .. }) => {
            let OusterError::PacketSize {
                record_index,
                actual,
                expected,
                ..
            } = e
            else {
                unreachable!()
            };
            assert_eq!(
                (record_index, actual, expected),
                (1, 100, meta.lidar_packet_size())
            );
            assert!(e.to_string().contains("RNG15_RFL8_NIR8"));
        }
        other => panic!("expected size error, got {other:?}"),
    }
}

#[test]
fn imu_and_foreign_packets_are_skipped() {
    let meta = meta("RNG15_RFL8_NIR8");
    let mut frames = capture(&meta);
    frames.insert(0, eth_udp(7503, &[0u8; 48]));
    frames.insert(2, eth_udp(7502, &[0u8; 48]));
    frames.insert(3, eth_udp(5353, &[0u8; 300]));
    let mut arp = vec![0u8; 12];
    arp.extend_from_slice(&0x0806u16.to_be_bytes());
    arp.extend_from_slice(&[0u8; 28]);
    frames.insert(4, arp);
    let decoded = read_pcap(&pcap_file(1, &frames), &meta).unwrap();
    check_frames(&meta, &decoded);
}

#[test]
fn pcapng_is_refused() {
    let meta = meta("RNG15_RFL8_NIR8");
    let mut file = vec![0x0A, 0x0D, 0x0D, 0x0A, 28, 0, 0, 0, 0x4D, 0x3C, 0x2B, 0x1A];
    file.resize(64, 0);
    let err = read_pcap(&file, &meta).unwrap_err();
    assert!(matches!(err, OusterError::PcapNg));
    assert!(err.to_string().contains("pcapng"));
}

#[test]
fn fragmented_datagrams_are_reassembled() {
    let meta = meta("RNG19_RFL8_SIG16_NIR16");
    let mut frames = Vec::new();
    for (k, whole) in capture(&meta).iter().enumerate() {
        let ip_payload = udp(7502, &whole[14 + 20 + 8..]);
        let chunks: Vec<&[u8]> = ip_payload.chunks(64).collect();
        let mut pieces: Vec<Vec<u8>> = chunks
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let more = i + 1 < chunks.len();
                ethernet(&ipv4_udp(c, 100 + k as u16, Some((i * 64, more))))
            })
            .collect();
        pieces.swap(0, 2); // out of order
        frames.extend(pieces);
    }
    let decoded = read_pcap(&pcap_file(1, &frames), &meta).unwrap();
    check_frames(&meta, &decoded);
}

#[test]
fn linux_cooked_and_big_endian_captures() {
    let meta = meta("RNG15_RFL8_NIR8");
    let cooked: Vec<Vec<u8>> = capture(&meta)
        .iter()
        .map(|f| {
            let mut sll = vec![0u8; 14];
            sll.extend_from_slice(&0x0800u16.to_be_bytes());
            sll.extend_from_slice(&f[14..]);
            sll
        })
        .collect();
    check_frames(&meta, &read_pcap(&pcap_file(113, &cooked), &meta).unwrap());

    // Same capture written big-endian with nanosecond magic.
    let le = pcap_file(1, &capture(&meta));
    let mut be = Vec::new();
    be.extend_from_slice(&0xA1B2_3C4Du32.to_be_bytes());
    be.extend_from_slice(&le[4..24]);
    for at in [4usize, 6] {
        be[at..at + 2].reverse();
    }
    for at in [8usize, 12, 16, 20] {
        be[at..at + 4].reverse();
    }
    let mut at = 24;
    while at < le.len() {
        let len = u32::from_le_bytes(le[at + 8..at + 12].try_into().unwrap()) as usize;
        for field in 0..4 {
            let mut w: [u8; 4] = le[at + 4 * field..at + 4 * field + 4].try_into().unwrap();
            w.reverse();
            be.extend_from_slice(&w);
        }
        be.extend_from_slice(&le[at + 16..at + 16 + len]);
        at += 16 + len;
    }
    check_frames(&meta, &read_pcap(&be, &meta).unwrap());
}

#[test]
fn invalid_columns_are_not_counted() {
    let meta = meta("LEGACY");
    let frames = vec![
        eth_udp(7502, &packet(&meta, 3, 0, true)),
        eth_udp(7502, &packet(&meta, 3, CPP, false)),
    ];
    let decoded = read_pcap(&pcap_file(1, &frames), &meta).unwrap();
    assert_eq!(decoded.len(), 1);
    assert_eq!(decoded[0].columns_seen, CPP);
}

#[test]
fn destagger_wraps_negative_shifts() {
    assert_eq!(destaggered_column(0, -1, 16), 15);
    assert_eq!(destaggered_column(15, 2, 16), 1);
    assert_eq!(destaggered_column(3, 0, 16), 3);
}

#[test]
fn hand_edited_metadata_is_revalidated() {
    let mut meta = meta("RNG15_RFL8_NIR8");
    meta.pixel_shift_by_row.pop();
    let file = pcap_file(1, &capture(&meta));
    assert!(matches!(
        read_pcap(&file, &meta),
        Err(OusterError::Metadata(_))
    ));
}

//! Decodes a real OS-1-128 capture (RNG15_RFL8_NIR8, 3 frames) and checks
//! the geometry: beam elevations, plausible ranges, and that destaggering
//! lines up the beams of a column (and does so better than the opposite
//! shift sign would).

mod common;

use rangegan_mcap::lidar::ouster_pcap::{self as op, OusterFrame, OusterMetadata};

const DIR: &str = "other_sensors/ouster_os1_128_lb_3frames";

fn load() -> Option<(Vec<u8>, String)> {
    let dir = common::real_data("ouster_pcap")?.join(DIR);
    let pcap = dir.join("OS-1-128_v2.3.0_1024x10_lb_n3.pcap");
    let json = dir.join("OS-1-128_v2.3.0_1024x10.json");
    match (std::fs::read(&pcap), std::fs::read_to_string(&json)) {
        (Ok(p), Ok(j)) => Some((p, j)),
        _ => {
            println!("SKIP: real Ouster capture not found under {DIR}");
            None
        }
    }
}

fn median(v: &mut [f64]) -> f64 {
    assert!(!v.is_empty());
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn wrap_deg(a: f64) -> f64 {
    (a + 180.0).rem_euclid(360.0) - 180.0
}

/// Point back in the lidar frame (mm): undo lidar_to_sensor_transform.
fn to_lidar(meta: &OusterMetadata, p: [f32; 3]) -> [f64; 3] {
    let t = &meta.lidar_to_sensor_transform;
    let d = [
        f64::from(p[0]) * 1e3 - t[3],
        f64::from(p[1]) * 1e3 - t[7],
        f64::from(p[2]) * 1e3 - t[11],
    ];
    // R^T * d
    [0, 1, 2].map(|j| t[j] * d[0] + t[4 + j] * d[1] + t[8 + j] * d[2])
}

fn is_return(p: [f32; 3]) -> bool {
    p != [0.0; 3]
}

/// Max |per-row median elevation - beam altitude| over rows with returns.
fn elevation_error_deg(meta: &OusterMetadata, f: &OusterFrame) -> f64 {
    let (w, n) = (f.scan.width, meta.lidar_origin_to_beam_origin_mm);
    let mut worst: f64 = 0.0;
    for (row, alt) in meta.beam_altitude_angles.iter().enumerate() {
        let mut el: Vec<f64> = f.scan.xyz[row * w..(row + 1) * w]
            .iter()
            .filter(|p| is_return(**p))
            .map(|p| {
                let q = to_lidar(meta, *p);
                q[2].atan2(q[0].hypot(q[1]) - n).to_degrees()
            })
            .collect();
        if el.len() >= 20 {
            worst = worst.max((median(&mut el) - alt).abs());
        }
    }
    worst
}

/// Spread (max - min) of the per-row median z over the steep downward rows
/// (below -11 deg), which see the road: a flat ground needs every such beam
/// at its right elevation, which checks row order against the physical world
/// rather than against the altitude table used to build the points.
fn ground_z_spread_m(meta: &OusterMetadata, f: &OusterFrame) -> f64 {
    let w = f.scan.width;
    let medians: Vec<f64> = meta
        .beam_altitude_angles
        .iter()
        .enumerate()
        .filter(|(_, alt)| **alt < -11.0)
        .map(|(row, _)| {
            let mut z: Vec<f64> = f.scan.xyz[row * w..(row + 1) * w]
                .iter()
                .filter(|p| is_return(**p))
                .map(|p| f64::from(p[2]))
                .collect();
            median(&mut z)
        })
        .collect();
    let max = medians.iter().copied().fold(f64::MIN, f64::max);
    let min = medians.iter().copied().fold(f64::MAX, f64::min);
    max - min
}

/// Median over columns of the azimuth spread (max - min, degrees) of the
/// returns in that column; only returns beyond 2 m to keep parallax tiny.
fn destagger_spread_deg(meta: &OusterMetadata, f: &OusterFrame) -> f64 {
    let (w, h) = (f.scan.width, f.scan.height);
    let mut spreads = Vec::new();
    for col in 0..w {
        let az: Vec<f64> = (0..h)
            .map(|row| to_lidar(meta, f.scan.xyz[row * w + col]))
            .filter(|q| q[0].hypot(q[1]) > 2000.0)
            .map(|q| q[1].atan2(q[0]).to_degrees())
            .collect();
        if az.len() < 10 {
            continue;
        }
        let (s, c) = az.iter().fold((0.0, 0.0), |(s, c), a| {
            (s + a.to_radians().sin(), c + a.to_radians().cos())
        });
        let mean = f64::atan2(s, c).to_degrees();
        let dev: Vec<f64> = az.iter().map(|a| wrap_deg(a - mean)).collect();
        let max = dev.iter().copied().fold(f64::MIN, f64::max);
        let min = dev.iter().copied().fold(f64::MAX, f64::min);
        spreads.push(max - min);
    }
    median(&mut spreads)
}

/// Share of consecutive-column return pairs whose azimuth decreases by
/// 0..2 column steps (the encoder turns clockwise seen from above).
fn monotonic_share(meta: &OusterMetadata, f: &OusterFrame) -> f64 {
    let (w, h) = (f.scan.width, f.scan.height);
    let step = 360.0 / w as f64;
    let (mut good, mut total) = (0usize, 0usize);
    for row in 0..h {
        for col in 1..w {
            let a = f.scan.xyz[row * w + col - 1];
            let b = f.scan.xyz[row * w + col];
            if !is_return(a) || !is_return(b) {
                continue;
            }
            let (qa, qb) = (to_lidar(meta, a), to_lidar(meta, b));
            let d = wrap_deg(qb[1].atan2(qb[0]).to_degrees() - qa[1].atan2(qa[0]).to_degrees());
            total += 1;
            if d < 0.0 && d > -2.0 * step {
                good += 1;
            }
        }
    }
    good as f64 / total as f64
}

#[test]
fn real_os1_128_capture() {
    let Some((pcap, json)) = load() else {
        return;
    };
    let meta = OusterMetadata::from_json(&json).unwrap();
    assert_eq!(meta.lidar_packet_size(), 8448);
    let frames = op::read_pcap(&pcap, &meta).unwrap();
    let ids: Vec<u32> = frames.iter().map(|f| f.frame_id).collect();
    assert_eq!(ids, vec![1795, 1796, 1797]);

    for f in &frames {
        let s = &f.scan;
        assert_eq!((s.height, s.width, s.xyz.len()), (128, 1024, 128 * 1024));
        assert_eq!(f.columns_seen, 1024);
        assert!(f.is_complete());

        let returns: Vec<[f32; 3]> = s.xyz.iter().copied().filter(|p| is_return(*p)).collect();
        let share = returns.len() as f64 / s.xyz.len() as f64;
        let mut ranges: Vec<f64> = returns
            .iter()
            .map(|p| {
                let q = to_lidar(&meta, *p);
                (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() * 1e-3
            })
            .collect();
        let r_med = median(&mut ranges);
        let r_max = ranges.last().copied().unwrap();
        let r_p999 = ranges[ranges.len() * 999 / 1000];
        let far = ranges.iter().filter(|r| **r > 200.0).count();
        let elev = elevation_error_deg(&meta, f);
        let ground = ground_z_spread_m(&meta, f);
        let spread = destagger_spread_deg(&meta, f);
        let mono = monotonic_share(&meta, f);
        let t_max = s
            .time_s
            .as_ref()
            .unwrap()
            .iter()
            .copied()
            .fold(0.0f32, f32::max);
        println!(
            "frame {}: ts {} ns, returns {:.1} %, elevation max err {:.5} deg, ground z spread \
             {:.3} m, range median {:.2} m p99.9 {:.2} m max {:.2} m ({} > 200 m), destagger \
             spread (median) {:.3} deg, monotonic {:.1} %, time_s max {:.4} s",
            f.frame_id,
            f.timestamp_ns,
            share * 100.0,
            elev,
            ground,
            r_med,
            r_p999,
            r_max,
            far,
            spread,
            mono * 100.0,
            t_max
        );
        assert!(share > 0.5, "returns share {share}");
        assert!(elev < 0.5, "elevation error {elev}");
        assert!(ground < 0.1, "ground z spread {ground}");
        assert!((2.0..60.0).contains(&r_med), "median range {r_med}");
        // RNG15 encodes at most 32767 * 8 mm; a handful of far returns
        // (one at 216.8 m in frame 1795) exceed the 200 m spec, so bound the
        // bulk by the 99.9th percentile and the count of far points.
        assert!(
            r_p999 < 200.0 && far < 10 && r_max <= 262.136,
            "ranges {r_p999} {r_max}"
        );
        assert!(spread < 2.0, "destagger spread {spread}");
        assert!(mono > 0.9, "monotonic share {mono}");
        assert!((0.09..0.101).contains(&t_max), "sweep time {t_max}");
    }
    let dt = frames[1].timestamp_ns - frames[0].timestamp_ns;
    assert!(
        (99_000_000..101_000_000).contains(&dt),
        "frame period {dt} ns"
    );
}

/// Share of vertically adjacent return pairs (rows r, r+1, same column)
/// whose ranges differ by more than 0.5 m. Unlike the azimuth spread, this
/// uses only measured ranges, so it tests the destagger direction against
/// the scene itself: misaligned beams put unrelated surfaces side by side.
fn vertical_jump_share(f: &OusterFrame) -> f64 {
    let (w, h) = (f.scan.width, f.scan.height);
    let range = |i: usize| {
        let p = f.scan.xyz[i];
        f64::from(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
    };
    let (mut pairs, mut jumps) = (0usize, 0usize);
    for row in 0..h - 1 {
        for col in 0..w {
            let (a, b) = (range(row * w + col), range((row + 1) * w + col));
            if a > 0.0 && b > 0.0 {
                pairs += 1;
                jumps += usize::from((a - b).abs() > 0.5);
            }
        }
    }
    jumps as f64 / pairs as f64
}

#[test]
fn real_capture_opposite_shift_sign_is_worse() {
    let Some((pcap, json)) = load() else {
        return;
    };
    let meta = OusterMetadata::from_json(&json).unwrap();
    let mut flipped = meta.clone();
    flipped.pixel_shift_by_row.iter_mut().for_each(|s| *s = -*s);
    let right = &op::read_pcap(&pcap, &meta).unwrap()[1];
    let wrong = &op::read_pcap(&pcap, &flipped).unwrap()[1];
    let (good, bad) = (
        destagger_spread_deg(&meta, right),
        destagger_spread_deg(&flipped, wrong),
    );
    let (good_j, bad_j) = (vertical_jump_share(right), vertical_jump_share(wrong));
    println!(
        "destagger azimuth spread: +shift {good:.3} deg, -shift {bad:.3} deg; vertical \
         range jumps > 0.5 m: +shift {:.1} %, -shift {:.1} %",
        good_j * 100.0,
        bad_j * 100.0
    );
    assert!(bad > 4.0 * good && bad > 2.0, "+{good} vs -{bad}");
    assert!(bad_j > 2.0 * good_j, "jumps +{good_j} vs -{bad_j}");
}

#[test]
fn real_metadata_shifts_match_azimuth_derivation() {
    let Some((_, json)) = load() else {
        return;
    };
    let meta = OusterMetadata::from_json(&json).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&json).unwrap();
    v["data_format"]
        .as_object_mut()
        .unwrap()
        .remove("pixel_shift_by_row");
    let derived = OusterMetadata::from_json(&v.to_string()).unwrap();
    assert_eq!(derived.pixel_shift_by_row, meta.pixel_shift_by_row);
}

//! Tests of the per-pixel features: completion of dropped pixels, incidence, edges.

use super::*;
use crate::lidar::AngleGrid;

/// An image of a flat ground plane `height_m` below the sensor, rows looking down.
fn ground_image(h: usize, w: usize, height_m: f32) -> RangeImage {
    let angles = AngleGrid::regular_columns(h, w, |i| -0.05 - 0.02 * i as f32);
    let mut img = RangeImage::empty(angles);
    for k in 0..img.len() {
        let phi = img.angles.elevation_rad[k];
        img.range_m[k] = height_m / (-phi).sin();
        // Class 40 (road), instance 3 in the high bits.
        img.label[k] = 40 | (3 << 16);
    }
    img
}

#[test]
fn incidence_of_flat_ground_matches_elevation() {
    let img = ground_image(8, 64, 1.7);
    let f = ScanFeatures::from_image(&img, &FeatureOptions::default());
    for k in 0..f.len() {
        // The ray meets a horizontal plane at incidence pi/2 - |phi|.
        let expected = std::f32::consts::FRAC_PI_2 + img.angles.elevation_rad[k];
        assert!(
            (f.incidence_rad[k] - expected).abs() < 0.02,
            "k={k}: {} vs {expected}",
            f.incidence_rad[k]
        );
    }
}

#[test]
fn dropped_pixels_are_filled_from_neighbours() {
    let mut img = ground_image(8, 64, 1.7);
    let truth = img.clone();
    let holes = [3 * 64 + 10, 3 * 64 + 11, 5 * 64 + 63];
    for k in holes {
        img.range_m[k] = 0.0;
        img.label[k] = 0;
    }
    let f = ScanFeatures::from_image(&img, &FeatureOptions::default());
    for k in holes {
        assert!(!f.kept[k]);
        let rel = (f.range_m[k] - truth.range_m[k]).abs() / truth.range_m[k];
        // Same-row neighbours fill exactly on ground (rows differ in range).
        assert!(
            rel < 1e-6,
            "k={k}: {} vs {}",
            f.range_m[k],
            truth.range_m[k]
        );
        assert_eq!(f.class[k], 40, "class from neighbours");
        assert!(f.incidence_rad[k].is_finite());
    }
    assert_eq!(f.kept.iter().filter(|k| !**k).count(), holes.len());
    assert!((f.drop_rate() - 3.0 / 512.0).abs() < 1e-9);
    assert_eq!(f.row[5 * 64 + 63], 5);
}

#[test]
fn holes_on_one_plane_get_its_geometry_back() {
    let mut img = ground_image(24, 64, 1.7);
    let truth = img.clone();
    // A 10 x 10 block: most of it beyond the neighbour fill's reach.
    let hole: Vec<usize> = (8..18)
        .flat_map(|i| (20..30).map(move |j| i * 64 + j))
        .collect();
    for &k in &hole {
        img.range_m[k] = 0.0;
    }
    let f = ScanFeatures::from_image(&img, &FeatureOptions::default());
    for &k in &hole {
        let rel = (f.range_m[k] - truth.range_m[k]).abs() / truth.range_m[k];
        assert!(
            rel < 1e-4,
            "k={k}: {} vs {}",
            f.range_m[k],
            truth.range_m[k]
        );
        let expected = std::f32::consts::FRAC_PI_2 + img.angles.elevation_rad[k];
        assert!((f.incidence_rad[k] - expected).abs() < 0.02, "k={k}");
    }
}

/// A given completion (the GAN's x_d) is a guess; a hole spanned by one surface has
/// its geometry measured on both sides. A completion that disagrees with it would
/// mark every dropped pixel as a depth edge with a grazing normal, and make drops
/// look like edge and incidence physics.
#[test]
fn a_given_completion_fills_only_what_no_surface_spans() {
    let mut img = ground_image(24, 64, 1.7);
    let truth = img.clone();
    let bridged = 14 * 64 + 30;
    let wide: Vec<usize> = (16..24)
        .flat_map(|i| (0..64).map(move |j| i * 64 + j))
        .collect();
    for &k in wide.iter().chain([&bridged]) {
        img.range_m[k] = 0.0;
    }
    let completed: Vec<f32> = truth.range_m.iter().map(|r| 1.3 * r).collect();
    let f = ScanFeatures::from_image_completed(&img, Some(&completed), &FeatureOptions::default());
    let rel = (f.range_m[bridged] - truth.range_m[bridged]).abs() / truth.range_m[bridged];
    assert!(rel < 1e-4, "bridged hole took {}", f.range_m[bridged]);
    let expected = std::f32::consts::FRAC_PI_2 + img.angles.elevation_rad[bridged];
    assert!((f.incidence_rad[bridged] - expected).abs() < 0.02);
    // The bottom rows, dropped all round: no return closes a column below them or
    // a row beside them, so nothing spans them and the completion fills them.
    let filled = wide
        .iter()
        .filter(|&&k| f.range_m[k] == completed[k])
        .count();
    assert_eq!(filled, wide.len());
}

/// In the upper half a dropped ray mostly met nothing (sky, or beyond reach). A
/// completion gives every pixel a depth; there it would put the no-returns at the
/// model's typical depth, so the upper half keeps the neighbour fill.
#[test]
fn a_given_completion_leaves_the_upper_half_to_the_neighbour_fill() {
    let mut img = ground_image(24, 64, 1.7);
    let top: Vec<usize> = (0..3 * 64).collect();
    for &k in &top {
        img.range_m[k] = 0.0;
    }
    let completed = vec![35.0; img.len()];
    let options = FeatureOptions::default();
    let with = ScanFeatures::from_image_completed(&img, Some(&completed), &options);
    let without = ScanFeatures::from_image(&img, &options);
    assert!(top.iter().any(|&k| with.range_m[k].is_finite()));
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&with.range_m), bits(&without.range_m));
}

/// Drops the block `rows` x `columns` of `img`, completes it, and checks the range
/// and incidence of every completed pixel against the image's own and `expected_incidence`.
fn assert_block_completed_as(
    mut img: RangeImage,
    rows: std::ops::Range<usize>,
    columns: std::ops::Range<usize>,
    expected_incidence: &[f32],
) {
    let (w, truth) = (img.width, img.range_m.clone());
    let hole: Vec<usize> = rows
        .flat_map(|i| columns.clone().map(move |j| i * w + j))
        .collect();
    for &k in &hole {
        img.range_m[k] = 0.0;
    }
    let f = ScanFeatures::from_image(&img, &FeatureOptions::default());
    let mut checked = 0;
    for &k in &hole {
        if f.range_m[k].is_nan() {
            continue; // beyond the neighbour fill's reach: no geometry
        }
        let rel = (f.range_m[k] - truth[k]).abs() / truth[k];
        assert!(rel < 1e-3, "k={k}: {} vs {}", f.range_m[k], truth[k]);
        assert!(
            (f.incidence_rad[k] - expected_incidence[k]).abs() < 0.05,
            "k={k}: incidence {} vs {}",
            f.incidence_rad[k],
            expected_incidence[k]
        );
        checked += 1;
    }
    assert!(
        checked >= hole.len() / 3,
        "only {checked} of {} completed",
        hole.len()
    );
}

#[test]
fn wide_holes_in_the_ground_are_completed_as_ground() {
    // Too tall and too wide for a bridge: rows 4-21 over 60 columns dropped.
    let img = ground_image(24, 256, 1.7);
    let grazing: Vec<f32> = (0..img.len())
        .map(|k| std::f32::consts::FRAC_PI_2 + img.angles.elevation_rad[k])
        .collect();
    assert_block_completed_as(img, 4..22, 20..80, &grazing);
}

#[test]
fn holes_under_a_wall_are_completed_as_the_wall() {
    // A wall 6 m away over columns 100-159 stands on the ground (rows 0-11 see
    // it, rows 12 and below the ground in front of it); the wall's rows 5-11
    // are dropped there, too tall and wide for a bridge.
    let (h, w, depth, wall_m) = (24, 256, 1.7f32, 6.0f32);
    let mut img = ground_image(h, w, depth);
    let mut facing = vec![0.0f32; h * w];
    for (k, incidence) in facing.iter_mut().enumerate() {
        let (j, e) = (k % w, img.angles.elevation_rad[k]);
        let on_wall = (100..160).contains(&j) && depth / (-e).tan() > wall_m;
        *incidence = if on_wall {
            img.range_m[k] = wall_m / e.cos();
            // A vertical wall facing the sensor: incidence = |elevation|.
            -e
        } else {
            std::f32::consts::FRAC_PI_2 + e
        };
    }
    assert_block_completed_as(img, 5..12, 100..160, &facing);
}

#[test]
fn holes_between_two_surfaces_are_not_bridged() {
    // A wall at 20 m behind an object at 8 m: the 6 dropped columns between them
    // in each row must not be interpolated from both.
    let angles = AngleGrid::regular_columns(4, 64, |i| 0.02 * i as f32);
    let mut img = RangeImage::empty(angles);
    for k in 0..img.len() {
        let j = k % 64;
        img.range_m[k] = match j {
            0..20 => 8.0,
            20..26 => 0.0,
            _ => 20.0,
        };
    }
    let bridged = bridge_fill(
        &Grid {
            h: 4,
            w: 64,
            wrap: false,
        },
        &img,
        &(0..img.len())
            .map(|k| img.range_m[k] > 0.0)
            .collect::<Vec<_>>(),
        16,
    );
    assert!((0..4).all(|i| (20..26).all(|j| bridged[i * 64 + j].is_nan())));
}

#[test]
fn far_holes_stay_without_geometry() {
    let mut img = ground_image(8, 64, 1.7);
    // Blank the top three rows entirely (a sky): beyond one fill pass from row 3.
    for k in 0..3 * 64 {
        img.range_m[k] = 0.0;
    }
    let options = FeatureOptions {
        fill_passes: 1,
        ..FeatureOptions::default()
    };
    let f = ScanFeatures::from_image(&img, &options);
    assert!(f.range_m[2 * 64 + 5].is_finite(), "adjacent row filled");
    assert!(f.range_m[5].is_nan(), "top row too far to fill");
    assert!(f.incidence_rad[5].is_nan());
}

#[test]
fn edge_proximity_counts_steps_from_a_depth_jump() {
    let angles = AngleGrid::regular_columns(4, 32, |i| 0.01 * i as f32);
    let mut img = RangeImage::empty(angles);
    for k in 0..img.len() {
        // A wall at 10 m on columns 0..16, at 30 m beyond.
        img.range_m[k] = if k % 32 < 16 { 10.0 } else { 30.0 };
    }
    let options = FeatureOptions {
        wrap_azimuth: false,
        ..FeatureOptions::default()
    };
    let f = ScanFeatures::from_image(&img, &options);
    assert_eq!(f.edge_px[15], 0);
    assert_eq!(f.edge_px[16], 0);
    assert_eq!(f.edge_px[12], 3);
    assert_eq!(f.edge_px[20], 4);
    assert_eq!(f.edge_px[0], 8, "capped far from the edge");
    // With wrapping, column 0 sits next to column 31: another edge.
    let wrapped = ScanFeatures::from_image(&img, &FeatureOptions::default());
    assert_eq!(wrapped.edge_px[0], 0);
    assert_eq!(wrapped.edge_px[1], 1);
}

#[test]
fn most_common_prefers_frequency_then_smallest() {
    assert_eq!(most_common(&mut []), None);
    assert_eq!(most_common(&mut [7, 3, 7, 3, 9]), Some(3));
    assert_eq!(most_common(&mut [7, 3, 7]), Some(7));
}

//! Tests of grid resizing and range-image resampling.

use super::super::range_image::column_azimuth;
use super::*;

fn uniform_profile(beams: usize, columns: usize, top: f32, bottom: f32) -> SensorProfile {
    let step = (top - bottom) / (beams - 1) as f32;
    SensorProfile {
        name: "uniform".into(),
        elevation_deg: (0..beams).map(|i| top - step * i as f32).collect(),
        azimuth_offset_deg: None,
        columns,
        min_range_m: 0.5,
        max_range_m: 100.0,
    }
}

fn angle_diff(a: f32, b: f32) -> f32 {
    super::super::profile::wrap_pi(a - b).abs()
}

#[test]
fn regular_columns_resize_exactly_and_uniform_rows_stay_uniform() {
    // 16 beams, 2 deg apart; 2x rows and 4x columns.
    let p = uniform_profile(16, 256, 15.0, -15.0);
    let g = p.angle_grid().resized(32, 1024);
    assert_eq!((g.height, g.width), (32, 1024));
    for j in [0usize, 1, 511, 512, 1023] {
        assert!(
            angle_diff(g.azimuth_rad[5 * 1024 + j], column_azimuth(j, 1024)) < 1e-5,
            "column {j}"
        );
    }
    // Pixel-centre alignment: new rows at source coordinates i/2 - 0.25, i.e.
    // 1 deg apart starting half a new row above the old top row.
    for i in 0..32 {
        let expect = (15.0 + 0.5 - i as f32).to_radians();
        assert!(
            (g.elevation_rad[i * 1024 + 7] - expect).abs() < 1e-5,
            "row {i}: {} vs {expect}",
            g.elevation_rad[i * 1024 + 7]
        );
    }
    // Downsampling back gives the original grid.
    let back = g.resized(16, 256);
    let orig = p.angle_grid();
    for k in 0..orig.len() {
        assert!(angle_diff(back.azimuth_rad[k], orig.azimuth_rad[k]) < 1e-5);
        assert!((back.elevation_rad[k] - orig.elevation_rad[k]).abs() < 1e-5);
    }
}

#[test]
fn azimuth_interpolation_is_circular_across_the_seam() {
    // Two columns at +170 and -170 deg (via a custom grid): midpoints must be at
    // +-180, not 0, which a plain lerp of the angles would give.
    let g = AngleGrid {
        height: 1,
        width: 2,
        elevation_rad: vec![0.0, 0.0],
        azimuth_rad: vec![170f32.to_radians(), (-170f32).to_radians()],
    };
    let r = g.resized(1, 4);
    // Output column 1 reads source column 0.25 (from +170 towards -170 across
    // +-180); column 3 reads 1.25, i.e. from -170 back towards +170.
    for a in &r.azimuth_rad {
        assert!(
            a.abs() > 160f32.to_radians(),
            "azimuth {} deg leaked to the front",
            a.to_degrees()
        );
    }
    // A quarter of the way along the 20 deg arc (interpolating the chord, then
    // atan2, lands within 0.05 deg of the arc's quarter point).
    assert!(
        angle_diff(r.azimuth_rad[1], 175f32.to_radians()) < 0.05f32.to_radians(),
        "{}",
        r.azimuth_rad[1].to_degrees()
    );
    assert!(
        angle_diff(r.azimuth_rad[3], (-175f32).to_radians()) < 0.05f32.to_radians(),
        "{}",
        r.azimuth_rad[3].to_degrees()
    );
}

#[test]
fn profile_resampling_matches_grid_resizing() {
    let p = SensorProfile::kitti_hdl64e().with_columns(512);
    let q = p.resampled(128, 2048);
    assert_eq!((q.beams(), q.columns), (128, 2048));
    assert!(q.elevation_deg.windows(2).all(|w| w[0] > w[1]));
    let a = q.angle_grid();
    let b = p.angle_grid().resized(128, 2048);
    for k in (0..a.len()).step_by(97) {
        assert!((a.elevation_rad[k] - b.elevation_rad[k]).abs() < 1e-5);
        assert!(angle_diff(a.azimuth_rad[k], b.azimuth_rad[k]) < 1e-5);
    }
    // Each new row pair brackets its old row: rows 2i and 2i+1 straddle row i.
    for i in 1..63 {
        assert!(
            q.elevation_deg[2 * i] > p.elevation_deg[i]
                && q.elevation_deg[2 * i + 1] < p.elevation_deg[i]
        );
    }
}

/// A range image on a uniform profile whose range is a smooth function of the
/// direction, with a hole.
fn smooth_image(p: &SensorProfile) -> RangeImage {
    let mut img = RangeImage::empty(p.angle_grid());
    for k in 0..img.len() {
        let (phi, theta) = (img.angles.elevation_rad[k], img.angles.azimuth_rad[k]);
        let d = 20.0 + 5.0 * theta.cos() + 30.0 * phi;
        img.range_m[k] = d;
        let [x, y, z] = img.angles.direction(k);
        img.xyz[k] = [d * x, d * y, d * z];
        img.intensity[k] = 1.0;
        img.label[k] = 7;
        img.point_index[k] = k as u32;
    }
    img
}

#[test]
fn identity_resampling_returns_the_image() {
    let p = uniform_profile(8, 64, 10.0, -10.0);
    let img = smooth_image(&p);
    for m in [Interpolation::Nearest, Interpolation::Bilinear] {
        let out = resample_to_profile(&img, &p, m);
        for k in 0..img.len() {
            assert!(
                (out.range_m[k] - img.range_m[k]).abs() < 1e-3,
                "{} pixel {k}",
                m.name()
            );
        }
    }
    let nearest = resample_to_profile(&img, &p, Interpolation::Nearest);
    assert_eq!(nearest.point_index, img.point_index);
}

#[test]
fn bilinear_upsampling_is_closer_than_nearest_on_smooth_scenes() {
    let p = uniform_profile(8, 64, 10.0, -10.0);
    let img = smooth_image(&p);
    let fine = p.angle_grid().resized(8, 256);
    let truth = |k: usize| 20.0 + 5.0 * fine.azimuth_rad[k].cos() + 30.0 * fine.elevation_rad[k];
    let err = |m| {
        let out = resample_image(&img, &fine, m);
        assert_eq!(out.valid_count(), fine.len());
        (0..fine.len())
            .map(|k| (out.range_m[k] - truth(k)).abs())
            .fold(0.0f32, f32::max)
    };
    let (near, bil) = (err(Interpolation::Nearest), err(Interpolation::Bilinear));
    assert!(
        bil < 0.05 && bil < near / 5.0,
        "bilinear {bil} nearest {near}"
    );
}

#[test]
fn bilinear_never_blends_with_empty_pixels() {
    let p = uniform_profile(4, 16, 3.0, -3.0);
    let mut img = RangeImage::empty(p.angle_grid());
    // Left half at 10 m, right half empty, one pixel at 30 m on row 1.
    for i in 0..4 {
        for j in 0..8 {
            img.range_m[i * 16 + j] = 10.0;
        }
    }
    img.range_m[16 + 3] = 30.0;
    let out = resample_image(
        &img,
        &p.angle_grid().resized(8, 64),
        Interpolation::Bilinear,
    );
    let mut seen_blend = false;
    for k in 0..out.len() {
        let r = out.range_m[k];
        assert!(
            r == 0.0 || (10.0 - 1e-4..=30.0 + 1e-4).contains(&r),
            "pixel {k}: {r}"
        );
        seen_blend |= r > 10.5 && r < 29.5;
    }
    assert!(
        seen_blend,
        "the 30 m pixel is blended with its valid neighbours"
    );
    // Validity follows the nearest source pixel: half the columns are valid.
    assert_eq!(out.valid_count(), out.len() / 2);
    let near = resample_image(&img, &p.angle_grid().resized(8, 64), Interpolation::Nearest);
    assert_eq!(near.valid_count(), out.valid_count());
}

#[test]
fn resampling_onto_another_sensor_reads_the_right_directions() {
    // A 64-beam source, 0.5 deg apart, and a 16-beam target on the same span:
    // every target beam lies on a source row, so values are reproduced.
    let src = uniform_profile(61, 360, 15.0, -15.0);
    let img = smooth_image(&src);
    let dst = uniform_profile(16, 1024, 15.0, -15.0);
    let out = resample_to_profile(&img, &dst, Interpolation::Bilinear);
    assert_eq!(out.valid_count(), out.len());
    for k in 0..out.len() {
        let truth =
            20.0 + 5.0 * out.angles.azimuth_rad[k].cos() + 30.0 * out.angles.elevation_rad[k];
        assert!((out.range_m[k] - truth).abs() < 0.01, "pixel {k}");
        let n = out.xyz[k].iter().map(|c| c * c).sum::<f32>().sqrt();
        assert!((n - out.range_m[k]).abs() < 1e-3);
    }
    // A target reaching beyond the source's field of view stays empty there.
    let wide = uniform_profile(9, 64, 40.0, -40.0);
    let out = resample_to_profile(&img, &wide, Interpolation::Nearest);
    for i in 0..9 {
        let inside = wide.elevation_deg[i].abs() <= 15.25;
        let valid = (0..64).filter(|&j| out.is_valid(i * 64 + j)).count();
        assert_eq!(
            valid,
            if inside { 64 } else { 0 },
            "row {i} at {} deg",
            wide.elevation_deg[i]
        );
    }
}

/// 8 x 512: rows 0-3 a wall at 10 m, rows 4-7 the road at 40 m (slightly varying).
fn edge_image(p: &SensorProfile) -> RangeImage {
    let mut img = smooth_image(p);
    for k in 0..img.len() {
        let d = if k / 512 < 4 {
            10.0
        } else {
            40.0 + 0.001 * (k % 512) as f32
        };
        img.range_m[k] = d;
        let [x, y, z] = img.angles.direction(k);
        img.xyz[k] = [d * x, d * y, d * z];
    }
    img
}

#[test]
fn surface_resampling_never_averages_across_a_depth_edge() {
    let p = uniform_profile(8, 512, 7.0, -7.0);
    let img = edge_image(&p);
    let fine = p.angle_grid().resized(16, 512);
    let on_a_surface = |d: f32| (d - 10.0).abs() < 1e-4 || (40.0..=40.52).contains(&d);
    let bilinear = resample_image(&img, &fine, Interpolation::Bilinear);
    assert!(bilinear.range_m.iter().any(|d| !on_a_surface(*d)));
    // Without a guide, with the edge between rows (2 deg apart) trusted, the nearest row
    // decides: new rows 7 (source row 3.25) and 8 (3.75) go to the wall and to the road.
    let trusting = SurfaceRule {
        trust_below_deg: 3.0,
        ..SurfaceRule::default()
    };
    let edge = resample_by_surface(&img, &fine, &trusting, None);
    assert_eq!(edge.valid_count(), bilinear.valid_count());
    for (k, d) in edge.range_m.iter().enumerate() {
        assert!(on_a_surface(*d), "pixel {k}: {d}");
    }
    assert!(on_a_surface(edge.range_m[7 * 512 + 5]) && edge.range_m[7 * 512 + 5] < 11.0);
    assert!(edge.range_m[8 * 512 + 5] >= 40.0);
    // A guide that puts new row 7 on the road wins over the nearer wall row.
    let guide_target: Vec<f32> = (0..fine.len())
        .map(|k| if k / 512 < 7 { 11.0 } else { 38.0 })
        .collect();
    let guide_source: Vec<f32> = (0..img.len())
        .map(|k| if k / 512 < 4 { 11.0 } else { 38.0 })
        .collect();
    let guide = Some(Guide {
        target_m: &guide_target,
        source_m: &guide_source,
    });
    // With the shipped margin the guide overrides the blend only where it clearly
    // disagrees with it: new row 7 (a quarter road) goes to the road, new row 8 (three
    // quarters road) is blended, as bilinear would.
    let margin = resample_by_surface(&img, &fine, &SurfaceRule::default(), guide);
    assert!(margin.range_m[7 * 512 + 5] >= 40.0);
    assert!((margin.range_m[8 * 512 + 5] - bilinear.range_m[8 * 512 + 5]).abs() < 1e-3);
    // A guide that sees the edge exactly, trusted without a margin: never averaged.
    let exact = SurfaceRule {
        guide_jump: 0.0,
        ..SurfaceRule::default()
    };
    let guided = resample_by_surface(&img, &fine, &exact, guide);
    for (k, d) in guided.range_m.iter().enumerate() {
        assert!(on_a_surface(*d), "pixel {k}: {d}");
    }
    assert!(guided.range_m[7 * 512 + 5] >= 40.0);
    assert!((guided.range_m[6 * 512 + 5] - 10.0).abs() < 1e-4);
}

#[test]
fn surface_resampling_keeps_measured_returns_exactly() {
    let p = uniform_profile(8, 512, 7.0, -7.0);
    let mut img = edge_image(&p);
    img.range_m[3 * 512 + 9] = 0.0;
    let out = resample_by_surface(&img, &p.angle_grid(), &SurfaceRule::default(), None);
    for k in 0..img.len() {
        assert_eq!(out.range_m[k].to_bits(), img.range_m[k].to_bits(), "{k}");
        if img.is_valid(k) {
            assert_eq!(out.xyz[k], img.xyz[k]);
            assert_eq!(out.point_index[k], img.point_index[k]);
        } else {
            assert_eq!(out.point_index[k], NO_POINT);
        }
    }
}

/// Moves every return of `img` `fraction` of a column clockwise of its pixel's centre
/// (its range kept), as a projected scan's nearest return lies anywhere in its pixel.
fn measure_clockwise(img: &mut RangeImage, fraction: f32) {
    let shift = fraction * std::f32::consts::TAU / img.width as f32;
    for k in 0..img.len() {
        let (phi, theta) = (
            img.angles.elevation_rad[k],
            img.angles.azimuth_rad[k] - shift,
        );
        let d = img.range_m[k];
        img.xyz[k] = [
            d * phi.cos() * theta.cos(),
            d * phi.cos() * theta.sin(),
            d * phi.sin(),
        ];
    }
}

#[test]
fn a_finer_azimuth_grid_keeps_each_return_where_it_was_measured() {
    // 8 x 128, each return measured 0.3 of a pixel clockwise of its pixel's centre, as a
    // projected scan's nearest return lies anywhere inside its pixel.
    let p = uniform_profile(8, 128, 7.0, -7.0);
    let mut img = smooth_image(&p);
    measure_clockwise(&mut img, 0.3);
    let fine = p.angle_grid().resized(8, 512);
    let out = resample_by_surface(&img, &fine, &SurfaceRule::default(), None);
    let bilinear = resample_image(&img, &fine, Interpolation::Bilinear);
    let mut blended = 0;
    for k in 0..img.len() {
        let [x, y, _] = img.xyz[k];
        let measured = y.atan2(x);
        let row = k / 128;
        let at = (0..512)
            .map(|c| row * 512 + c)
            .min_by(|&a, &b| {
                angle_diff(fine.azimuth_rad[a], measured)
                    .total_cmp(&angle_diff(fine.azimuth_rad[b], measured))
            })
            .unwrap();
        assert_eq!(out.range_m[at].to_bits(), img.range_m[k].to_bits(), "{k}");
        assert_eq!((out.point_index[at], out.xyz[at]), (k as u32, img.xyz[k]));
        blended += usize::from(bilinear.range_m[at] != img.range_m[k]);
    }
    assert!(blended > img.len() / 2, "bilinear blends them: {blended}");
    // The pixels between measured returns are still filled.
    assert_eq!(out.valid_count(), bilinear.valid_count());
}

#[test]
fn a_pixel_is_never_nearer_than_the_return_its_span_kept() {
    // A pole at 5 m before a wall at 30 m, every return measured 0.4 of a pixel clockwise
    // of its pixel's centre: the first finer pixels right of the pole lie closer to the
    // pole's return than to the wall's, but inside the wall's pixel, whose span held no
    // return nearer than the wall's (projection keeps the nearest).
    let p = uniform_profile(8, 128, 7.0, -7.0);
    let mut img = smooth_image(&p);
    for k in 0..img.len() {
        img.range_m[k] = if (40..44).contains(&(k % 128)) {
            5.0
        } else {
            30.0
        };
    }
    measure_clockwise(&mut img, 0.4);
    let fine = p.angle_grid().resized(8, 512);
    let out = resample_by_surface(&img, &fine, &SurfaceRule::default(), None);
    for k in 0..fine.len() {
        let own = (k / 512) * 128 + (k % 512) / 4;
        let floor = img.range_m[own] * (1.0 - 1e-5);
        assert!(out.range_m[k] >= floor, "{k}: {}", out.range_m[k]);
    }
    // The pole still fills the finer pixels of its own span next to its return.
    let row = 3 * 512;
    let near = |a: f32, b: f32| (a - b).abs() < 1e-3;
    assert!(near(out.range_m[row + 4 * 43 + 3], 5.0));
    assert!(near(out.range_m[row + 4 * 44], 30.0));
}

#[test]
fn column_weights_follow_the_measured_azimuths() {
    // Returns of columns 3 and 4 measured 0.4 left of and 0.2 right of their centres
    // (in columns, so 1.6 columns apart): a target at 3.5 lies 0.9 / 1.6 of the way.
    let mut measured = vec![f32::NAN; 8];
    measured[3] = 2.6;
    measured[4] = 4.2;
    let s = column_share(&measured, 3, 4, 3, 3.5, 8);
    assert!((s - 0.9 / 1.6).abs() < 1e-5, "{s}");
    // Without a measured azimuth on both sides: the pixel centres.
    assert_eq!(column_share(&measured, 3, 5, 3, 3.25, 8), 0.25);
    // Across the seam (columns 7 and 0 of 8).
    measured[7] = 7.3;
    measured[0] = 7.9;
    let s = column_share(&measured, 7, 0, 7, 7.6, 8);
    assert!((s - 0.5).abs() < 1e-5, "{s}");
}

//! Tests of the pixels a fit uses: how returns enclose them, the level planes that
//! complete them, and their collection.

use super::enclosure::{enclosures, laser_enclosures};
use super::level_plane::{ceiling_height_m, ceiling_range, open_ground_range};
use super::{ENCLOSED_PX, ENCLOSURE_CAP_PX, Pixels};
use crate::diagnose::features::ScanFeatures;

/// A scan of level ground 1.5 m down, rows 1 deg apart from -1 deg down, 64
/// columns; the rows looking farther than `dropped_beyond_m` lost their rays,
/// and the fill copied the nearest return's range into them.
fn far_ground_dropped(rows: usize, dropped_beyond_m: f32) -> ScanFeatures {
    let elevation = |i: usize| -(1.0 + i as f32).to_radians();
    let nearest_kept = (0..rows)
        .map(|i| 1.5 / (-elevation(i)).sin())
        .find(|&r| r <= dropped_beyond_m)
        .unwrap_or(f32::NAN);
    level_rows(rows, |i| {
        let e = elevation(i);
        let r = 1.5 / (-e).sin();
        let kept = r <= dropped_beyond_m;
        let range = if kept { r } else { nearest_kept };
        (e, kept, range, std::f32::consts::FRAC_PI_2 + e)
    })
}

/// Rows looking up 15 deg to 1 deg under a ceiling 1.5 m above the sensor, 64
/// columns; rays meeting it farther than 15 m lost their returns (grazing), and
/// the fill copied a far wall's 40 m into them.
fn ceiling_grazing_dropped() -> ScanFeatures {
    level_rows(15, |i| {
        let e = (15.0 - i as f32).to_radians();
        let r = 1.5 / e.sin();
        let kept = r <= 15.0;
        (e, kept, if kept { r } else { 40.0 }, 0.3)
    })
}

/// A scan of 64 columns whose every row `i` is the same all round:
/// `row(i)` = (elevation, kept, range, incidence).
fn level_rows(rows: usize, row: impl Fn(usize) -> (f32, bool, f32, f32)) -> ScanFeatures {
    let w = 64;
    let mut f = ScanFeatures::empty(rows, w);
    for i in 0..rows {
        let (e, kept, range, incidence) = row(i);
        for j in 0..w {
            f.row.push(i as u32);
            f.azimuth_rad
                .push(j as f32 * std::f32::consts::TAU / w as f32);
            f.elevation_rad.push(e);
            f.range_m.push(range);
            f.incidence_rad.push(incidence);
            f.edge_px.push(8);
            f.row_edge_px.push(8);
            f.class.push(0);
            f.kept.push(kept);
        }
    }
    f
}

#[test]
fn a_level_ceiling_completes_the_upward_rows_that_grazing_drops_emptied() {
    let mut f = ceiling_grazing_dropped();
    assert!((ceiling_height_m(std::slice::from_ref(&f)).unwrap() - 1.5).abs() < 1e-3);
    // A pillar 12 m away in column 3, seen by the lowest row: the rays above it
    // whose ceiling point lies beyond 12 m hit the pillar, not the ceiling.
    let k = 14 * f.width + 3;
    f.kept[k] = true;
    f.range_m[k] = 12.0 / f.elevation_rad[k].cos();
    let ceiling = ceiling_range(&f, 1.5, 60.0);
    for (k, &c) in ceiling.iter().enumerate() {
        let e = f.elevation_rad[k];
        let beyond_pillar = k % f.width == 3 && 1.5 / e.tan() >= 12.0;
        if f.kept[k] || beyond_pillar || 1.5 / e.sin() > 60.0 {
            assert!(c.is_nan(), "pixel {k}: {c}");
        } else {
            assert!((c - 1.5 / e.sin()).abs() < 1e-3, "pixel {k}: {c}");
        }
    }
    // The completed pixels reach the fit as grazing ceiling, not as the wall.
    let px = Pixels::collect(std::slice::from_ref(&f), 60.0);
    let plane: Vec<usize> = (0..px.len()).filter(|&i| px.level_plane[i]).collect();
    assert!(!plane.is_empty());
    for i in plane {
        let e = px.row_elevation_rad[px.row[i] as usize];
        assert!(!px.kept[i] && px.range_m[i] > 15.0);
        assert!(
            (px.range_m[i] * e.sin() - 1.5).abs() < 1e-3,
            "{}",
            px.range_m[i]
        );
        assert!(px.cos_incidence[i] < 0.1);
    }

    // In the open, upward returns spread over trees and facades: no ceiling.
    let mut open = ceiling_grazing_dropped();
    for k in (0..open.len()).filter(|&k| open.kept[k]) {
        let height = 0.5 + (k % 37) as f32 * 0.3;
        open.range_m[k] = height / open.elevation_rad[k].sin();
    }
    assert_eq!(ceiling_height_m(std::slice::from_ref(&open)), None);
}

#[test]
fn open_ground_takes_the_level_grounds_range_where_nothing_stands_in_front() {
    let f = far_ground_dropped(30, 20.0);
    let enclosure = enclosures(&f).0;
    let open_above = -(3.0f32).to_radians();
    let ground = open_ground_range(&f, &enclosure, open_above, 1.5);
    for (k, &g) in ground.iter().enumerate() {
        let e = f.elevation_rad[k];
        let far = !f.kept[k] && enclosure[k] > ENCLOSED_PX;
        if far && e <= open_above {
            assert!((g - 1.5 / (-e).sin()).abs() < 1e-3, "pixel {k}: {g}");
        } else {
            assert!(g.is_nan(), "pixel {k}: {g}");
        }
    }
    assert!(ground.iter().any(|g| g.is_finite()));

    // Grazing drops that empty the ground from 8 m on leave its columns nothing
    // farther to see: what they lost is still the level ground.
    let near = far_ground_dropped(30, 8.0);
    let ground = open_ground_range(&near, &enclosures(&near).0, open_above, 1.5);
    let lost = (0..near.len()).filter(|&k| !near.kept[k] && near.elevation_rad[k] <= open_above);
    for k in lost {
        let e = near.elevation_rad[k];
        assert!(
            (ground[k] - 1.5 / (-e).sin()).abs() < 1e-3,
            "pixel {k}: {}",
            ground[k]
        );
    }

    // A wall 10 m away across the top rows of column 5 stands in front of the
    // far ground below it: that column keeps the fill's range.
    let mut walled = f.clone();
    for i in 0..3 {
        let k = i * walled.width + 5;
        walled.kept[k] = true;
        walled.range_m[k] = 10.0 / walled.elevation_rad[k].cos();
    }
    // A return 50 m away in column 7 shows the column saw past the lost
    // pixels' ground points: they are not open ground either.
    let k = 7;
    walled.kept[k] = true;
    walled.range_m[k] = 50.0 / walled.elevation_rad[k].cos();
    let open = vec![ENCLOSURE_CAP_PX; walled.len()];
    let ground = open_ground_range(&walled, &open, open_above, 1.5);
    for j in [5, 7] {
        assert!((0..walled.height).all(|i| ground[i * walled.width + j].is_nan()));
    }
    assert!((0..walled.height).any(|i| ground[i * walled.width + 6].is_finite()));

    // The open ground's pixels reach the range family's bins with their ground range.
    let px = Pixels::collect(std::slice::from_ref(&f), 60.0);
    assert!(px.level_plane.iter().any(|&o| o));
    for i in (0..px.len()).filter(|&i| px.level_plane[i]) {
        assert!(!px.kept[i] && px.range_m[i] > 20.0);
        assert!(
            (px.cos_incidence[i] - px.row_elevation_rad[px.row[i] as usize].abs().sin()).abs()
                < 1e-4
        );
    }
}

#[test]
fn a_kept_pixels_enclosure_is_read_from_its_neighbours() {
    // One row: returns in columns 0, 2 and 4, then open space.
    let mut f = level_rows(1, |_| (0.0, true, 10.0, 0.0));
    for j in 0..64 {
        f.kept[j] = j <= 4 && j % 2 == 0;
    }
    let e = enclosures(&f).0;
    assert_eq!(e[1], 1, "a hole between two returns");
    assert_eq!(e[2], 2, "a return between returns two pixels away");
    assert_eq!(e[4], ENCLOSURE_CAP_PX, "a return beside open space");
}

#[test]
fn a_gap_between_two_surfaces_is_not_a_hole_in_one() {
    // One row: a crown 10 m away (columns 0-9), open sky (10-11), another crown
    // 14 m away (12-20), a hole in it (21), the crown again (22-30).
    let mut f = level_rows(1, |_| (0.0, true, 10.0, 0.0));
    for j in 0..64 {
        f.kept[j] = j <= 30 && !matches!(j, 10 | 11 | 21);
        f.range_m[j] = if j < 12 { 10.0 } else { 14.0 };
    }
    let (any, surface) = enclosures(&f);
    assert_eq!((any[10], any[21]), (2, 1), "both enclosed by returns");
    assert_eq!(surface[10], ENCLOSURE_CAP_PX, "the sky between the crowns");
    assert_eq!(surface[21], 1, "the hole in the far crown");
}

#[test]
fn a_dead_laser_over_the_ground_of_a_sparse_sensor_is_a_hole_in_it() {
    // Three rows 2 deg apart looking down at the ground 2 m below: their ground
    // points lie 9.6, 11.4 and 14.2 m away (inverse ranges 30 % apart), one height.
    // The middle laser is dead all round.
    let elevation = |i: usize| -(12.0f32 - 2.0 * i as f32).to_radians();
    let mut f = level_rows(3, |i| {
        let e = elevation(2 - i);
        (e, i != 1, 2.0 / -e.sin(), 0.0)
    });
    let (any, surface) = enclosures(&f);
    assert_eq!(
        (any[64 + 5], surface[64 + 5]),
        (1, 1),
        "the ground above and below"
    );
    // A wall 20 m away above the dead row and the ground below it: two surfaces.
    for j in 0..64 {
        f.range_m[j] = 20.0 / elevation(2).cos();
    }
    assert_eq!(
        enclosures(&f).1[64 + 5],
        ENCLOSURE_CAP_PX,
        "a wall above, the ground below"
    );
}

#[test]
fn a_dead_bottom_laser_under_the_ground_is_a_hole_in_it() {
    // Three rows 2 deg apart looking down at the ground 2 m below; the bottom laser
    // is dead all round. Nothing lies below it, but the ground above runs on under it.
    let elevation = |i: usize| -(8.0f32 + 2.0 * i as f32).to_radians();
    let mut f = level_rows(3, |i| {
        let e = elevation(i);
        (e, i != 2, 2.0 / -e.sin(), 0.0)
    });
    let bottom = 2 * 64 + 5;
    let laser = |f: &ScanFeatures| laser_enclosures(f, &enclosures(f).1)[bottom];
    assert_eq!(enclosures(&f).1[bottom], ENCLOSURE_CAP_PX, "nothing below");
    assert_eq!(laser(&f), 1, "the ground above");
    f.kept[bottom] = true;
    assert_eq!(
        laser(&f),
        1,
        "a kept pixel there too: read from the returns above only"
    );
    // A wall 20 m away over the bottom row: not the ground.
    for k in 0..2 * 64 {
        f.range_m[k] = 20.0 / f.elevation_rad[k].cos();
    }
    assert_eq!(laser(&f), ENCLOSURE_CAP_PX, "a wall above");
}

#[test]
fn the_horizon_between_a_ceiling_and_a_floor_is_not_enclosed() {
    // A garage's corridor: the top row meets the ceiling 1.2 m above, the bottom
    // row the floor 1.6 m below, and the row between them, just above the horizon,
    // reaches neither within range: open space, whatever lies above and below.
    let rows = [(1.4f32, 1.2f32), (0.4, f32::NAN), (-1.3, -1.6)];
    let f = level_rows(3, |i| {
        let (e_deg, z) = rows[i];
        let e = e_deg.to_radians();
        (
            e,
            !z.is_nan(),
            if z.is_nan() { 200.0 } else { z / e.sin() },
            0.0,
        )
    });
    let (any, surface) = enclosures(&f);
    assert_eq!(
        (any[64 + 5], surface[64 + 5]),
        (ENCLOSURE_CAP_PX, ENCLOSURE_CAP_PX)
    );
    // A wall 20 m away across the same rows encloses it: a hole in one surface.
    let f = level_rows(3, |i| {
        let e = rows[i].0.to_radians();
        (e, i != 1, 20.0 / e.cos(), 0.0)
    });
    let (any, surface) = enclosures(&f);
    assert_eq!((any[64 + 5], surface[64 + 5]), (1, 1));
}

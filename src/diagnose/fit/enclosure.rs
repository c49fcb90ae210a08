//! How returns enclose a pixel: the distance to its nearest returns on both sides
//! along its row or its column, as any returns, as one surface, and as what a laser
//! can hit.

#[cfg(doc)]
use super::Pixels;
use crate::diagnose::features::ScanFeatures;

/// Largest enclosure distance [`Pixels::enclosure_px`] tells apart.
pub const ENCLOSURE_CAP_PX: u8 = 16;

/// Two returns enclose a pixel as one surface ([`Pixels::surface_px`]) when their
/// inverse ranges differ by at most this share of the larger one, or, above and below
/// it, their heights do (one level plane: the ground, a ceiling).
pub(super) const SURFACE_TOLERANCE: f32 = 0.15;
/// Heights nearer the sensor's than this (m) do not tell a level plane: at the horizon
/// every surface has them.
const LEVEL_MIN_HEIGHT_M: f32 = 0.5;

/// A dropped pixel is enclosed when returns lie on both sides of it within this many
/// pixels along its row or its column ([`Pixels::enclosure_px`]).
pub const ENCLOSED_PX: u8 = 8;

/// [`Pixels::enclosure_px`] and [`Pixels::surface_px`] of every pixel of one scan, from
/// one search for each pixel's nearest returns.
pub(super) fn enclosures(f: &ScanFeatures) -> (Vec<u8>, Vec<u8>) {
    let (h, w) = (f.height, f.width.max(1));
    let cap = usize::from(ENCLOSURE_CAP_PX);
    // Distance to the nearest return from `k` in steps of `step`, at most `limit` steps.
    let reach = |k: usize, step: isize, limit: usize| -> usize {
        (1..=cap.min(limit))
            .find(|&d| f.kept[(k as isize + step * d as isize) as usize])
            .unwrap_or(cap)
    };
    // The farther of the nearest returns on both sides, `step` apart, within `before`
    // and `after` steps: as any returns, and as one surface (their inverse ranges
    // within `SURFACE_TOLERANCE` of each other).
    let side = |k: usize, step: isize, before: usize, after: usize| -> (usize, usize) {
        let a = reach(k, -step, before);
        let b = reach(k, step, after);
        if a >= cap || b >= cap {
            return (cap, cap);
        }
        let (ka, kb) = (
            (k as isize - step * a as isize) as usize,
            (k as isize + step * b as isize) as usize,
        );
        let (ua, ub) = (1.0 / f.range_m[ka], 1.0 / f.range_m[kb]);
        let near = |x: f32, y: f32| (x - y).abs() <= SURFACE_TOLERANCE * x.abs().max(y.abs());
        // Along a column, the heights of the two returns, where both lie at least
        // `LEVEL_MIN_HEIGHT_M` above or below the sensor (nearer, at the horizon,
        // every surface has such heights).
        let heights = (step != 1)
            .then(|| {
                let height = |k: usize| f.range_m[k] * f.elevation_rad[k].sin();
                (height(ka), height(kb))
            })
            .filter(|(za, zb)| za.abs().min(zb.abs()) >= LEVEL_MIN_HEIGHT_M);
        let mut level = false;
        if let Some((za, zb)) = heights {
            // A return above the sensor and one below it (a ceiling and the floor of a
            // corridor, a crown and the road) leave the horizon between them open: the
            // rays there may pass both.
            if za * zb < 0.0 {
                return (cap, cap);
            }
            // Rows of a sparse sensor meet the ground at ranges far apart, at one height.
            level = near(za, zb);
        }
        let one_surface = near(ua, ub) || level;
        (a.max(b), if one_surface { a.max(b) } else { cap })
    };
    (0..f.len())
        .map(|k| {
            let (i, j) = (k / w, k % w);
            let row = side(k, 1, j, w - 1 - j);
            let column = side(k, w as isize, i, h - 1 - i);
            (row.0.min(column.0) as u8, row.1.min(column.1) as u8)
        })
        .unzip()
}

/// [`Pixels::laser_px`] of every pixel of one scan: `surface` ([`enclosures`]), and the
/// bottom row under level ground. The bottom row has nothing below it; where the two
/// nearest returns above a pixel there lie on one level plane below the sensor, the
/// ground runs on towards the car under it: the pixel sees that ground or lost its ray
/// (a dead bottom laser). Kept and dropped pixels alike, from the returns above only.
pub(super) fn laser_enclosures(f: &ScanFeatures, surface: &[u8]) -> Vec<u8> {
    let (h, w) = (f.height, f.width.max(1));
    let cap = usize::from(ENCLOSURE_CAP_PX);
    let mut out = surface.to_vec();
    if h < 3 {
        return out;
    }
    // The nearest return above `k` (its index and distance in rows), within the cap.
    let above = |k: usize| -> Option<(usize, usize)> {
        (1..=cap.min(k / w))
            .find(|&d| f.kept[k - d * w])
            .map(|d| (k - d * w, d))
    };
    let height = |k: usize| f.range_m[k] * f.elevation_rad[k].sin();
    let bottom = (h - 1) * w;
    for (k, slot) in out.iter_mut().enumerate().skip(bottom) {
        let Some((ka, a)) = above(k) else { continue };
        let Some((kb, _)) = above(ka) else { continue };
        let (za, zb) = (height(ka), height(kb));
        let level = za <= -LEVEL_MIN_HEIGHT_M
            && zb <= -LEVEL_MIN_HEIGHT_M
            && (za - zb).abs() <= SURFACE_TOLERANCE * za.abs().max(zb.abs());
        if level {
            *slot = (*slot).min(a as u8);
        }
    }
    out
}

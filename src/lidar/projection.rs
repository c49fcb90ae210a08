//! Projection of a [`Scan`] onto a [`SensorProfile`]'s grid: one routine whose only
//! variable part is how a point's row (beam) is found ([`Strategy`]). The column
//! always comes from the point's azimuth, and the nearest return wins a pixel.

use super::range_image::azimuth_column;
use super::{RangeImage, Scan, SensorProfile};

/// How a point's row (beam) is found (also `convert --projection`).
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    Hash,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum Strategy {
    /// Pick one of the others from the data (`choose_strategy`).
    #[default]
    Auto,
    /// A `ring` / `channel` / `laser_id` field; rings ordered by their median elevation.
    RingField,
    /// Points in raw ring order, each ring a sweep starting straight ahead (KITTI
    /// `.bin`): a new ring starts where the azimuth crosses from below 0 to >= 0
    /// with x > 0. (Splitting at "azimuth jump > pi" is wrong on real KITTI.)
    RingOrder,
    /// Column-major firing order: the beam index cycles fastest (Ouster, nuScenes),
    /// so point `i` is on beam `i % beams`. Needs every cell kept (organized data).
    ColumnMajor,
    /// Row-major organized cloud: point `i` is on row `i / width`.
    RowMajor,
    /// Nearest beam elevation of the profile.
    Spherical,
}

impl Strategy {
    pub fn name(self) -> &'static str {
        match self {
            Strategy::Auto => "auto",
            Strategy::RingField => "ring-field",
            Strategy::RingOrder => "ring-order",
            Strategy::ColumnMajor => "column-major",
            Strategy::RowMajor => "row-major",
            Strategy::Spherical => "spherical",
        }
    }
}

/// Why a scan could not be projected with the chosen strategy.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProjectionError {
    #[error("strategy {strategy} needs a ring field, and the cloud has none")]
    NoRingField { strategy: &'static str },
    #[error(
        "found {found} rings, but the sensor profile '{profile}' has {beams} beams; try --sensor auto or --projection spherical"
    )]
    RingCount {
        found: usize,
        beams: usize,
        profile: String,
    },
    #[error(
        "{points} points are not a whole number of {beams}-beam columns; column-major order needs an organized cloud"
    )]
    ColumnMajorLength { points: usize, beams: usize },
    #[error("invalid sensor profile: {0}")]
    Profile(String),
    #[error("the {field} field has {len} values for {points} points")]
    FieldLength {
        field: &'static str,
        len: usize,
        points: usize,
    },
}

/// Checks that every optional per-point field has one value per point, so the
/// projection can index them by point.
fn check_fields(scan: &Scan) -> Result<(), ProjectionError> {
    let points = scan.len();
    let lens = [
        ("intensity", scan.intensity.as_ref().map(Vec::len)),
        ("ring", scan.ring.as_ref().map(Vec::len)),
        ("time", scan.time_s.as_ref().map(Vec::len)),
        ("label", scan.label.as_ref().map(Vec::len)),
    ];
    for (field, len) in lens {
        if let Some(len) = len.filter(|&l| l != points) {
            return Err(ProjectionError::FieldLength { field, len, points });
        }
    }
    Ok(())
}

pub(crate) fn elevation(p: [f32; 3]) -> f32 {
    p[2].atan2(p[0].hypot(p[1]))
}

pub(crate) fn azimuth(p: [f32; 3]) -> f32 {
    p[1].atan2(p[0])
}

/// Fewest returns a KITTI ring-order ring may have: a lone point whose azimuth reads
/// exactly 0 (real KITTI drive_a at 4.2 s ends with one) is no new ring.
const MIN_RING_RETURNS: usize = 8;

/// Ring id of every point in KITTI raw ring order (see [`Strategy::RingOrder`]).
/// Points without a return keep the current ring; a "ring" of fewer than
/// [`MIN_RING_RETURNS`] returns belongs to the ring before it.
pub fn ring_order_ids(scan: &Scan) -> Vec<u32> {
    let mut ring = 0u32;
    let mut prev_az: Option<f32> = None;
    let mut ids = Vec::with_capacity(scan.len());
    let mut returns = vec![0usize];
    for i in 0..scan.len() {
        if scan.is_return(i) {
            let p = scan.xyz[i];
            let az = azimuth(p);
            if prev_az.is_some_and(|prev| prev < 0.0 && az >= 0.0 && p[0] > 0.0) {
                ring += 1;
                returns.push(0);
            }
            prev_az = Some(az);
            returns[ring as usize] += 1;
        }
        ids.push(ring);
    }
    // Renumber with short rings folded into their predecessor (the first into the next).
    let mut new_id = Vec::with_capacity(returns.len());
    let mut next = 0u32;
    for (r, &n) in returns.iter().enumerate() {
        if r > 0 && n < MIN_RING_RETURNS {
            new_id.push(next - 1);
        } else {
            new_id.push(next);
            next += 1;
        }
    }
    if returns.len() > 1 && returns[0] < MIN_RING_RETURNS {
        new_id
            .iter_mut()
            .skip(1)
            .for_each(|r| *r = r.saturating_sub(1));
    }
    ids.iter().map(|&r| new_id[r as usize]).collect()
}

/// Maps arbitrary group ids (rings, laser ids) to rows of `profile`, ordered by
/// each group's median elevation, top first. With as many groups as beams, the
/// k-th highest group is row k; with fewer (beams without a single return), each
/// group goes to the row whose elevation fits best, keeping the order (see
/// [`match_rows`]), so one missing beam does not shift every row below it.
/// Returns the row per point (`u32::MAX` for no row) and the number of groups.
fn rows_by_median_elevation(
    scan: &Scan,
    group: &[u32],
    profile: &SensorProfile,
) -> (Vec<u32>, usize) {
    let mut elevations: std::collections::BTreeMap<u32, Vec<f32>> = Default::default();
    for (i, &g) in group.iter().enumerate().take(scan.len()) {
        if scan.is_return(i) {
            elevations
                .entry(g)
                .or_default()
                .push(elevation(scan.xyz[i]));
        }
    }
    let mut medians: Vec<(u32, f32)> = elevations
        .into_iter()
        .map(|(g, mut e)| {
            e.sort_by(f32::total_cmp);
            (g, e[e.len() / 2])
        })
        .collect();
    if let Some(row_of) = rows_by_id(&medians, profile.beams()) {
        let rows = group.iter().map(|g| row_of(*g)).collect();
        return (rows, medians.len());
    }
    medians.sort_by(|a, b| b.1.total_cmp(&a.1));
    let table: Vec<f32> = profile
        .elevation_deg
        .iter()
        .map(|e| e.to_radians())
        .collect();
    let sorted: Vec<f32> = medians.iter().map(|m| m.1).collect();
    let assigned = match_rows(&sorted, &table);
    let row_of: std::collections::HashMap<u32, u32> = medians
        .iter()
        .zip(&assigned)
        .map(|((g, _), &row)| (*g, row as u32))
        .collect();
    let rows = group
        .iter()
        .map(|g| row_of.get(g).copied().unwrap_or(u32::MAX))
        .collect();
    (rows, medians.len())
}

/// Rows straight from the group ids, where the ids number the beams in elevation order
/// (either way: Ouster top-down, Velodyne drivers bottom-up) and span exactly `beams`
/// values: a beam without returns then leaves its own row empty, and two neighbouring
/// beams keep their rows where parallax (a laser's offset from the sensor's centre moves a
/// ring's median elevation by up to a beam spacing at a few metres) swaps their medians.
/// "In elevation order": at least [`ID_ORDER_AGREEMENT`] of the steps between consecutive
/// ids go the same way in median elevation (a firing-order numbering, like the VLP-16's
/// raw laser ids, alternates). `medians` are (id, median elevation), sorted by id. `None`
/// where the ids do not follow elevation or do not span the beams.
fn rows_by_id(medians: &[(u32, f32)], beams: usize) -> Option<impl Fn(u32) -> u32> {
    let (first, last) = (medians.first()?.0, medians.last()?.0);
    if medians.len() < 2 || (last - first) as usize + 1 != beams {
        return None;
    }
    let steps = (medians.len() - 1) as f64;
    let down = medians.windows(2).filter(|w| w[0].1 > w[1].1).count() as f64;
    let falling = down >= ID_ORDER_AGREEMENT * steps;
    if !falling && steps - down < ID_ORDER_AGREEMENT * steps {
        return None;
    }
    Some(move |g: u32| match g.checked_sub(first) {
        Some(k) if g <= last && falling => k,
        Some(_) if g <= last => last - g,
        _ => u32::MAX,
    })
}

/// Share of consecutive ring ids whose median elevations step the same way, for the ids to
/// be taken as the beams' order ([`rows_by_id`]).
const ID_ORDER_AGREEMENT: f64 = 0.9;

/// Order-preserving assignment of `medians` (decreasing) to rows of `table`
/// (decreasing) minimising the total elevation mismatch: identity when the counts
/// are equal, dynamic programming (O(n m)) when there are fewer medians than rows.
/// More medians than rows cannot be matched: the extra ones get `usize::MAX`.
pub(crate) fn match_rows(medians: &[f32], table: &[f32]) -> Vec<usize> {
    let (n, m) = (medians.len(), table.len());
    if n == 0 {
        return Vec::new(); // no group has a return
    }
    if n >= m {
        return (0..n).map(|k| if k < m { k } else { usize::MAX }).collect();
    }
    // cost[k][r]: best total for medians 0..=k with median k on row r.
    let mut cost = vec![vec![f32::INFINITY; m]; n];
    let mut from = vec![vec![0usize; m]; n];
    for r in 0..m {
        cost[0][r] = (medians[0] - table[r]).abs();
    }
    for k in 1..n {
        let (mut best, mut arg) = (f32::INFINITY, 0usize);
        for r in k..m {
            // Best predecessor on rows < r.
            if cost[k - 1][r - 1] < best {
                best = cost[k - 1][r - 1];
                arg = r - 1;
            }
            cost[k][r] = best + (medians[k] - table[r]).abs();
            from[k][r] = arg;
        }
    }
    let mut rows = vec![0usize; n];
    let mut r = (0..m)
        .min_by(|&a, &b| cost[n - 1][a].total_cmp(&cost[n - 1][b]))
        .unwrap_or(0);
    for k in (0..n).rev() {
        rows[k] = r;
        r = from[k][r];
    }
    rows
}

/// Median absolute deviation of elevation within rows: small when a row assignment
/// matches the sensor's beams.
pub(crate) fn row_spread(scan: &Scan, rows: impl Fn(usize) -> usize, nrows: usize) -> f32 {
    let mut per_row = vec![Vec::new(); nrows];
    for i in (0..scan.len()).filter(|&i| scan.is_return(i)) {
        per_row[rows(i) % nrows].push(elevation(scan.xyz[i]));
    }
    let mut devs = Vec::new();
    for mut e in per_row.into_iter().filter(|e| !e.is_empty()) {
        e.sort_by(f32::total_cmp);
        let m = e[e.len() / 2];
        devs.extend(e.iter().map(|x| (x - m).abs()));
    }
    if devs.is_empty() {
        return f32::INFINITY;
    }
    devs.sort_by(f32::total_cmp);
    devs[devs.len() / 2]
}

/// Picks the row strategy from the data: a ring field if present; for organized
/// clouds whichever of row-/column-major order gives tighter rings; KITTI ring
/// order when it yields the profile's number of rings; else nearest elevation.
pub fn choose_strategy(scan: &Scan, profile: &SensorProfile) -> Strategy {
    if scan.ring.is_some() {
        return Strategy::RingField;
    }
    let beams = profile.beams();
    if beams == 0 {
        return Strategy::Spherical;
    }
    if scan.is_organized() {
        let (h, w) = (scan.height, scan.width);
        let row_major = row_spread(scan, |i| i / w, h);
        let col_major = if scan.len().is_multiple_of(beams) {
            row_spread(scan, |i| i % beams, beams)
        } else {
            f32::INFINITY
        };
        return if col_major < row_major {
            Strategy::ColumnMajor
        } else {
            Strategy::RowMajor
        };
    }
    let ids = ring_order_ids(scan);
    let rings = ids.last().map_or(0, |r| *r as usize + 1);
    if rings == beams && segments_are_rings(scan, &ids, rings) {
        return Strategy::RingOrder;
    }
    Strategy::Spherical
}

/// Whether the segments that KITTI ring order cuts (`ids`, `rings` of them) are each one
/// beam. A sensor whose sweeps start elsewhere than straight ahead, written ring by ring,
/// also crosses straight ahead once per ring, so the cut yields as many segments, but each
/// holds the end of one beam and the start of the next: its two ends lie a beam apart in
/// elevation, where a ring's ends share one.
fn segments_are_rings(scan: &Scan, ids: &[u32], rings: usize) -> bool {
    let mut per_ring = vec![Vec::new(); rings];
    for i in (0..scan.len()).filter(|&i| scan.is_return(i)) {
        per_ring[ids[i] as usize].push(elevation(scan.xyz[i]));
    }
    let median = |v: &mut [f32]| {
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    // Each segment's median elevation, and the step between the medians of its first
    // and last fiftieth of returns: both look just beside straight ahead, so a beam's
    // own offsets from the sensor's centre (KITTI's) hardly part them.
    let mut levels = Vec::new();
    let mut end_steps = Vec::new();
    for e in per_ring
        .iter_mut()
        .filter(|e| e.len() >= 2 * MIN_RING_RETURNS)
    {
        let end = (e.len() / 50).max(MIN_RING_RETURNS);
        let head = median(&mut e[..end].to_vec());
        let n = e.len();
        let tail = median(&mut e[n - end..].to_vec());
        end_steps.push((head - tail).abs());
        levels.push(median(e));
    }
    if levels.len() < 2 {
        return true;
    }
    levels.sort_by(|a, b| b.total_cmp(a));
    let mut spacing: Vec<f32> = levels.windows(2).map(|w| w[0] - w[1]).collect();
    2.0 * median(&mut end_steps) < median(&mut spacing)
}

/// Row of the beam in `table` (radians) nearest to elevation `e`: a binary search
/// when the table is top-down as profiles are, a scan of every beam otherwise.
fn nearest_beam(table: &[f32], e: f32) -> u32 {
    if table.windows(2).all(|w| w[0] >= w[1]) {
        let k = table.partition_point(|&t| t > e);
        let below = table.get(k).map(|t| (t - e).abs());
        let above = k.checked_sub(1).map(|a| (table[a] - e).abs());
        return match (above, below) {
            (Some(a), Some(b)) if a <= b => k as u32 - 1,
            (Some(_), None) => k as u32 - 1,
            (_, Some(_)) => k as u32,
            (None, None) => u32::MAX,
        };
    }
    table
        .iter()
        .enumerate()
        .min_by(|a, b| (a.1 - e).abs().total_cmp(&(b.1 - e).abs()))
        .map_or(u32::MAX, |(row, _)| row as u32)
}

/// Row of every point under `strategy` (`u32::MAX` = no row).
fn rows(
    scan: &Scan,
    profile: &SensorProfile,
    strategy: Strategy,
) -> Result<Vec<u32>, ProjectionError> {
    let beams = profile.beams();
    let check = |found: usize| {
        if found > beams {
            Err(ProjectionError::RingCount {
                found,
                beams,
                profile: profile.name.clone(),
            })
        } else {
            Ok(())
        }
    };
    Ok(match strategy {
        Strategy::Auto => return rows(scan, profile, choose_strategy(scan, profile)),
        Strategy::RingField => {
            let ring = scan.ring.as_ref().ok_or(ProjectionError::NoRingField {
                strategy: strategy.name(),
            })?;
            let ids: Vec<u32> = ring.iter().map(|&r| r as u32).collect();
            let (rows, n) = rows_by_median_elevation(scan, &ids, profile);
            check(n)?;
            rows
        }
        Strategy::RingOrder => {
            let ids = ring_order_ids(scan);
            check(ids.last().map_or(0, |r| *r as usize + 1))?;
            ids
        }
        Strategy::ColumnMajor => {
            if !scan.len().is_multiple_of(beams) {
                return Err(ProjectionError::ColumnMajorLength {
                    points: scan.len(),
                    beams,
                });
            }
            let ids: Vec<u32> = (0..scan.len()).map(|i| (i % beams) as u32).collect();
            rows_by_median_elevation(scan, &ids, profile).0
        }
        Strategy::RowMajor => {
            let ids: Vec<u32> = (0..scan.len())
                .map(|i| (i / scan.width.max(1)) as u32)
                .collect();
            let (rows, n) = rows_by_median_elevation(scan, &ids, profile);
            check(n)?;
            rows
        }
        Strategy::Spherical => {
            let table: Vec<f32> = profile
                .elevation_deg
                .iter()
                .map(|e| e.to_radians())
                .collect();
            scan.xyz
                .iter()
                .map(|&p| nearest_beam(&table, elevation(p)))
                .collect()
        }
    })
}

/// Projects `scan` onto `profile`'s grid. Returns with a range in
/// `[min_range_m, max_range_m]` compete for their pixel; the nearest wins and keeps
/// its exact xyz, intensity and label.
pub fn project(
    scan: &Scan,
    profile: &SensorProfile,
    strategy: Strategy,
) -> Result<RangeImage, ProjectionError> {
    profile.validate().map_err(ProjectionError::Profile)?;
    check_fields(scan)?;
    let rows = rows(scan, profile, strategy)?;
    let (h, w) = (profile.beams(), profile.columns);
    let mut image = RangeImage::empty(profile.angle_grid());
    for (i, &row) in rows.iter().enumerate() {
        if row as usize >= h || !scan.is_return(i) {
            continue;
        }
        let p = scan.xyz[i];
        let range = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        if range < profile.min_range_m || range > profile.max_range_m {
            continue;
        }
        let col = (azimuth_column(azimuth(p), w).round() as usize) % w;
        let k = row as usize * w + col;
        if image.range_m[k] == 0.0 || range < image.range_m[k] {
            image.range_m[k] = range;
            image.xyz[k] = p;
            image.intensity[k] = scan
                .intensity
                .as_ref()
                .and_then(|v| v.get(i).copied())
                .unwrap_or(0.0);
            image.label[k] = scan
                .label
                .as_ref()
                .and_then(|v| v.get(i).copied())
                .unwrap_or(0);
            image.point_index[k] = i as u32;
        }
    }
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A synthetic 4-beam sensor: each ring a full sweep starting straight ahead,
    /// counter-clockwise, as KITTI stores it.
    fn ring_order_scan(beams: usize, per_ring: usize, range: f32) -> (Scan, SensorProfile) {
        sweep_from(0.01, beams, per_ring, range)
    }

    /// The same sensor with every ring's sweep starting at azimuth `start` (radians).
    fn sweep_from(start: f32, beams: usize, per_ring: usize, range: f32) -> (Scan, SensorProfile) {
        let elev = [2.0f32, 0.0, -2.0, -4.0];
        let mut xyz = Vec::new();
        for e in elev.iter().take(beams) {
            for k in 0..per_ring {
                // Start just left of ahead (azimuth >= 0, as real KITTI rings do) and
                // sweep counter-clockwise, ending just right of ahead.
                let az = start + k as f32 * 2.0 * std::f32::consts::PI / per_ring as f32;
                let (e, az) = (e.to_radians(), az);
                xyz.push([
                    range * e.cos() * az.cos(),
                    range * e.cos() * az.sin(),
                    range * e.sin(),
                ]);
            }
        }
        let profile = SensorProfile {
            name: "test4".into(),
            elevation_deg: elev[..beams].to_vec(),
            azimuth_offset_deg: None,
            columns: per_ring,
            min_range_m: 1.0,
            max_range_m: 100.0,
        };
        (Scan::from_xyz(xyz), profile)
    }

    /// A lone trailing point whose azimuth reads exactly 0 (as in real KITTI) does not
    /// open a ring of its own.
    #[test]
    fn a_lone_point_at_azimuth_zero_is_no_new_ring() {
        let (mut scan, _) = ring_order_scan(4, 64, 10.0);
        scan.xyz.push([13.0, -0.0, -6.0]);
        scan.width = scan.xyz.len();
        let ids = ring_order_ids(&scan);
        assert_eq!(ids.iter().max(), Some(&3), "4 rings, not 5");
        assert_eq!(ids.last(), Some(&3));
    }

    /// Rings written one by one from a sweep start behind (an Ouster's, say): cutting them
    /// straight ahead gives as many segments as beams, each half one beam and half the
    /// next, so the rows come from elevation instead.
    #[test]
    fn rings_that_start_behind_are_not_cut_straight_ahead() {
        let (mut scan, profile) = sweep_from(3.3, 4, 64, 10.0);
        // The top beam sees nothing until it passes straight ahead (open sky behind).
        scan.xyz.drain(..30);
        scan.width = scan.xyz.len();
        let ids = ring_order_ids(&scan);
        assert_eq!(
            ids.last().map(|r| r + 1),
            Some(4),
            "the cut finds as many segments"
        );
        assert_eq!(choose_strategy(&scan, &profile), Strategy::Spherical);
        let img = project(&scan, &profile, Strategy::Auto).unwrap();
        assert_eq!(img.valid_count(), scan.len());
        for (row, e) in profile.elevation_deg.iter().enumerate() {
            for k in (row * 64..(row + 1) * 64).filter(|&k| img.range_m[k] > 0.0) {
                assert!((img.xyz[k][2] / img.range_m[k] - e.to_radians().sin()).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn ring_order_projection_keeps_every_point_and_round_trips() {
        let (scan, profile) = ring_order_scan(4, 64, 10.0);
        assert_eq!(choose_strategy(&scan, &profile), Strategy::RingOrder);
        let img = project(&scan, &profile, Strategy::Auto).unwrap();
        assert_eq!(img.valid_count(), scan.len());
        let mut back = img.to_points();
        let mut orig = scan.xyz.clone();
        let key = |p: &[f32; 3]| (p[0].to_bits(), p[1].to_bits(), p[2].to_bits());
        back.sort_by_key(key);
        orig.sort_by_key(key);
        assert_eq!(back, orig);
        // Row 3 holds the -4 deg ring.
        let k = 3 * 64 + 10;
        assert!((img.xyz[k][2] / img.range_m[k] - (-4f32).to_radians().sin()).abs() < 1e-4);
    }

    #[test]
    fn nearest_return_wins_and_range_limits_apply() {
        let profile = SensorProfile {
            columns: 8,
            ..SensorProfile::builtin("vlp16").unwrap()
        };
        let scan = Scan::from_xyz(vec![
            [10.0, 0.0, 0.0],
            [5.0, 0.0, 0.0],
            [0.1, 0.0, 0.0],
            [500.0, 0.0, 0.0],
        ]);
        let img = project(&scan, &profile, Strategy::Spherical).unwrap();
        assert_eq!(img.valid_count(), 1);
        let k = img
            .point_index
            .iter()
            .position(|&p| p != super::super::range_image::NO_POINT)
            .unwrap();
        assert_eq!(img.range_m[k], 5.0);
        assert_eq!(img.point_index[k], 1);
    }

    #[test]
    fn column_major_organized_clouds_are_detected() {
        // Organized header 4 x 64 but the beam index cycles fastest, as Ouster writes it.
        let (rm, profile) = ring_order_scan(4, 64, 10.0);
        let mut xyz = Vec::new();
        for col in 0..64 {
            for beam in 0..4 {
                xyz.push(rm.xyz[beam * 64 + col]);
            }
        }
        let scan = Scan {
            xyz,
            height: 4,
            width: 64,
            ..Default::default()
        };
        assert_eq!(choose_strategy(&scan, &profile), Strategy::ColumnMajor);
        let img = project(&scan, &profile, Strategy::Auto).unwrap();
        assert_eq!(img.valid_count(), 256);
        // Read as row-major, the same data smears beams across rows.
        let rows_wrong = project(&scan, &profile, Strategy::RowMajor).unwrap();
        assert!(rows_wrong.valid_count() < 256);
    }

    #[test]
    fn ring_field_rows_follow_elevation_not_id() {
        let (mut scan, profile) = ring_order_scan(4, 16, 10.0);
        // Velodyne numbers rings bottom-up: ring 0 is the lowest beam.
        scan.ring = Some((0..scan.len()).map(|i| 3 - (i / 16) as u16).collect());
        let img = project(&scan, &profile, Strategy::Auto).unwrap();
        assert_eq!(img.valid_count(), 64);
        assert!(img.xyz[0][2] > 0.0, "row 0 must be the top beam");
        let too_many = SensorProfile {
            elevation_deg: vec![1.0, 0.0],
            ..profile
        };
        assert!(matches!(
            project(&scan, &too_many, Strategy::RingField),
            Err(ProjectionError::RingCount { found: 4, .. })
        ));
    }

    #[test]
    fn a_beam_without_returns_does_not_shift_the_rows_below() {
        // Column-major 4-beam data with beam 1 (0 deg) entirely dropped.
        let (rm, profile) = ring_order_scan(4, 32, 10.0);
        let mut xyz = Vec::new();
        for col in 0..32 {
            for beam in 0..4 {
                xyz.push(if beam == 1 {
                    [0.0; 3]
                } else {
                    rm.xyz[beam * 32 + col]
                });
            }
        }
        let scan = Scan {
            xyz,
            height: 4,
            width: 32,
            ..Default::default()
        };
        let img = project(&scan, &profile, Strategy::ColumnMajor).unwrap();
        assert_eq!(img.valid_count(), 96);
        for (row, expect_deg) in [
            (0usize, Some(2.0f32)),
            (1, None),
            (2, Some(-2.0)),
            (3, Some(-4.0)),
        ] {
            let k = row * 32 + 5;
            match expect_deg {
                Some(e) => assert!(
                    (img.xyz[k][2] / img.range_m[k] - e.to_radians().sin()).abs() < 1e-4,
                    "row {row}"
                ),
                None => assert!(!img.is_valid(k), "row {row} must stay empty"),
            }
        }
        assert_eq!(
            match_rows(&[0.3, 0.1, -0.3], &[0.3, 0.2, 0.1, 0.0, -0.3]),
            vec![0, 2, 4]
        );
        assert_eq!(match_rows(&[0.3, 0.1], &[0.3, 0.1]), vec![0, 1]);
        assert!(
            match_rows(&[], &[0.3, 0.1]).is_empty(),
            "no returns, no rows"
        );
    }

    #[test]
    fn fields_of_the_wrong_length_are_an_error_not_a_panic() {
        let (mut scan, profile) = ring_order_scan(4, 16, 10.0);
        scan.ring = Some(vec![0; scan.len() + 3]);
        let err = project(&scan, &profile, Strategy::Auto).unwrap_err();
        assert_eq!(
            err,
            ProjectionError::FieldLength {
                field: "ring",
                len: 67,
                points: 64
            }
        );
        scan.ring = None;
        scan.intensity = Some(vec![1.0; 2]);
        assert!(
            err_text(project(&scan, &profile, Strategy::RingOrder))
                .contains("intensity field has 2 values for 64 points")
        );
    }

    fn err_text(r: Result<RangeImage, ProjectionError>) -> String {
        r.err().map(|e| e.to_string()).unwrap_or_default()
    }

    #[test]
    fn nearest_beam_search_agrees_with_a_full_scan() {
        let table: Vec<f32> = SensorProfile::builtin("vlp32c")
            .unwrap()
            .elevation_deg
            .iter()
            .map(|e| e.to_radians())
            .collect();
        let mut reversed = table.clone();
        reversed.reverse();
        for k in 0..=400 {
            let e = (-30.0 + 0.15 * k as f32).to_radians();
            let full = table
                .iter()
                .enumerate()
                .min_by(|a, b| (a.1 - e).abs().total_cmp(&(b.1 - e).abs()))
                .unwrap()
                .0;
            assert_eq!(
                nearest_beam(&table, e),
                full as u32,
                "elevation {} deg",
                e.to_degrees()
            );
            assert_eq!(nearest_beam(&reversed, e), (table.len() - 1 - full) as u32);
        }
        assert_eq!(nearest_beam(&[], 0.1), u32::MAX);
    }
}

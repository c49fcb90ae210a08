//! Sensor estimation for `--sensor auto`: a [`SensorProfile`] (beam elevation
//! table, columns, range limits) measured from one or a few scans, with a report of
//! how it was found ([`SensorEstimate`]) that `info` can print.
//!
//! Beams come from, in order of preference: a ring field (median elevation per
//! ring), the layout of an organized cloud (row- or column-major, whichever gives
//! tighter beams), KITTI raw ring order, or, for unorganized clouds with no ring
//! information, 1-D clustering of point elevations. Columns come from the median
//! azimuth step between neighbouring returns of one beam.

use std::collections::BTreeMap;
use std::f32::consts::TAU;
use std::fmt;

use super::profile::{MAX_BEAMS, MAX_COLUMNS};
use super::projection::{azimuth, elevation, ring_order_ids, row_spread};
use super::{Scan, SensorProfile};

/// How the beams were found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EstimateMethod {
    /// One beam per value of the `ring` / `channel` / `laser_id` field.
    RingField,
    /// Organized cloud, one beam per row.
    RowMajor,
    /// Organized cloud whose beam index cycles fastest (Ouster, nuScenes).
    ColumnMajor,
    /// KITTI raw ring order: a new ring where the azimuth crosses 0 ahead.
    RingOrder,
    /// Peaks of the distribution of point elevations.
    ElevationClusters,
}

impl EstimateMethod {
    pub fn name(self) -> &'static str {
        match self {
            EstimateMethod::RingField => "ring field",
            EstimateMethod::RowMajor => "organized, row-major",
            EstimateMethod::ColumnMajor => "organized, column-major",
            EstimateMethod::RingOrder => "KITTI ring order",
            EstimateMethod::ElevationClusters => "elevation clustering",
        }
    }
}

/// One estimated beam.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BeamStats {
    /// Median elevation of the beam's returns.
    pub elevation_deg: f32,
    /// Median absolute deviation of the returns' elevations from that median: the
    /// scatter real sensors show because the lasers are not at the origin.
    pub spread_deg: f32,
    /// Returns attributed to the beam, over all scans.
    pub points: usize,
}

/// What `--sensor auto` found, and the profile built from it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SensorEstimate {
    pub method: EstimateMethod,
    pub scans: usize,
    /// Returns used (finite, non-zero points).
    pub returns: usize,
    /// Beams, top first.
    pub beams: Vec<BeamStats>,
    /// Median azimuth step between neighbouring returns of one beam, when measurable.
    pub azimuth_step_deg: Option<f32>,
    /// Columns per revolution: `360 / azimuth_step_deg` rounded, or the organized
    /// width when no step could be measured.
    pub columns: usize,
    /// Smallest and largest return range seen.
    pub min_range_m: f32,
    pub max_range_m: f32,
    /// The profile built from all of the above (name `auto`).
    pub profile: SensorProfile,
}

/// Why no profile could be estimated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EstimateError {
    #[error("no scans to estimate a sensor profile from")]
    NoScans,
    #[error("the scans hold no returns (every point is NaN or zero); pick a profile with --sensor")]
    NoReturns,
    #[error("found {found} beam(s), too few for a range image; pick a profile with --sensor")]
    TooFewBeams { found: usize },
    #[error(
        "found {found} distinct ring values, more than the {max} beams a sensor profile may have; pick a profile with --sensor and --projection spherical"
    )]
    TooManyBeams { found: usize, max: usize },
    #[error("the {field} field has {len} values for {points} points")]
    FieldLength {
        field: &'static str,
        len: usize,
        points: usize,
    },
}

/// Column counts of common LiDAR modes (Ouster 512-4096, Velodyne at 5/10/20 Hz)
/// and of the reference implementation's grids.
const STANDARD_COLUMNS: [usize; 8] = [256, 512, 900, 1024, 1800, 2048, 3600, 4096];

/// A measured column count moved to a standard one within 2 %: the median azimuth
/// step of real and subsampled scans is a little off the sensor's mode (KITTI's
/// ~2010 points per ring are imaged at 2048 columns, as in the reference).
fn snap_columns(measured: usize) -> usize {
    STANDARD_COLUMNS
        .into_iter()
        .find(|&c| (c as f32 - measured as f32).abs() <= 0.02 * c as f32)
        .unwrap_or(measured)
}

/// Valid range of an estimated profile: beyond any automotive LiDAR.
const AUTO_MAX_RANGE_M: f32 = 1000.0;

/// Fewest beams accepted as a sensor.
const MIN_BEAMS: usize = 2;

/// Estimates a sensor profile from `scans` (all from one sensor). See the module
/// doc for the methods; the report says which one was used.
pub fn estimate_profile(scans: &[Scan]) -> Result<SensorEstimate, EstimateError> {
    if scans.is_empty() {
        return Err(EstimateError::NoScans);
    }
    for scan in scans {
        if let Some(ring) = &scan.ring
            && ring.len() != scan.len()
        {
            return Err(EstimateError::FieldLength {
                field: "ring",
                len: ring.len(),
                points: scan.len(),
            });
        }
    }
    let returns: usize = scans.iter().map(Scan::returns).sum();
    if returns == 0 {
        return Err(EstimateError::NoReturns);
    }

    let (method, groups) = if scans.iter().all(|s| s.ring.is_some()) {
        let ids = scans
            .iter()
            .map(|s| s.ring.iter().flatten().map(|&r| u32::from(r)).collect())
            .collect();
        (EstimateMethod::RingField, ids)
    } else if let Some(found) = organized_groups(scans) {
        found
    } else if let Some(ids) = ring_order_groups(scans) {
        (EstimateMethod::RingOrder, ids)
    } else {
        (EstimateMethod::ElevationClusters, cluster_groups(scans))
    };

    // Pool each group's elevations and azimuth steps over all scans.
    let mut elevations: BTreeMap<u32, Vec<f32>> = BTreeMap::new();
    let mut steps: Vec<f32> = Vec::new();
    for (scan, ids) in scans.iter().zip(&groups) {
        let mut azimuths: BTreeMap<u32, Vec<f32>> = BTreeMap::new();
        for (i, &g) in ids.iter().enumerate().take(scan.len()) {
            if g != u32::MAX && scan.is_return(i) {
                elevations
                    .entry(g)
                    .or_default()
                    .push(elevation(scan.xyz[i]));
                azimuths.entry(g).or_default().push(azimuth(scan.xyz[i]));
            }
        }
        for az in azimuths.values_mut() {
            if let Some(step) = median_azimuth_step(az) {
                steps.push(step);
            }
        }
    }
    let mut beams: Vec<BeamStats> = elevations
        .into_values()
        .map(|mut e| {
            let median = median_in_place(&mut e);
            let mut dev: Vec<f32> = e.iter().map(|x| (x - median).abs()).collect();
            BeamStats {
                elevation_deg: median.to_degrees(),
                spread_deg: median_in_place(&mut dev).to_degrees(),
                points: e.len(),
            }
        })
        .collect();
    beams.sort_by(|a, b| b.elevation_deg.total_cmp(&a.elevation_deg));
    if beams.len() < MIN_BEAMS {
        return Err(EstimateError::TooFewBeams { found: beams.len() });
    }
    if beams.len() > MAX_BEAMS {
        return Err(EstimateError::TooManyBeams {
            found: beams.len(),
            max: MAX_BEAMS,
        });
    }

    let azimuth_step = (!steps.is_empty()).then(|| median_in_place(&mut steps));
    let columns = match azimuth_step {
        Some(step) if step > 0.0 => snap_columns((TAU / step).round() as usize),
        _ => scans[0].width.max(1),
    }
    .min(MAX_COLUMNS);
    let (mut min_range_m, mut max_range_m) = (f32::INFINITY, 0.0f32);
    for scan in scans {
        for (i, p) in scan.xyz.iter().enumerate() {
            if scan.is_return(i) {
                let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                min_range_m = min_range_m.min(r);
                max_range_m = max_range_m.max(r);
            }
        }
    }
    // Round outwards to centimetres so every seen return stays inside the profile.
    let (min_range_m, max_range_m) = (
        (min_range_m * 100.0).floor() / 100.0,
        (max_range_m * 100.0).ceil() / 100.0,
    );
    // The ranges seen in a few scans are not the sensor's limits: later scans
    // reach nearer and farther, so the profile keeps every return the sensor gave.
    let profile = SensorProfile {
        name: "auto".into(),
        elevation_deg: beams.iter().map(|b| b.elevation_deg).collect(),
        azimuth_offset_deg: None,
        columns,
        min_range_m: 0.0,
        max_range_m: AUTO_MAX_RANGE_M.max(max_range_m),
    };
    Ok(SensorEstimate {
        method,
        scans: scans.len(),
        returns,
        beams,
        azimuth_step_deg: azimuth_step.map(f32::to_degrees),
        columns,
        min_range_m,
        max_range_m,
        profile,
    })
}

/// Sorts `v` and returns its median (upper median for even lengths); 0 when empty.
fn median_in_place(v: &mut [f32]) -> f32 {
    v.sort_by(f32::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Median gap between neighbouring azimuths of one beam (radians). Gaps of
/// (nearly) zero are dual returns of one firing and are skipped; a beam needs a
/// few dozen returns for a meaningful step.
fn median_azimuth_step(azimuths: &mut [f32]) -> Option<f32> {
    if azimuths.len() < 32 {
        return None;
    }
    azimuths.sort_by(f32::total_cmp);
    let mut gaps: Vec<f32> = azimuths
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&g| g > 1e-5)
        .collect();
    if gaps.len() < 16 {
        return None;
    }
    Some(median_in_place(&mut gaps))
}

/// Organized clouds with one shared height: one group per row, or per index
/// modulo the height when the beam cycles fastest, whichever gives tighter beams.
fn organized_groups(scans: &[Scan]) -> Option<(EstimateMethod, Vec<Vec<u32>>)> {
    let first = scans.first()?;
    let (h, w) = (first.height, first.width);
    if h < MIN_BEAMS
        || scans
            .iter()
            .any(|s| s.height != h || s.width != w || s.len() != h * w)
    {
        return None;
    }
    let row_major = row_spread(first, |i| i / w, h);
    let col_major = row_spread(first, |i| i % h, h);
    let (method, group): (EstimateMethod, fn(usize, usize, usize) -> u32) = if col_major < row_major
    {
        (EstimateMethod::ColumnMajor, |i, h, _| (i % h) as u32)
    } else {
        (EstimateMethod::RowMajor, |i, _, w| (i / w) as u32)
    };
    Some((
        method,
        scans
            .iter()
            .map(|s| (0..s.len()).map(|i| group(i, h, w)).collect())
            .collect(),
    ))
}

/// KITTI ring order, accepted only when it looks like a sensor: every scan splits
/// into the same number of rings (2..=256), each with a few dozen returns, whose
/// median elevations fall strictly from the first ring to the last.
fn ring_order_groups(scans: &[Scan]) -> Option<Vec<Vec<u32>>> {
    let mut count = None;
    let mut all = Vec::with_capacity(scans.len());
    for scan in scans {
        let ids = ring_order_ids(scan);
        let rings = ids.last().map_or(0, |&r| r as usize + 1);
        if !(MIN_BEAMS..=256).contains(&rings) || count.is_some_and(|c| c != rings) {
            return None;
        }
        count = Some(rings);
        let mut per_ring = vec![Vec::new(); rings];
        for (i, &r) in ids.iter().enumerate() {
            if scan.is_return(i) {
                per_ring.get_mut(r as usize)?.push(elevation(scan.xyz[i]));
            }
        }
        let mut medians = Vec::with_capacity(rings);
        for mut e in per_ring {
            if e.len() < 32 {
                return None;
            }
            let median = median_in_place(&mut e);
            // A ring is one beam: its elevations lie close together. A cloud in firing
            // order (every beam in each "ring" between two azimuth wraps) spreads over all.
            let mut dev: Vec<f32> = e.iter().map(|x| (x - median).abs()).collect();
            if median_in_place(&mut dev) > RING_ORDER_MAX_SPREAD_RAD {
                return None;
            }
            medians.push(median);
        }
        if !medians.windows(2).all(|m| m[0] > m[1]) {
            return None;
        }
        all.push(ids);
    }
    Some(all)
}

/// The largest median absolute deviation of elevation a ring of [`ring_order_groups`] may
/// have (KITTI's rings: about 0.1 deg, parallax included).
const RING_ORDER_MAX_SPREAD_RAD: f32 = 1.0f32.to_radians();

/// Histogram bin of the elevation clustering.
const CLUSTER_BIN_DEG: f32 = 0.01;
/// Gaussian smoothing of the histogram: wide enough to merge one beam's scatter at
/// range, narrow enough to split beams 1/3 deg apart (VLP-32C).
const CLUSTER_SIGMA_DEG: f32 = 0.04;

/// Returns nearer than this stay out of the clustering (see [`cluster_groups`]).
const CLUSTER_MIN_RANGE_M: f32 = 2.5;

/// 1-D clustering of point elevations over all scans: peaks of a smoothed,
/// range-weighted histogram, refined by a few rounds of "assign to the nearest
/// centre, move the centre to the median". Near returns weigh less, because a
/// laser's offset from the origin bends their apparent elevation (parallax).
/// Returns the cluster id of every point (`u32::MAX` for none).
fn cluster_groups(scans: &[Scan]) -> Vec<Vec<u32>> {
    let mut samples: Vec<(f32, f32)> = Vec::new(); // (elevation deg, weight)
    let mut near: Vec<(f32, f32)> = Vec::new();
    for scan in scans {
        for (i, p) in scan.xyz.iter().enumerate() {
            if scan.is_return(i) {
                let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                let sample = (elevation(*p).to_degrees(), (r / 20.0).clamp(0.05, 1.0));
                if r >= CLUSTER_MIN_RANGE_M {
                    samples.push(sample)
                } else {
                    near.push(sample)
                }
            }
        }
    }
    // Returns this near are often the vehicle's own body (nuScenes), not a beam's
    // sweep; use them only when they are most of the cloud (a small room).
    if near.len() > samples.len() {
        samples.append(&mut near);
    }
    let centres = refine_centres(&samples, histogram_peaks(&samples));
    scans
        .iter()
        .map(|scan| {
            (0..scan.len())
                .map(|i| {
                    if !scan.is_return(i) {
                        return u32::MAX;
                    }
                    nearest_centre(&centres, elevation(scan.xyz[i]).to_degrees())
                        .map_or(u32::MAX, |c| c as u32)
                })
                .collect()
        })
        .collect()
}

/// Local maxima of the smoothed weighted histogram, above 0.5 % of the highest and
/// separated from the previous kept peak by a valley below 80 % of the lower one.
fn histogram_peaks(samples: &[(f32, f32)]) -> Vec<f32> {
    let (lo, hi) = samples
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &(e, _)| {
            (lo.min(e), hi.max(e))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return Vec::new();
    }
    let lo = lo - 4.0 * CLUSTER_SIGMA_DEG;
    let bins = ((hi + 4.0 * CLUSTER_SIGMA_DEG - lo) / CLUSTER_BIN_DEG).ceil() as usize + 1;
    let mut hist = vec![0.0f32; bins];
    for &(e, w) in samples {
        if let Some(b) = hist.get_mut(((e - lo) / CLUSTER_BIN_DEG) as usize) {
            *b += w;
        }
    }
    let sigma = CLUSTER_SIGMA_DEG / CLUSTER_BIN_DEG;
    let half = (4.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> = (-half..=half)
        .map(|k| (-0.5 * (k as f32 / sigma).powi(2)).exp())
        .collect();
    let smooth: Vec<f32> = (0..bins as isize)
        .map(|b| {
            (-half..=half)
                .filter_map(|k| {
                    hist.get(usize::try_from(b + k).ok()?)
                        .map(|h| h * kernel[(k + half) as usize])
                })
                .sum()
        })
        .collect();
    let top = smooth.iter().copied().fold(0.0f32, f32::max);
    let mut peaks: Vec<usize> = Vec::new();
    for b in 1..bins.saturating_sub(1) {
        if smooth[b] > smooth[b - 1] && smooth[b] >= smooth[b + 1] && smooth[b] >= 0.005 * top {
            if let Some(&prev) = peaks.last() {
                let valley = smooth[prev..=b]
                    .iter()
                    .copied()
                    .fold(f32::INFINITY, f32::min);
                if valley >= 0.8 * smooth[prev].min(smooth[b]) {
                    // Not separated: keep the higher of the two.
                    if smooth[b] > smooth[prev] {
                        peaks.pop();
                        peaks.push(b);
                    }
                    continue;
                }
            }
            peaks.push(b);
        }
    }
    peaks
        .into_iter()
        .map(|b| lo + (b as f32 + 0.5) * CLUSTER_BIN_DEG)
        .collect()
}

/// Moves each centre to the weighted median of the samples nearest to it, and
/// drops centres that gather almost nothing (under 1 % of the median cluster).
fn refine_centres(samples: &[(f32, f32)], mut centres: Vec<f32>) -> Vec<f32> {
    for _ in 0..4 {
        let mut members: Vec<Vec<f32>> = vec![Vec::new(); centres.len()];
        for &(e, _) in samples {
            if let Some(c) = nearest_centre(&centres, e) {
                members[c].push(e);
            }
        }
        let mut sizes: Vec<f32> = members.iter().map(|m| m.len() as f32).collect();
        let floor = (0.01 * median_in_place(&mut sizes)).max(5.0);
        centres = members
            .into_iter()
            .filter(|m| m.len() as f32 >= floor)
            .map(|mut m| median_in_place(&mut m))
            .collect();
        centres.sort_by(f32::total_cmp);
        centres.dedup();
    }
    centres
}

/// Index of the centre nearest to `e` (centres sorted ascending).
fn nearest_centre(centres: &[f32], e: f32) -> Option<usize> {
    let k = centres.partition_point(|&c| c < e);
    match (k.checked_sub(1), centres.get(k)) {
        (Some(a), Some(&cb)) => Some(if e - centres[a] <= cb - e { a } else { k }),
        (Some(a), None) => Some(a),
        (None, Some(_)) => Some(k),
        (None, None) => None,
    }
}

impl fmt::Display for SensorEstimate {
    /// A short report; the alternate form (`{:#}`) adds one line per beam.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let spreads: Vec<f32> = self.beams.iter().map(|b| b.spread_deg).collect();
        let (lo, hi) = spreads
            .iter()
            .fold((f32::INFINITY, 0.0f32), |(lo, hi), &s| {
                (lo.min(s), hi.max(s))
            });
        let mut sorted = spreads.clone();
        let median_spread = median_in_place(&mut sorted);
        writeln!(
            f,
            "sensor estimate ({}), {} scan(s), {} returns",
            self.method.name(),
            self.scans,
            self.returns
        )?;
        let (top, bottom) = (
            self.profile.elevation_deg.first(),
            self.profile.elevation_deg.last(),
        );
        if let (Some(top), Some(bottom)) = (top, bottom) {
            writeln!(
                f,
                "  beams: {}, elevation {top:+.3} .. {bottom:+.3} deg",
                self.beams.len()
            )?;
        }
        writeln!(
            f,
            "  spread per beam (median abs. deviation): {lo:.3} .. {hi:.3} deg, median {median_spread:.3} deg"
        )?;
        match self.azimuth_step_deg {
            Some(step) => writeln!(
                f,
                "  columns: {} (azimuth step {step:.4} deg)",
                self.columns
            )?,
            None => writeln!(
                f,
                "  columns: {} (organized width; no azimuth step measured)",
                self.columns
            )?,
        }
        write!(
            f,
            "  range: {:.2} .. {:.2} m",
            self.min_range_m, self.max_range_m
        )?;
        if f.alternate() {
            write!(f, "\n  beam  elevation_deg  spread_deg  points")?;
            for (k, b) in self.beams.iter().enumerate() {
                write!(
                    f,
                    "\n  {k:>4}  {:>+13.3}  {:>10.3}  {:>6}",
                    b.elevation_deg, b.spread_deg, b.points
                )?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod snap_tests {
    use super::snap_columns;

    #[test]
    fn measured_columns_snap_to_standard_modes_only_when_close() {
        assert_eq!(snap_columns(508), 512);
        assert_eq!(snap_columns(2011), 2048);
        assert_eq!(snap_columns(1800), 1800);
        assert_eq!(
            snap_columns(1084),
            1084,
            "nuScenes' HDL-32E mode is not standard"
        );
        assert_eq!(snap_columns(360), 360);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-random numbers in [0, 1) (xorshift), for noise.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
        /// Roughly Gaussian (sum of uniforms), unit variance.
        fn normal(&mut self) -> f32 {
            (0..12).map(|_| self.next()).sum::<f32>() - 6.0
        }
    }

    /// A synthetic scan in KITTI ring order (each ring starts just left of ahead
    /// and sweeps counter-clockwise), with elevation noise, random ranges and 10 %
    /// of returns dropped (kept as zero points so layouts can be rearranged).
    /// Returns the points, beam of each point, and the columns.
    fn synthetic(
        table_deg: &[f32],
        columns: usize,
        noise_deg: f32,
        seed: u64,
    ) -> (Vec<[f32; 3]>, Vec<u16>) {
        let mut rng = Rng(seed);
        let (mut xyz, mut beam) = (Vec::new(), Vec::new());
        for (b, e) in table_deg.iter().enumerate() {
            for c in 0..columns {
                let az = 0.001 + c as f32 * TAU / columns as f32;
                let e = (e + noise_deg * rng.normal()).to_radians();
                let r = 3.0 + 60.0 * rng.next();
                let keep = rng.next() > 0.1;
                let p = [r * e.cos() * az.cos(), r * e.cos() * az.sin(), r * e.sin()];
                xyz.push(if keep { p } else { [0.0; 3] });
                beam.push(b as u16);
            }
        }
        (xyz, beam)
    }

    fn vlp32c() -> Vec<f32> {
        SensorProfile::builtin("vlp32c").unwrap().elevation_deg
    }

    fn assert_table(est: &SensorEstimate, truth: &[f32], tol_deg: f32) {
        assert_eq!(est.beams.len(), truth.len(), "{est:#}");
        for (b, t) in est.beams.iter().zip(truth) {
            assert!(
                (b.elevation_deg - t).abs() < tol_deg,
                "{} vs {t}\n{est:#}",
                b.elevation_deg
            );
        }
        est.profile.validate().unwrap();
    }

    /// Drops the zero placeholders, as an unorganized cloud would.
    fn compact(xyz: &[[f32; 3]], beam: &[u16]) -> (Vec<[f32; 3]>, Vec<u16>) {
        xyz.iter()
            .zip(beam)
            .filter(|(p, _)| **p != [0.0; 3])
            .map(|(p, b)| (*p, *b))
            .unzip()
    }

    #[test]
    fn ring_field_gives_median_elevations_in_any_point_order() {
        let table = vlp32c();
        let (xyz, beam) = synthetic(&table, 900, 0.02, 1);
        let (xyz, beam) = compact(&xyz, &beam);
        // Reverse the order and number rings bottom-up, as Velodyne drivers do.
        let ring: Vec<u16> = beam.iter().rev().map(|b| 31 - b).collect();
        let mut scan = Scan::from_xyz(xyz.into_iter().rev().collect());
        scan.ring = Some(ring);
        let est = estimate_profile(&[scan]).unwrap();
        assert_eq!(est.method, EstimateMethod::RingField);
        assert_table(&est, &table, 0.01);
        assert_eq!(est.columns, 900);
        assert!(
            est.beams
                .iter()
                .all(|b| b.spread_deg > 0.005 && b.spread_deg < 0.03),
            "{est:#}"
        );
    }

    #[test]
    fn kitti_ring_order_is_recognised_without_a_ring_field() {
        let table: Vec<f32> = SensorProfile::kitti_hdl64e().elevation_deg;
        let scans: Vec<Scan> = (0..2)
            .map(|seed| {
                let (xyz, beam) = synthetic(&table, 1024, 0.02, 10 + seed);
                Scan::from_xyz(compact(&xyz, &beam).0)
            })
            .collect();
        let est = estimate_profile(&scans).unwrap();
        assert_eq!(est.method, EstimateMethod::RingOrder);
        assert_table(&est, &table, 0.01);
        assert_eq!(est.columns, 1024);
        assert_eq!(est.scans, 2);
        assert!(est.min_range_m >= 2.99 && est.max_range_m <= 63.01, "{est}");
    }

    #[test]
    fn column_major_organized_clouds_are_told_from_row_major() {
        let table = vec![15.0, 5.0, 1.0, -1.0, -5.0, -15.0];
        let (xyz, beam) = synthetic(&table, 512, 0.02, 3);
        let cm: Vec<[f32; 3]> = (0..512)
            .flat_map(|c| (0..6).map(move |b| b * 512 + c))
            .map(|i| xyz[i])
            .collect();
        let scan = Scan {
            xyz: cm,
            height: 6,
            width: 512,
            ..Default::default()
        };
        let est = estimate_profile(&[scan]).unwrap();
        assert_eq!(est.method, EstimateMethod::ColumnMajor);
        assert_table(&est, &table, 0.01);
        assert_eq!(est.columns, 512);
        // The same data stored row-major is read row by row.
        let scan = Scan {
            xyz,
            height: 6,
            width: 512,
            ..Default::default()
        };
        let est = estimate_profile(&[scan]).unwrap();
        assert_eq!(est.method, EstimateMethod::RowMajor);
        assert_table(&est, &table, 0.01);
        assert_eq!(beam.len(), 6 * 512);
    }

    #[test]
    fn clustering_finds_beams_of_an_unordered_cloud() {
        // VLP-32C: beams as close as 1/3 deg, shuffled, no ring field.
        let table = vlp32c();
        let (xyz, beam) = synthetic(&table, 1800, 0.03, 4);
        let (xyz, _) = compact(&xyz, &beam);
        let mut rng = Rng(99);
        let mut order: Vec<(f32, [f32; 3])> = xyz.into_iter().map(|p| (rng.next(), p)).collect();
        order.sort_by(|a, b| a.0.total_cmp(&b.0));
        let scan = Scan::from_xyz(order.into_iter().map(|(_, p)| p).collect());
        let est = estimate_profile(&[scan]).unwrap();
        assert_eq!(est.method, EstimateMethod::ElevationClusters);
        assert_table(&est, &table, 0.02);
        assert_eq!(est.columns, 1800);
        let text = format!("{est:#}");
        assert!(
            text.contains("elevation clustering") && text.contains("columns: 1800"),
            "{text}"
        );
        assert_eq!(text.lines().count(), 5 + 1 + 32, "{text}");
    }

    /// A cloud in firing order (every beam of a column, then the next column), starting a
    /// little before straight ahead as a Hesai XT32's does: the azimuth wraps once inside
    /// it, which KITTI's ring order would read as two "rings" of every beam. Each such ring
    /// spreads over the whole field of view, so it is not taken for ring order; the
    /// clustering finds the 32 beams.
    #[test]
    fn a_cloud_in_firing_order_is_not_read_as_ring_order() {
        let table: Vec<f32> = (0..32).map(|b| 15.0 - b as f32).collect();
        let mut rng = Rng(7);
        let columns = 2000;
        let mut xyz = Vec::new();
        for c in 0..columns {
            let az = -0.2 + c as f32 * TAU / columns as f32;
            for e in &table {
                let e = (e + 0.02 * rng.normal()).to_radians();
                let r = 3.0 + 30.0 * rng.next();
                xyz.push([r * e.cos() * az.cos(), r * e.cos() * az.sin(), r * e.sin()]);
            }
        }
        let est = estimate_profile(&[Scan::from_xyz(xyz)]).unwrap();
        assert_eq!(est.method, EstimateMethod::ElevationClusters, "{est:#}");
        assert_eq!(est.beams.len(), 32, "{est:#}");
    }

    #[test]
    fn empty_and_degenerate_input_is_an_error() {
        assert_eq!(estimate_profile(&[]).unwrap_err(), EstimateError::NoScans);
        let scan = Scan::from_xyz(vec![[0.0; 3], [f32::NAN, 0.0, 0.0]]);
        assert_eq!(
            estimate_profile(&[scan]).unwrap_err(),
            EstimateError::NoReturns
        );
        // One flat ring is not a sensor.
        let (xyz, beam) = synthetic(&[0.0], 360, 0.01, 5);
        let scan = Scan::from_xyz(compact(&xyz, &beam).0);
        assert_eq!(
            estimate_profile(&[scan]).unwrap_err(),
            EstimateError::TooFewBeams { found: 1 }
        );
        let mut scan = Scan::from_xyz(vec![[1.0, 0.0, 0.0]; 4]);
        scan.ring = Some(vec![0; 3]);
        assert!(matches!(
            estimate_profile(&[scan]),
            Err(EstimateError::FieldLength {
                field: "ring",
                len: 3,
                points: 4
            })
        ));
    }
}

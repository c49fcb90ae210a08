//! One LiDAR sweep as decoded from a message or a dataset file, in the sensor frame.

/// Farthest range a return may have. No LiDAR measures beyond a few hundred metres; a
/// point past this is a corrupt or placeholder value and never reaches a pixel.
pub const MAX_RETURN_RANGE_M: f32 = 2_000.0;

/// A decoded point cloud, structure of arrays, points in message order.
///
/// Organized clouds (`height > 1`) keep every cell, with non-finite or all-zero
/// xyz where the sensor had no return; unorganized clouds (`height == 1`) usually
/// omit dropped points. Optional fields are `Some` only when the source had them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scan {
    /// Cartesian coordinates in meters, sensor frame (x forward, y left, z up).
    pub xyz: Vec<[f32; 3]>,
    /// Intensity or reflectivity, as stored by the source (units vary by sensor).
    pub intensity: Option<Vec<f32>>,
    /// Laser (beam) index from a `ring` / `channel` / `laser_id` field.
    pub ring: Option<Vec<u16>>,
    /// Per-point time offset from the start of the sweep, in seconds.
    pub time_s: Option<Vec<f32>>,
    /// Semantic label (SemanticKITTI class id in the low 16 bits).
    pub label: Option<Vec<u32>>,
    /// Rows of an organized cloud (1 when unorganized).
    pub height: usize,
    /// Points per row (`len()` when unorganized).
    pub width: usize,
}

impl Scan {
    /// An unorganized scan from bare coordinates.
    pub fn from_xyz(xyz: Vec<[f32; 3]>) -> Self {
        let width = xyz.len();
        Scan {
            xyz,
            height: 1,
            width,
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }

    pub fn is_organized(&self) -> bool {
        self.height > 1
    }

    /// Whether point `i` is a real return: finite, not the all-zero placeholder that
    /// drivers (Ouster, Velodyne organized mode) write for no return, and within
    /// [`MAX_RETURN_RANGE_M`] (coordinates near 1e30 would overflow the range to infinity).
    pub fn is_return(&self, i: usize) -> bool {
        let [x, y, z] = self.xyz[i];
        let r2 = x * x + y * y + z * z;
        r2 > 0.0 && r2 <= MAX_RETURN_RANGE_M * MAX_RETURN_RANGE_M
    }

    /// Points with finite coordinates that are still no return: beyond
    /// [`MAX_RETURN_RANGE_M`], or so large that their range overflows.
    pub fn absurd_points(&self) -> usize {
        let finite = |p: &[f32; 3]| p.iter().all(|c| c.is_finite());
        (0..self.len())
            .filter(|&i| finite(&self.xyz[i]) && self.xyz[i] != [0.0; 3] && !self.is_return(i))
            .count()
    }

    /// Number of real returns.
    pub fn returns(&self) -> usize {
        (0..self.len()).filter(|&i| self.is_return(i)).count()
    }
}

/// Ring ids from a ring field's raw values. Non-negative integers below 65 536 (every
/// driver's numbering) are kept as they are. Other finite values (negative rings of a signed
/// field, fractions, values past u16) are renumbered 0, 1, ... in the order of their values,
/// so that no two rings merge: projection orders rings by their median elevation, so only
/// which points share a ring matters. A non-finite value at a return leaves no usable ring
/// field: `Err` with how many such returns there are. At a point without a return any value
/// is harmless (it is never projected).
pub fn ring_ids(values: &[f64], is_return: impl Fn(usize) -> bool) -> Result<Vec<u16>, usize> {
    let bad = (0..values.len())
        .filter(|&i| !values[i].is_finite() && is_return(i))
        .count();
    if bad > 0 {
        return Err(bad);
    }
    let plain = |v: f64| (0.0..=u16::MAX as f64).contains(&v) && v.fract() == 0.0;
    if values.iter().all(|&v| plain(v) || !v.is_finite()) {
        return Ok(values.iter().map(|&v| v as u16).collect());
    }
    let mut distinct: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    distinct.sort_by(f64::total_cmp);
    distinct.dedup();
    Ok(values
        .iter()
        .map(|v| {
            let rank = distinct.partition_point(|d| d < v);
            rank.min(u16::MAX as usize) as u16
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_and_nan_points_are_not_returns() {
        let scan = Scan::from_xyz(vec![[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [f32::NAN, 1.0, 1.0]]);
        assert!(scan.is_return(0));
        assert!(!scan.is_return(1));
        assert!(!scan.is_return(2));
        assert_eq!(scan.returns(), 1);
        assert!(!scan.is_organized());
    }

    /// Ring values of any sign or size keep their rings apart; unsigned ones are kept as
    /// they are; a non-finite value at a return leaves no ring field, at a point without a
    /// return it is harmless.
    #[test]
    fn ring_values_of_any_sign_keep_their_rings_apart() {
        let all = |_: usize| true;
        assert_eq!(ring_ids(&[3.0, 0.0, 63.0], all), Ok(vec![3, 0, 63]));
        assert_eq!(
            ring_ids(&[-16.0, 15.0, -1.0, 0.0, -16.0], all),
            Ok(vec![0, 3, 1, 2, 0])
        );
        let min = i32::MIN as f64;
        assert_eq!(ring_ids(&[min, 1.0, 2.0, min], all), Ok(vec![0, 1, 2, 0]));
        assert_eq!(ring_ids(&[0.5, 1.5, 70_000.0], all), Ok(vec![0, 1, 2]));
        assert_eq!(ring_ids(&[1.0, f64::NAN, 2.0], all), Err(1));
        assert_eq!(
            ring_ids(&[1.0, f64::NAN, 2.0], |i| i != 1),
            Ok(vec![1, 0, 2])
        );
    }
}

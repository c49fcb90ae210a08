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
}

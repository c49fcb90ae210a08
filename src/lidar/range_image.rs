//! Range images: an H x W grid, row = beam (elevation), column = azimuth, holding
//! per pixel the range, the xyz of the return that won the pixel, intensity, label,
//! and the per-pixel angle grid the pixel stands for.

use std::f32::consts::PI;

/// Per-pixel directions of a range image, row-major `H x W`.
///
/// Azimuth `theta` follows the reference convention: column `j` of a regular grid
/// sits at `pi - (j + 0.5) * 2 pi / W` (column 0 at the rear, clockwise seen from
/// above, the image centre straight ahead along +x). Elevation `phi` is up from the
/// horizontal plane. Both in radians.
#[derive(Debug, Clone, PartialEq)]
pub struct AngleGrid {
    pub height: usize,
    pub width: usize,
    pub elevation_rad: Vec<f32>,
    pub azimuth_rad: Vec<f32>,
}

impl AngleGrid {
    /// A grid whose row `i` sits at `elevation_of_row(i)` and whose columns are the
    /// regular azimuths of the reference convention.
    pub fn regular_columns(
        height: usize,
        width: usize,
        elevation_of_row: impl Fn(usize) -> f32,
    ) -> Self {
        let mut elevation_rad = Vec::with_capacity(height * width);
        let mut azimuth_rad = Vec::with_capacity(height * width);
        for i in 0..height {
            let phi = elevation_of_row(i);
            for j in 0..width {
                elevation_rad.push(phi);
                azimuth_rad.push(column_azimuth(j, width));
            }
        }
        AngleGrid {
            height,
            width,
            elevation_rad,
            azimuth_rad,
        }
    }

    /// Unit direction of pixel `k` (row-major index), sensor frame.
    pub fn direction(&self, k: usize) -> [f32; 3] {
        let (phi, theta) = (self.elevation_rad[k], self.azimuth_rad[k]);
        [phi.cos() * theta.cos(), phi.cos() * theta.sin(), phi.sin()]
    }

    pub fn len(&self) -> usize {
        self.height * self.width
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Azimuth of column `j` of `width` (reference convention), in (-pi, pi).
pub fn column_azimuth(j: usize, width: usize) -> f32 {
    PI - (j as f32 + 0.5) * 2.0 * PI / width as f32
}

/// The (fractional) column of azimuth `theta` on a `width`-column grid, in [0, width).
pub fn azimuth_column(theta: f32, width: usize) -> f32 {
    let c = (PI - theta) * width as f32 / (2.0 * PI) - 0.5;
    c.rem_euclid(width as f32)
}

/// Marker for "no point landed here" in [`RangeImage::point_index`].
pub const NO_POINT: u32 = u32::MAX;

/// A projected scan. All per-pixel vectors are row-major `H x W`.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeImage {
    pub height: usize,
    pub width: usize,
    /// Range in meters; 0.0 where no return landed.
    pub range_m: Vec<f32>,
    /// The xyz of the return that won the pixel (kept exactly, so back-projection
    /// returns every kept point); zeros where empty.
    pub xyz: Vec<[f32; 3]>,
    /// Intensity of the winning return (0 where empty or absent in the source).
    pub intensity: Vec<f32>,
    /// Label of the winning return (0 = unlabelled).
    pub label: Vec<u32>,
    /// Index of the winning point in the source scan, or [`NO_POINT`].
    pub point_index: Vec<u32>,
    /// The direction each pixel stands for.
    pub angles: AngleGrid,
}

impl RangeImage {
    /// An empty image on `angles`.
    pub fn empty(angles: AngleGrid) -> Self {
        let n = angles.len();
        RangeImage {
            height: angles.height,
            width: angles.width,
            range_m: vec![0.0; n],
            xyz: vec![[0.0; 3]; n],
            intensity: vec![0.0; n],
            label: vec![0; n],
            point_index: vec![NO_POINT; n],
            angles,
        }
    }

    pub fn len(&self) -> usize {
        self.height * self.width
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether pixel `k` holds a return.
    pub fn is_valid(&self, k: usize) -> bool {
        self.range_m[k] > 0.0
    }

    /// Number of pixels holding a return.
    pub fn valid_count(&self) -> usize {
        self.range_m.iter().filter(|r| **r > 0.0).count()
    }

    /// The kept returns as points: the exact xyz stored per pixel, row-major order.
    pub fn to_points(&self) -> Vec<[f32; 3]> {
        (0..self.len())
            .filter(|&k| self.is_valid(k))
            .map(|k| self.xyz[k])
            .collect()
    }

    /// Points from the range alone along each pixel's grid direction, as a generated
    /// depth image has no measured xyz: `(d cos phi cos theta, d cos phi sin theta, d sin phi)`.
    pub fn grid_points(&self) -> Vec<[f32; 3]> {
        (0..self.len())
            .filter(|&k| self.is_valid(k))
            .map(|k| {
                let [x, y, z] = self.angles.direction(k);
                let d = self.range_m[k];
                [d * x, d * y, d * z]
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn azimuth_and_column_are_inverse() {
        for w in [4usize, 512, 2048] {
            for j in [0, 1, w / 2, w - 1] {
                let c = azimuth_column(column_azimuth(j, w), w);
                assert!((c - j as f32).abs() < 1e-3, "w={w} j={j} c={c}");
            }
        }
        // Straight ahead lands in the middle of the image.
        assert!((azimuth_column(0.0, 512) - 255.5).abs() < 1e-3);
    }

    #[test]
    fn grid_points_follow_the_pixel_direction() {
        let angles = AngleGrid::regular_columns(2, 4, |i| if i == 0 { 0.1 } else { -0.2 });
        let mut img = RangeImage::empty(angles);
        let k = 4 + 2; // row 1, column 2: azimuth -pi/4
        img.range_m[k] = 10.0;
        let p = img.grid_points();
        assert_eq!(p.len(), 1);
        let r = (p[0][0].powi(2) + p[0][1].powi(2) + p[0][2].powi(2)).sqrt();
        assert!((r - 10.0).abs() < 1e-4);
        assert!((p[0][2] - 10.0 * (-0.2f32).sin()).abs() < 1e-4);
        assert!(
            (p[0][1] / p[0][0] + 1.0).abs() < 1e-4,
            "azimuth -pi/4: y = -x"
        );
    }
}

//! Ray casting a [`SensorProfile`] in a [`Scene`]: one ray per range-image pixel
//! from the sensor pose at the scan's start time (an ideal, instantaneous, i.e.
//! de-skewed, scan), rayon over rows. Produces a [`SimScan`]: the range image plus
//! the per-pixel ground truth the physics layer keys on (material, incidence,
//! reflectivity, time, true range).

use rayon::prelude::*;

use super::geometry::{Ray, Vec3, v3};
use super::material::Material;
use super::scene::Scene;
use crate::lidar::{RangeImage, Scan, SensorProfile};
use crate::util::rng::key_hash;

/// When each column is measured within a sweep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SweepTiming {
    /// Seconds per revolution (10 Hz: 0.1).
    pub period_s: f32,
    /// Azimuth at which a sweep starts (KITTI cuts its scans straight ahead: 0).
    pub start_azimuth_rad: f32,
    /// Sweep direction: true = counter-clockwise seen from above (increasing
    /// azimuth), the point order of KITTI `.bin` rings.
    pub counter_clockwise: bool,
}

impl Default for SweepTiming {
    fn default() -> Self {
        SweepTiming {
            period_s: 0.1,
            start_azimuth_rad: 0.0,
            counter_clockwise: true,
        }
    }
}

impl SweepTiming {
    /// Time offset from the sweep start at which azimuth `theta` is measured.
    pub fn time_at(&self, theta: f32) -> f32 {
        let tau = std::f32::consts::TAU;
        let delta = if self.counter_clockwise {
            theta - self.start_azimuth_rad
        } else {
            self.start_azimuth_rad - theta
        };
        delta.rem_euclid(tau) / tau * self.period_s
    }
}

/// The sensor's pose and motion at a scan's start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorPose {
    /// Sensor origin in the world frame.
    pub origin: Vec3,
    /// Columns: the sensor's x (forward), y (left), z (up) axes in the world frame.
    pub axes: [Vec3; 3],
    /// Ego linear velocity in the sensor frame, m/s.
    pub velocity_mps: [f32; 3],
    /// Ego yaw rate, rad/s (counter-clockwise).
    pub yaw_rate_rps: f32,
    /// Planar heading in the world frame.
    pub yaw_rad: f32,
}

impl SensorPose {
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.axes[0] * v.x + self.axes[1] * v.y + self.axes[2] * v.z
    }
    pub fn to_sensor(&self, v: Vec3) -> Vec3 {
        v3(
            v.dot(self.axes[0]),
            v.dot(self.axes[1]),
            v.dot(self.axes[2]),
        )
    }
    /// Rotation world_from_sensor as a unit quaternion [x, y, z, w].
    pub fn quaternion(&self) -> [f64; 4] {
        let [x, y, z] = self.axes;
        let m = [[x.x, y.x, z.x], [x.y, y.y, z.y], [x.z, y.z, z.z]].map(|r| r.map(f64::from));
        let tr = m[0][0] + m[1][1] + m[2][2];
        let q = if tr > 0.0 {
            let s = (tr + 1.0).sqrt() * 2.0;
            [
                (m[2][1] - m[1][2]) / s,
                (m[0][2] - m[2][0]) / s,
                (m[1][0] - m[0][1]) / s,
                0.25 * s,
            ]
        } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
            let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
            [
                0.25 * s,
                (m[0][1] + m[1][0]) / s,
                (m[0][2] + m[2][0]) / s,
                (m[2][1] - m[1][2]) / s,
            ]
        } else if m[1][1] > m[2][2] {
            let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
            [
                (m[0][1] + m[1][0]) / s,
                0.25 * s,
                (m[1][2] + m[2][1]) / s,
                (m[0][2] - m[2][0]) / s,
            ]
        } else {
            let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
            [
                (m[0][2] + m[2][0]) / s,
                (m[1][2] + m[2][1]) / s,
                0.25 * s,
                (m[1][0] - m[0][1]) / s,
            ]
        };
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        q.map(|c| c / n)
    }
}

/// One simulated scan: a range image (row-major H x W, sensor frame) plus per-pixel
/// ground truth. A pixel with no return has range 0 and material `None`.
#[derive(Debug, Clone)]
pub struct SimScan {
    pub image: RangeImage,
    /// Material of the surface hit (ground truth, kept when physics drops the return).
    pub material: Vec<Material>,
    /// Angle between the ray and the surface normal, radians (0 = head-on).
    pub incidence_rad: Vec<f32>,
    /// Unit normal of the surface hit in the sensor frame, facing the sensor; zero where no
    /// surface was hit or its orientation is unknown.
    pub normal: Vec<[f32; 3]>,
    /// Diffuse reflectivity of the surface hit.
    pub reflectivity: Vec<f32>,
    /// Time offset of the pixel's measurement from the sweep start.
    pub time_s: Vec<f32>,
    /// First-hit range before any physics (0 = no surface within max range).
    pub true_range_m: Vec<f32>,
    /// Class label of the surface hit before any physics (kept for dropped rays).
    pub true_label: Vec<u32>,
    /// Scan index within the drive.
    pub index: u32,
    /// Start time of the scan from the start of the drive.
    pub start_time_s: f64,
    pub pose: SensorPose,
    pub min_range_m: f32,
    pub max_range_m: f32,
}

/// Intensity model: reflectivity x cos(incidence) x range falloff
/// `d0^2 / (d0^2 + d^2)` with `d0` = 40 m (close targets saturate to rho cos).
pub fn intensity(reflectivity: f32, cos_incidence: f32, range_m: f32) -> f32 {
    const D0: f32 = 40.0;
    reflectivity * cos_incidence * (D0 * D0 / (D0 * D0 + range_m * range_m))
}

impl SimScan {
    pub fn height(&self) -> usize {
        self.image.height
    }
    pub fn width(&self) -> usize {
        self.image.width
    }
    pub fn len(&self) -> usize {
        self.image.len()
    }
    pub fn is_empty(&self) -> bool {
        self.image.is_empty()
    }
    /// Whether pixel `k` holds a return now.
    pub fn is_return(&self, k: usize) -> bool {
        self.image.range_m[k] > 0.0
    }
    /// Removes the return of pixel `k` (a dropped ray).
    pub fn drop_return(&mut self, k: usize) {
        self.image.range_m[k] = 0.0;
        self.image.xyz[k] = [0.0; 3];
        self.image.intensity[k] = 0.0;
        self.image.label[k] = 0;
        self.image.point_index[k] = crate::lidar::range_image::NO_POINT;
    }
    /// Moves the return of pixel `k` to `range_m` along its measured direction.
    pub fn set_range(&mut self, k: usize, range_m: f32) {
        let old = self.image.range_m[k];
        if old <= 0.0 {
            return;
        }
        let s = range_m / old;
        self.image.xyz[k] = self.image.xyz[k].map(|c| c * s);
        self.image.range_m[k] = range_m;
    }
    /// Kept returns / pixels.
    pub fn keep_rate(&self) -> f32 {
        self.image.valid_count() as f32 / self.len().max(1) as f32
    }

    /// The scan as a point cloud with fields x, y, z, intensity, ring (row, top = 0),
    /// time and label. `organized`: every pixel, NaN xyz where no return
    /// (`height` x `width`); else only returns, row-major.
    pub fn to_scan(&self, organized: bool) -> Scan {
        let n = self.len();
        let w = self.width();
        let keep: Vec<usize> = if organized {
            (0..n).collect()
        } else {
            (0..n).filter(|&k| self.is_return(k)).collect()
        };
        let nan = [f32::NAN; 3];
        let xyz = keep
            .iter()
            .map(|&k| {
                if self.is_return(k) {
                    self.image.xyz[k]
                } else {
                    nan
                }
            })
            .collect();
        Scan {
            xyz,
            intensity: Some(keep.iter().map(|&k| self.image.intensity[k]).collect()),
            ring: Some(keep.iter().map(|&k| (k / w) as u16).collect()),
            time_s: Some(keep.iter().map(|&k| self.time_s[k]).collect()),
            label: Some(keep.iter().map(|&k| self.image.label[k]).collect()),
            height: if organized { self.height() } else { 1 },
            width: if organized { w } else { keep.len() },
        }
    }
}

/// A unit surface normal turned to face a ray of direction `dir` (whichever side of a
/// surface a ray hits, the normal that matters faces back along it).
pub fn facing_sensor(normal: Vec3, dir: Vec3) -> [f32; 3] {
    let n = normal.normalized();
    if n.dot(dir) > 0.0 {
        (n * -1.0).to_array()
    } else {
        n.to_array()
    }
}

/// Casts every pixel ray of `profile` from `pose` in `scene` at time `t_s`.
pub fn cast_scan(
    scene: &Scene,
    profile: &SensorProfile,
    pose: &SensorPose,
    timing: &SweepTiming,
    t_s: f64,
    index: u32,
) -> SimScan {
    let angles = profile.angle_grid();
    let (h, w) = (angles.height, angles.width);
    let n = h * w;
    let dynamic = scene.dynamic_bvh(
        t_s as f32,
        [pose.origin.x, pose.origin.y],
        profile.max_range_m,
    );
    let seed = scene.config.seed;
    let mut image = RangeImage::empty(angles);
    let mut material = vec![Material::None; n];
    let mut incidence_rad = vec![0.0f32; n];
    let mut normal = vec![[0.0f32; 3]; n];
    let mut reflectivity = vec![0.0f32; n];
    let mut true_label = vec![0u32; n];
    let time_s: Vec<f32> = (0..n)
        .map(|k| timing.time_at(image.angles.azimuth_rad[k]))
        .collect();
    // Pixel directions from per-row and per-column sines (rows share an elevation).
    let elevation: Vec<(f32, f32)> = (0..h)
        .map(|i| image.angles.elevation_rad[i * w].sin_cos())
        .collect();
    let azimuth: Vec<(f32, f32)> = (0..w)
        .map(|j| image.angles.azimuth_rad[j].sin_cos())
        .collect();
    let (min_r, max_r) = (profile.min_range_m, profile.max_range_m);
    {
        let rows = image
            .range_m
            .par_chunks_mut(w)
            .zip(image.xyz.par_chunks_mut(w))
            .zip(image.intensity.par_chunks_mut(w))
            .zip(image.label.par_chunks_mut(w))
            .zip(image.point_index.par_chunks_mut(w))
            .zip(material.par_chunks_mut(w))
            .zip(incidence_rad.par_chunks_mut(w))
            .zip(normal.par_chunks_mut(w))
            .zip(reflectivity.par_chunks_mut(w))
            .zip(true_label.par_chunks_mut(w))
            .enumerate();
        rows.for_each(
            |(
                row,
                (((((((((range, xyz), inten), label), pidx), mat), inc), nrm), refl), tlabel),
            )| {
                let (sin_e, cos_e) = elevation[row];
                for j in 0..w {
                    let k = row * w + j;
                    let (sin_a, cos_a) = azimuth[j];
                    let d_sensor = v3(cos_e * cos_a, cos_e * sin_a, sin_e);
                    let ray = Ray::new(pose.origin, pose.to_world(d_sensor));
                    let key = key_hash(&[seed, index as u64, k as u64]);
                    let Some(hit) = scene.cast(&dynamic, &ray, max_r, key) else {
                        continue;
                    };
                    let cos_inc = (-hit.normal.dot(ray.dir)).clamp(0.0, 1.0);
                    let class = hit.surface.label | ((hit.instance as u32) << 16);
                    mat[j] = hit.surface.material;
                    inc[j] = cos_inc.acos();
                    nrm[j] = facing_sensor(pose.to_sensor(hit.normal), d_sensor);
                    refl[j] = hit.surface.reflectivity;
                    tlabel[j] = class;
                    if hit.t < min_r {
                        continue;
                    }
                    range[j] = hit.t;
                    xyz[j] = (d_sensor * hit.t).to_array();
                    inten[j] = intensity(hit.surface.reflectivity, cos_inc, hit.t);
                    label[j] = class;
                    pidx[j] = k as u32;
                }
            },
        );
    }
    let true_range_m = image.range_m.clone();
    SimScan {
        image,
        material,
        incidence_rad,
        normal,
        reflectivity,
        time_s,
        true_range_m,
        true_label,
        index,
        start_time_s: t_s,
        pose: *pose,
        min_range_m: min_r,
        max_range_m: max_r,
    }
}

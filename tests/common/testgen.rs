//! An independent generator of concealed sim/real pairs for the diagnosis: its
//! own scene family (parking lot, highway with barriers, rural road with
//! vegetation, garage or tunnel), its own analytic ray caster (planes, boxes,
//! vertical cylinders, spheres; nothing of `rangegan_mcap::sim::scene`, `bvh` or
//! `raycast`), and randomised sensors (16 / 32 / 64 / 128 beams, uniform or
//! horizon-dense beam spacing, 1.2-2.2 m mounting height, organized or
//! unorganized clouds, a ring field or none). Both sides of a pair come from
//! it: the same sensor and scene family, other scene seeds; the left-out effects
//! (the catalogue's own `Effect`s) on the real side, the sim side's uniform
//! dropout raised until the global drop rates match (the effect concealed).
//! Each side's clouds go through the same projection as `diagnose` (automatic
//! strategy) before their features are computed.
#![allow(dead_code)]

use std::collections::BTreeMap;

use rangegan_mcap::diagnose::features::{FeatureOptions, ScanFeatures};
use rangegan_mcap::diagnose::{DiagnoseOptions, Diagnosis, diagnose};
use rangegan_mcap::lidar::projection::choose_strategy;
use rangegan_mcap::lidar::{RangeImage, SensorProfile, project};
use rangegan_mcap::physics::dropout::{
    BeamDropout, IncidenceDropout, MaterialDropout, OcclusionSector, RangeDropout, SelfOcclusion,
    UniformDropout,
};
use rangegan_mcap::physics::perturb::{MixedPixels, MotionDistortion, RangeNoise};
use rangegan_mcap::physics::{Effect, Physics};
use rangegan_mcap::sim::raycast::intensity;
use rangegan_mcap::sim::{Material, SensorPose, SimScan, label};

/// The catalogue effects the diagnosis has a candidate for.
pub const EFFECTS: [&str; 8] = [
    "range_dropout",
    "incidence_dropout",
    "beam_dropout",
    "material_dropout",
    "self_occlusion",
    "range_noise",
    "mixed_pixels",
    "motion_distortion",
];

/// Seeded splitmix64 stream (its own, not the simulator's keyed hash).
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed ^ 0x7e57_9e4e_0000_0001)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn f(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f()
    }
    pub fn pick<T: Copy>(&mut self, items: &[T]) -> T {
        items[(self.next_u64() % items.len() as u64) as usize]
    }
    pub fn chance(&mut self, p: f32) -> bool {
        self.f() < p
    }
}

/// What a surface is: class, material, diffuse reflectivity.
#[derive(Debug, Clone, Copy)]
struct Surface {
    label: u32,
    material: Material,
    reflectivity: f32,
}

const fn surf(label: u32, material: Material, reflectivity: f32) -> Surface {
    Surface {
        label,
        material,
        reflectivity,
    }
}

#[derive(Debug, Clone, Copy)]
enum Shape {
    /// Axis-aligned box.
    Box {
        min: [f32; 3],
        max: [f32; 3],
    },
    /// Vertical cylinder.
    Cylinder {
        c: [f32; 2],
        r: f32,
        z0: f32,
        z1: f32,
    },
    Sphere {
        c: [f32; 3],
        r: f32,
    },
}

#[derive(Debug, Clone, Copy)]
struct Object {
    shape: Shape,
    surface: Surface,
}

impl Object {
    /// Centre and radius of the footprint in the ground plane (for culling).
    fn footprint(&self) -> ([f32; 2], f32) {
        match self.shape {
            Shape::Box { min, max } => {
                let c = [(min[0] + max[0]) / 2.0, (min[1] + max[1]) / 2.0];
                let r = ((max[0] - min[0]).powi(2) + (max[1] - min[1]).powi(2)).sqrt() / 2.0;
                (c, r)
            }
            Shape::Cylinder { c, r, .. } => (c, r),
            Shape::Sphere { c, r } => ([c[0], c[1]], r),
        }
    }

    /// Nearest hit distance and outward normal of ray `o + t d`, t > 0.
    fn hit(&self, o: [f32; 3], d: [f32; 3]) -> Option<(f32, [f32; 3])> {
        match self.shape {
            Shape::Box { min, max } => {
                let (mut t0, mut t1, mut axis) = (0.0f32, f32::INFINITY, 3usize);
                for a in 0..3 {
                    if d[a].abs() < 1e-9 {
                        if o[a] < min[a] || o[a] > max[a] {
                            return None;
                        }
                        continue;
                    }
                    let (mut ta, mut tb) = ((min[a] - o[a]) / d[a], (max[a] - o[a]) / d[a]);
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis = a;
                    }
                    t1 = t1.min(tb);
                    if t0 > t1 {
                        return None;
                    }
                }
                if axis == 3 {
                    return None; // origin inside
                }
                let mut n = [0.0; 3];
                n[axis] = -d[axis].signum();
                Some((t0, n))
            }
            Shape::Cylinder { c, r, z0, z1 } => {
                let (px, py) = (o[0] - c[0], o[1] - c[1]);
                let a = d[0] * d[0] + d[1] * d[1];
                if a < 1e-12 {
                    return None;
                }
                let b = px * d[0] + py * d[1];
                let disc = b * b - a * (px * px + py * py - r * r);
                if disc < 0.0 {
                    return None;
                }
                let t = (-b - disc.sqrt()) / a;
                let z = o[2] + t * d[2];
                (t > 0.0 && z >= z0 && z <= z1).then(|| {
                    let (nx, ny) = (px + t * d[0], py + t * d[1]);
                    (t, [nx / r, ny / r, 0.0])
                })
            }
            Shape::Sphere { c, r } => {
                let p = [o[0] - c[0], o[1] - c[1], o[2] - c[2]];
                let b = p[0] * d[0] + p[1] * d[1] + p[2] * d[2];
                let disc = b * b - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2] - r * r);
                if disc < 0.0 {
                    return None;
                }
                let t = -b - disc.sqrt();
                (t > 0.0).then(|| {
                    let q = [p[0] + t * d[0], p[1] + t * d[1], p[2] + t * d[2]];
                    (t, [q[0] / r, q[1] / r, q[2] / r])
                })
            }
        }
    }
}

/// The scene kinds of this family.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    ParkingLot,
    Highway,
    RuralRoad,
    Garage,
}

impl Kind {
    pub const ALL: [Kind; 4] = [
        Kind::ParkingLot,
        Kind::Highway,
        Kind::RuralRoad,
        Kind::Garage,
    ];
    pub fn name(self) -> &'static str {
        match self {
            Kind::ParkingLot => "parking lot",
            Kind::Highway => "highway",
            Kind::RuralRoad => "rural road",
            Kind::Garage => "garage",
        }
    }
}

/// One scene: a ground plane (its surface by the lateral offset), an optional
/// ceiling, and objects; the ego drives along +x at `speed_mps`.
#[derive(Debug, Clone)]
pub struct Scene {
    pub kind: Kind,
    road_half_width_m: f32,
    road: Surface,
    verge: Surface,
    ceiling_m: Option<f32>,
    objects: Vec<Object>,
    pub speed_mps: f32,
    lane_y_m: f32,
}

const CONCRETE: Surface = surf(label::BUILDING, Material::Concrete, 0.35);
const BARRIER: Surface = surf(label::FENCE, Material::Concrete, 0.45);
const POLE: Surface = surf(label::POLE, Material::Metal, 0.5);
const TRUNK: Surface = surf(label::TRUNK, Material::Bark, 0.25);
const FOLIAGE: Surface = surf(label::VEGETATION, Material::Foliage, 0.45);
const GLASS: Surface = surf(label::CAR, Material::Glass, 0.08);
const TYRE: Surface = surf(label::CAR, Material::Rubber, 0.05);

fn car(objects: &mut Vec<Object>, rng: &mut Rng, x: f32, y: f32, along_x: bool) {
    let (l, w) = (rng.range(3.8, 5.0), rng.range(1.7, 1.95));
    let (hx, hy) = if along_x {
        (l / 2.0, w / 2.0)
    } else {
        (w / 2.0, l / 2.0)
    };
    let paint = match rng.next_u64() % 3 {
        0 => surf(label::CAR, Material::DarkPaint, rng.range(0.04, 0.12)),
        1 => surf(label::CAR, Material::BrightPaint, rng.range(0.5, 0.8)),
        _ => surf(label::CAR, Material::Metal, rng.range(0.3, 0.5)),
    };
    let body_h = rng.range(0.9, 1.1);
    objects.push(Object {
        shape: Shape::Box {
            min: [x - hx, y - hy, 0.3],
            max: [x + hx, y + hy, body_h],
        },
        surface: paint,
    });
    // Tyre band below the body, glass cabin above it.
    objects.push(Object {
        shape: Shape::Box {
            min: [x - hx * 0.9, y - hy * 0.98, 0.0],
            max: [x + hx * 0.9, y + hy * 0.98, 0.3],
        },
        surface: TYRE,
    });
    let cabin_h = body_h + rng.range(0.4, 0.6);
    let (cx, cy) = if along_x {
        (hx * 0.55, hy * 0.9)
    } else {
        (hx * 0.9, hy * 0.55)
    };
    objects.push(Object {
        shape: Shape::Box {
            min: [x - cx, y - cy, body_h],
            max: [x + cx, y + cy, cabin_h],
        },
        surface: GLASS,
    });
}

fn pole(objects: &mut Vec<Object>, x: f32, y: f32, r: f32, h: f32, surface: Surface) {
    objects.push(Object {
        shape: Shape::Cylinder {
            c: [x, y],
            r,
            z0: 0.0,
            z1: h,
        },
        surface,
    });
}

fn wall(objects: &mut Vec<Object>, min: [f32; 3], max: [f32; 3], surface: Surface) {
    objects.push(Object {
        shape: Shape::Box { min, max },
        surface,
    });
}

impl Scene {
    /// A scene of `kind` from `seed`, covering the drive from x = 0 to `length_m`.
    pub fn generate(kind: Kind, seed: u64, length_m: f32) -> Scene {
        let mut rng = Rng::new(seed.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ kind as u64);
        let mut o = Vec::new();
        let x0 = -90.0;
        let x1 = length_m + 90.0;
        let asphalt = surf(label::ROAD, Material::Asphalt, rng.range(0.08, 0.2));
        match kind {
            Kind::ParkingLot => {
                // Rows of parked cars across the lot, lamp posts, a low wall around.
                let mut x = x0;
                while x < x1 {
                    for side in [-1.0f32, 1.0] {
                        let y = side * rng.range(5.0, 7.0);
                        if rng.chance(0.7) {
                            car(&mut o, &mut rng, x, y, false);
                        }
                        let y2 = side * rng.range(12.0, 14.0);
                        if rng.chance(0.6) {
                            car(&mut o, &mut rng, x, y2, false);
                        }
                    }
                    x += rng.range(2.4, 3.2);
                }
                let mut x = x0;
                while x < x1 {
                    let y = rng.pick(&[-9.5f32, 9.5, -20.0, 20.0]);
                    pole(&mut o, x, y, 0.12, rng.range(6.0, 9.0), POLE);
                    x += rng.range(12.0, 25.0);
                }
                let d = rng.range(28.0, 40.0);
                wall(&mut o, [x0, d, 0.0], [x1, d + 0.3, 1.2], CONCRETE);
                wall(&mut o, [x0, -d - 0.3, 0.0], [x1, -d, 1.2], CONCRETE);
                Scene {
                    kind,
                    road_half_width_m: 60.0,
                    road: asphalt,
                    verge: asphalt,
                    ceiling_m: None,
                    objects: o,
                    speed_mps: rng.range(3.0, 8.0),
                    lane_y_m: 0.0,
                }
            }
            Kind::Highway => {
                // Concrete barriers at the road edges and the median, traffic in
                // the lanes, sign gantry poles, a sound wall behind the verge.
                let half = rng.range(7.0, 11.0);
                for y in [-half, half] {
                    wall(&mut o, [x0, y - 0.3, 0.0], [x1, y + 0.3, 0.8], BARRIER);
                }
                wall(
                    &mut o,
                    [x0, half + 1.5, 0.0],
                    [x1, half + 1.8, 0.8],
                    BARRIER,
                );
                let sound = half + rng.range(6.0, 15.0);
                wall(&mut o, [x0, sound, 0.0], [x1, sound + 0.4, 4.0], CONCRETE);
                let mut x = x0;
                while x < x1 {
                    let lane = rng.pick(&[-0.75f32, -0.25, 0.25, 0.75]) * half;
                    if lane.abs() > 1.5 {
                        car(&mut o, &mut rng, x, lane, true);
                    }
                    x += rng.range(8.0, 30.0);
                }
                let mut x = x0;
                while x < x1 {
                    pole(&mut o, x, half + 0.8, 0.15, 7.0, POLE);
                    x += rng.range(30.0, 60.0);
                }
                Scene {
                    kind,
                    road_half_width_m: half,
                    road: asphalt,
                    verge: surf(label::TERRAIN, Material::Grass, rng.range(0.2, 0.4)),
                    ceiling_m: None,
                    objects: o,
                    speed_mps: rng.range(15.0, 25.0),
                    lane_y_m: -0.25 * half,
                }
            }
            Kind::RuralRoad => {
                // A narrow road through grass, trees (trunk and crown), bushes,
                // a wooden fence, a few farm buildings.
                let half = rng.range(2.8, 3.8);
                let mut x = x0;
                while x < x1 {
                    let y = rng.pick(&[-1.0f32, 1.0]) * rng.range(half + 2.0, 25.0);
                    if rng.chance(0.5) {
                        let h = rng.range(3.0, 6.0);
                        pole(&mut o, x, y, rng.range(0.15, 0.35), h, TRUNK);
                        o.push(Object {
                            shape: Shape::Sphere {
                                c: [x, y, h + 1.0],
                                r: rng.range(1.5, 3.0),
                            },
                            surface: FOLIAGE,
                        });
                    } else {
                        let r = rng.range(0.6, 1.4);
                        o.push(Object {
                            shape: Shape::Sphere {
                                c: [x, y, r * 0.6],
                                r,
                            },
                            surface: FOLIAGE,
                        });
                    }
                    x += rng.range(3.0, 9.0);
                }
                // Cars parked at farm gates along the road.
                let mut x = x0 + rng.range(0.0, 20.0);
                while x < x1 {
                    let y = rng.pick(&[-1.0f32, 1.0]) * (half + 1.2);
                    car(&mut o, &mut rng, x, y, true);
                    x += rng.range(15.0, 40.0);
                }
                let fence_y = half + rng.range(1.0, 3.0);
                let wood = surf(label::FENCE, Material::Wood, 0.3);
                wall(&mut o, [x0, fence_y, 0.0], [x1, fence_y + 0.1, 1.1], wood);
                let mut x = x0 + rng.range(0.0, 40.0);
                while x < x1 {
                    let y = rng.pick(&[-1.0f32, 1.0]) * rng.range(20.0, 35.0);
                    let brick = surf(label::BUILDING, Material::Brick, 0.3);
                    wall(&mut o, [x, y - 5.0, 0.0], [x + 12.0, y + 5.0, 5.0], brick);
                    x += rng.range(50.0, 90.0);
                }
                Scene {
                    kind,
                    road_half_width_m: half,
                    road: asphalt,
                    verge: surf(label::TERRAIN, Material::Grass, rng.range(0.25, 0.45)),
                    ceiling_m: None,
                    objects: o,
                    speed_mps: rng.range(8.0, 16.0),
                    lane_y_m: -0.5 * half,
                }
            }
            Kind::Garage => {
                // Side walls, a ceiling, a grid of pillars, parked cars between.
                let half = rng.range(9.0, 14.0);
                for y in [-half - 0.4, half] {
                    wall(&mut o, [x0, y, 0.0], [x1, y + 0.4, 3.0], CONCRETE);
                }
                let spacing = rng.range(7.0, 9.0);
                let mut x = x0;
                while x < x1 {
                    for y in [-3.5f32, 3.5] {
                        wall(
                            &mut o,
                            [x - 0.3, y - 0.3, 0.0],
                            [x + 0.3, y + 0.3, 3.0],
                            CONCRETE,
                        );
                    }
                    for side in [-1.0f32, 1.0] {
                        for slot in 0..3 {
                            if rng.chance(0.6) {
                                let xs = x + 1.5 + 2.5 * slot as f32;
                                car(&mut o, &mut rng, xs, side * (half - 3.0), false);
                            }
                        }
                    }
                    x += spacing;
                }
                Scene {
                    kind,
                    road_half_width_m: 60.0,
                    road: surf(label::ROAD, Material::Concrete, rng.range(0.2, 0.35)),
                    verge: CONCRETE,
                    ceiling_m: Some(rng.range(2.6, 3.2)),
                    objects: o,
                    speed_mps: rng.range(2.0, 5.0),
                    lane_y_m: 0.0,
                }
            }
        }
    }

    /// Nearest hit of a ray from `o` along unit `d` within `max_m`, among the
    /// ground, the ceiling and `objects` (indices into the scene's objects).
    fn cast(
        &self,
        o: [f32; 3],
        d: [f32; 3],
        max_m: f32,
        objects: &[u32],
    ) -> Option<(f32, [f32; 3], Surface)> {
        let mut best: Option<(f32, [f32; 3], Surface)> = None;
        let mut take = |t: f32, n: [f32; 3], s: Surface| {
            if t > 0.0 && t <= max_m && best.is_none_or(|b| t < b.0) {
                best = Some((t, n, s));
            }
        };
        if d[2] < -1e-6 {
            let t = -o[2] / d[2];
            let y = o[1] + t * d[1];
            let s = if y.abs() <= self.road_half_width_m {
                self.road
            } else {
                self.verge
            };
            take(t, [0.0, 0.0, 1.0], s);
        }
        if let Some(h) = self.ceiling_m
            && d[2] > 1e-6
        {
            take((h - o[2]) / d[2], [0.0, 0.0, -1.0], CONCRETE);
        }
        for &i in objects {
            let obj = &self.objects[i as usize];
            if let Some((t, n)) = obj.hit(o, d) {
                take(t, n, obj.surface);
            }
        }
        best
    }
}

/// A randomised sensor: beams, spacing, columns, mounting height, cloud layout.
#[derive(Debug, Clone)]
pub struct Sensor {
    pub profile: SensorProfile,
    pub height_m: f32,
    pub organized: bool,
    pub ring_field: bool,
}

impl Sensor {
    /// `beams` lasers between a drawn top and bottom elevation, either evenly
    /// spaced or denser near the horizon.
    pub fn random(rng: &mut Rng, beams: usize) -> Sensor {
        let (top, bottom) = match beams {
            16 => (rng.range(10.0, 15.0), -rng.range(10.0, 15.0)),
            32 => (rng.range(8.0, 15.0), -rng.range(16.0, 30.0)),
            64 => (rng.range(2.0, 16.0), -rng.range(16.0, 26.0)),
            _ => (rng.range(10.0, 22.0), -rng.range(16.0, 22.0)),
        };
        let dense = rng.chance(0.5);
        let elevation_deg: Vec<f32> = (0..beams)
            .map(|i| {
                let u = i as f32 / (beams - 1) as f32;
                // Horizon-dense: a cubic ease that packs beams near the middle.
                let s = if dense {
                    let c = 2.0 * u - 1.0;
                    0.5 + 0.5 * (0.6 * c + 0.4 * c * c * c)
                } else {
                    u
                };
                top + (bottom - top) * s
            })
            .collect();
        let columns = match beams {
            16 => rng.pick(&[1024usize, 2048]),
            32 => rng.pick(&[1024usize, 1800]),
            64 => rng.pick(&[512usize, 1024]),
            _ => 512,
        };
        Sensor {
            profile: SensorProfile {
                name: format!("testgen-{beams}"),
                elevation_deg,
                azimuth_offset_deg: None,
                columns,
                min_range_m: rng.range(0.5, 2.0),
                max_range_m: rng.range(80.0, 120.0),
            },
            height_m: rng.range(1.2, 2.2),
            organized: rng.chance(0.5),
            ring_field: rng.chance(0.5),
        }
    }

    pub fn describe(&self) -> String {
        format!(
            "{} beams x {} ({:.1}..{:.1} deg, {:.2} m up, {}, {})",
            self.profile.beams(),
            self.profile.columns,
            self.profile.elevation_deg[0],
            self.profile.elevation_deg[self.profile.beams() - 1],
            self.height_m,
            if self.organized {
                "organized"
            } else {
                "unorganized"
            },
            if self.ring_field {
                "ring field"
            } else {
                "no ring field"
            },
        )
    }
}

/// Scans a side and their spacing in time.
pub const SCANS: u32 = 16;
const STRIDE_S: f32 = 0.3;

/// Ideal scan `index` of `scene` with `sensor`: one ray per pixel from the pose
/// at the scan start, each column timed within the 10 Hz sweep (starting straight
/// ahead, counter-clockwise).
pub fn cast_scan(scene: &Scene, sensor: &Sensor, index: u32) -> SimScan {
    let profile = &sensor.profile;
    let angles = profile.angle_grid();
    let (h, w) = (angles.height, angles.width);
    let t = index as f32 * STRIDE_S;
    let origin = [scene.speed_mps * t, scene.lane_y_m, sensor.height_m];
    // Cull: each object under the columns its footprint spans.
    let mut by_column: Vec<Vec<u32>> = vec![Vec::new(); w];
    let col_of = |a: f32| {
        let j = (std::f32::consts::PI - a) / std::f32::consts::TAU * w as f32;
        j.rem_euclid(w as f32) as usize % w
    };
    for (i, obj) in scene.objects.iter().enumerate() {
        let (c, r) = obj.footprint();
        let (dx, dy) = (c[0] - origin[0], c[1] - origin[1]);
        let dist = (dx * dx + dy * dy).sqrt();
        if dist - r > profile.max_range_m {
            continue;
        }
        if dist <= r + 0.5 {
            by_column.iter_mut().for_each(|v| v.push(i as u32));
            continue;
        }
        let a = dy.atan2(dx);
        let half = (r / dist).asin() + 2.0 * std::f32::consts::TAU / w as f32;
        let (ja, jb) = (col_of(a + half), col_of(a - half));
        let mut j = ja;
        loop {
            by_column[j].push(i as u32);
            if j == jb {
                break;
            }
            j = (j + 1) % w;
        }
    }
    let mut image = RangeImage::empty(angles);
    let n = h * w;
    let mut material = vec![Material::None; n];
    let mut incidence_rad = vec![0.0f32; n];
    let mut reflectivity = vec![0.0f32; n];
    let mut true_label = vec![0u32; n];
    let period = 0.1f32;
    let time_s: Vec<f32> = (0..n)
        .map(|k| {
            let a = image.angles.azimuth_rad[k];
            a.rem_euclid(std::f32::consts::TAU) / std::f32::consts::TAU * period
        })
        .collect();
    for k in 0..n {
        let d = image.angles.direction(k);
        let Some((t_hit, normal, s)) =
            scene.cast(origin, d, profile.max_range_m, &by_column[k % w])
        else {
            continue;
        };
        let cos_inc = (-(normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2])).clamp(0.0, 1.0);
        material[k] = s.material;
        incidence_rad[k] = cos_inc.acos();
        reflectivity[k] = s.reflectivity;
        true_label[k] = s.label;
        if t_hit < profile.min_range_m {
            continue;
        }
        image.range_m[k] = t_hit;
        image.xyz[k] = d.map(|c| c * t_hit);
        image.intensity[k] = intensity(s.reflectivity, cos_inc, t_hit);
        image.label[k] = s.label;
        image.point_index[k] = k as u32;
    }
    let true_range_m = image.range_m.clone();
    SimScan {
        image,
        material,
        incidence_rad,
        reflectivity,
        time_s,
        true_range_m,
        true_label,
        index,
        start_time_s: f64::from(t),
        pose: SensorPose {
            origin: rangegan_mcap::sim::geometry::v3(origin[0], origin[1], origin[2]),
            axes: [
                rangegan_mcap::sim::geometry::v3(1.0, 0.0, 0.0),
                rangegan_mcap::sim::geometry::v3(0.0, 1.0, 0.0),
                rangegan_mcap::sim::geometry::v3(0.0, 0.0, 1.0),
            ],
            velocity_mps: [scene.speed_mps, 0.0, 0.0],
            yaw_rate_rps: 0.0,
            yaw_rad: 0.0,
        },
        min_range_m: profile.min_range_m,
        max_range_m: profile.max_range_m,
    }
}

/// One left-out effect with parameters drawn across the ranges real sensors
/// show (the reference's physics catalogue), fitted to `sensor`'s geometry.
pub fn draw_effect(id: &str, rng: &mut Rng, sensor: &Sensor) -> Box<dyn Effect> {
    let el = &sensor.profile.elevation_deg;
    match id {
        "range_dropout" => Box::new(RangeDropout {
            enabled: true,
            range_50_m: rng.range(25.0, 60.0),
            softness: rng.range(0.15, 0.45),
        }),
        "incidence_dropout" => Box::new(IncidenceDropout {
            enabled: true,
            cos_50: rng.range(0.08, 0.25),
            softness: rng.range(0.1, 0.3),
        }),
        "beam_dropout" => Box::new(BeamDropout {
            enabled: true,
            rates: None,
            mean_rate: rng.range(0.05, 0.15),
            spread: rng.range(0.5, 1.0),
            beam_seed: rng.next_u64(),
            dead_beams: if rng.chance(0.3) {
                vec![(rng.next_u64() % el.len() as u64) as usize]
            } else {
                vec![]
            },
        }),
        "material_dropout" => {
            let dark = rng.range(0.25, 0.6);
            Box::new(MaterialDropout {
                enabled: true,
                drop_prob: BTreeMap::from([
                    (Material::Glass, rng.range(0.4, 0.9)),
                    (Material::DarkPaint, dark),
                    (Material::Rubber, dark),
                ]),
                drop_prob_by_class: BTreeMap::new(),
            })
        }
        "self_occlusion" => {
            // The ego's body behind the sensor: a rear sector over the bottom
            // 15-30 % of the beams.
            let half = rng.range(20.0, 45.0);
            let row = ((el.len() as f32) * rng.range(0.7, 0.85)) as usize;
            let centre = rng.pick(&[180.0f32, 0.0]);
            let (lo, hi) = if centre == 180.0 {
                (180.0 - half, -180.0 + half)
            } else {
                (-half, half)
            };
            Box::new(SelfOcclusion {
                enabled: true,
                sectors: vec![OcclusionSector {
                    azimuth_min_deg: lo,
                    azimuth_max_deg: hi,
                    elevation_max_deg: el[row.min(el.len() - 1)] + 0.01,
                    prob: rng.range(0.6, 1.0),
                }],
                boxes: vec![],
            })
        }
        "range_noise" => Box::new(RangeNoise {
            enabled: true,
            sigma0_m: rng.range(0.015, 0.06),
            k: rng.range(0.0, 0.001),
        }),
        "mixed_pixels" => Box::new(MixedPixels {
            enabled: true,
            prob: rng.range(0.3, 0.9),
            min_gap_m: rng.range(0.5, 1.5),
        }),
        "motion_distortion" => Box::new(MotionDistortion {
            enabled: true,
            scale: rng.range(0.5, 1.0),
        }),
        other => panic!("no generator for {other}"),
    }
}

/// One concealed pair and what it hides.
pub struct Pair {
    pub seed: u64,
    pub kind: Kind,
    pub sensor: Sensor,
    /// The left-out effects (real side only), with their parameters.
    pub truth: Vec<String>,
    pub truth_params: Vec<String>,
    pub sim: Vec<ScanFeatures>,
    pub real: Vec<ScanFeatures>,
    /// Global drop rates after concealment.
    pub drop_rate_sim: f64,
    pub drop_rate_real: f64,
    /// Where a left-out effect drops rays: the share of the real side's rays they dropped
    /// (its drop rate beside the same scans with the uniform dropout alone), how visible
    /// they are at all.
    pub effect_share: Option<f64>,
    /// Each left-out effect's own share of the real side's rays (the drop rate with the
    /// uniform dropout and that effect alone, beside the uniform dropout alone); None for
    /// effects that drop no rays.
    pub effect_shares: Vec<Option<f64>>,
}

fn cast(scene: &Scene, sensor: &Sensor) -> Vec<SimScan> {
    (0..SCANS).map(|i| cast_scan(scene, sensor, i)).collect()
}

fn applied(cast: &[SimScan], physics: &Physics, seed: u64) -> Vec<SimScan> {
    cast.iter()
        .map(|s| {
            let mut s = s.clone();
            physics.apply(&mut s, seed);
            s
        })
        .collect()
}

fn drop_rate(scans: &[SimScan]) -> f64 {
    scans
        .iter()
        .map(|s| 1.0 - s.keep_rate() as f64)
        .sum::<f64>()
        / scans.len() as f64
}

/// A scan as the diagnosis sees it: the cloud (organized or not, ring field or
/// not) projected onto the sensor's grid with the automatic strategy.
fn features(scan: &SimScan, sensor: &Sensor) -> ScanFeatures {
    let mut cloud = scan.to_scan(sensor.organized);
    if !sensor.ring_field {
        cloud.ring = None;
    }
    let strategy = choose_strategy(&cloud, &sensor.profile);
    let image = project(&cloud, &sensor.profile, strategy).expect("projection");
    ScanFeatures::from_image(&image, &FeatureOptions::default())
}

/// The pair `seed` with `effects` left out of the sim side (none: a null pair),
/// on a sensor with `beams` lasers. The real side's scene seed is `seed`, the
/// sim side's another one; the sim side's uniform dropout matches the global
/// drop rates. Both sides always carry a little uniform dropout (real sensors
/// drop some rays everywhere).
pub fn pair(seed: u64, effects: &[&str], beams: usize) -> Pair {
    pair_with(seed, effects, beams, None)
}

/// As [`pair`], the cloud organized or not as `organized` says (None: drawn).
pub fn pair_with(seed: u64, effects: &[&str], beams: usize, organized: Option<bool>) -> Pair {
    let mut rng = Rng::new(seed);
    let kind = rng.pick(&Kind::ALL);
    let mut sensor = Sensor::random(&mut rng, beams);
    if let Some(o) = organized {
        sensor.organized = o;
    }
    let length = 30.0 * STRIDE_S * SCANS as f32;
    let real_scene = Scene::generate(kind, seed, length);
    let sim_scene = Scene::generate(kind, seed ^ 0x5151_5151, length);
    let base = rng.range(0.005, 0.03);
    let uniform = || -> Box<dyn Effect> {
        Box::new(UniformDropout {
            enabled: true,
            prob: base,
        })
    };
    let mut real_effects = vec![uniform()];
    let mut truth_params = Vec::new();
    let mut drops = false;
    // Each effect is drawn again from the same stream to measure it alone.
    let effects_rng = rng.clone();
    for id in effects {
        let e = draw_effect(id, &mut rng, &sensor);
        truth_params.push(format!("{e:?}"));
        drops |= e.drops();
        real_effects.push(e);
    }
    let real_cast = cast(&real_scene, &sensor);
    let real = applied(
        &real_cast,
        &Physics {
            effects: real_effects,
        },
        seed,
    );
    let uniform_only = Physics {
        effects: vec![uniform()],
    };
    let r = drop_rate(&real);
    let uniform_rate = drop_rate(&applied(&real_cast, &uniform_only, seed));
    let effect_share = drops.then_some(r - uniform_rate);
    let mut again = effects_rng;
    let effect_shares = effects
        .iter()
        .map(|id| {
            let e = draw_effect(id, &mut again, &sensor);
            e.drops().then(|| {
                let alone = Physics {
                    effects: vec![uniform(), e],
                };
                drop_rate(&applied(&real_cast, &alone, seed)) - uniform_rate
            })
        })
        .collect();
    let sim_cast = cast(&sim_scene, &sensor);
    let ideal = applied(&sim_cast, &Physics::ideal(), seed ^ 1);
    let s0 = drop_rate(&ideal);
    let prob = ((r - s0).max(0.0) / (1.0 - s0)) as f32;
    let sim_physics = Physics {
        effects: vec![Box::new(UniformDropout {
            enabled: true,
            prob: prob.max(base),
        })],
    };
    let sim = applied(&sim_cast, &sim_physics, seed ^ 1);
    Pair {
        seed,
        kind,
        truth: effects.iter().map(|s| s.to_string()).collect(),
        truth_params,
        drop_rate_sim: drop_rate(&sim),
        drop_rate_real: r,
        effect_share,
        effect_shares,
        sim: sim.iter().map(|s| features(s, &sensor)).collect(),
        real: real.iter().map(|s| features(s, &sensor)).collect(),
        sensor,
    }
}

/// The evaluation's plan: every effect alone four times, six nulls, six pairs
/// of two and two of three effects (46 pairs), beams cycling through 16 / 32 /
/// 64 / 128.
pub fn plan(seed: u64) -> Vec<(u64, Vec<&'static str>, usize)> {
    let mut rng = Rng::new(seed);
    let mut cases: Vec<Vec<&'static str>> = Vec::new();
    for _ in 0..4 {
        cases.extend(EFFECTS.iter().map(|e| vec![*e]));
    }
    cases.extend((0..6).map(|_| vec![]));
    let distinct = |k: usize, rng: &mut Rng| {
        let mut v: Vec<&'static str> = Vec::new();
        while v.len() < k {
            let e = rng.pick(&EFFECTS);
            if !v.contains(&e) {
                v.push(e);
            }
        }
        v
    };
    for _ in 0..6 {
        cases.push(distinct(2, &mut rng));
    }
    for _ in 0..2 {
        cases.push(distinct(3, &mut rng));
    }
    let beams = [16usize, 32, 64, 128];
    cases
        .into_iter()
        .enumerate()
        .map(|(i, c)| {
            (
                seed.wrapping_mul(1000) + i as u64,
                c,
                beams[(i + i / 8) % 4],
            )
        })
        .collect()
}

/// The diagnosis of a pair as `diagnose` runs it (default options, neighbour
/// completion, the sim side ideal but for its uniform dropout).
pub fn diagnose_pair(p: &Pair) -> Diagnosis {
    diagnose(
        &p.sim,
        &p.real,
        &serde_json::Map::new(),
        "neighbour-fill",
        &DiagnoseOptions::default(),
    )
    .expect("diagnosis")
}

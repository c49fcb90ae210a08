//! The scene family (parking lot, highway with barriers, rural road with vegetation,
//! garage or tunnel), generated from a seed, and the nearest hit of a ray in a scene.

use rangegan_mcap::sim::{Material, label};

use super::Rng;
use super::shapes::{Object, Shape, Surface, surf};

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
    pub(super) objects: Vec<Object>,
    pub speed_mps: f32,
    pub(super) lane_y_m: f32,
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
    pub(super) fn cast(
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

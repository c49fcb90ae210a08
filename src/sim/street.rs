//! The street grid's pieces: cambered road strips and intersections, and each block's
//! curbs, sidewalks, street furniture, frontage (buildings, walls, fences, green) and
//! parked cars.

use std::f32::consts::{FRAC_PI_2, PI};

use super::builder::{Actor, Builder, TreeShape, car_template, pedestrian_template};
use super::geometry::{Primitive, Shape, Vec3, v3};
use super::material::surface as S;
use crate::util::rng::Rng;

/// The street grid's dimensions, drawn per seed.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    /// Street spacing along x and y (streets at `x = i * block_m[0]`, `y = k * block_m[1]`).
    pub block_m: [f32; 2],
    /// Half the carriageway width, curb to curb.
    pub road_half_width_m: f32,
    pub sidewalk_m: f32,
    pub curb_m: f32,
    /// Cross slope of the road from crown to gutter (e.g. 0.02 = 2 %).
    pub camber: f32,
    /// Global ground slope dz/dx, dz/dy.
    pub slope: [f32; 2],
    /// Lateral offset of a driving lane's centre from the street centreline.
    pub lane_offset_m: f32,
    /// Whether streets have parking lanes along the curbs.
    pub parking: bool,
}

impl Layout {
    pub fn ground_z(&self, x: f32, y: f32) -> f32 {
        self.slope[0] * x + self.slope[1] * y
    }
}

/// One side of a block: points are `origin + along * s + inward * u`.
pub(super) struct BlockSide {
    pub(super) origin: [f32; 2],
    pub(super) along: [f32; 2],
    pub(super) inward: [f32; 2],
    pub(super) len: f32,
    /// Free depth from the curb towards the block centre.
    pub(super) depth: f32,
}

impl BlockSide {
    pub(super) fn at(&self, s: f32, u: f32) -> [f32; 2] {
        [
            self.origin[0] + self.along[0] * s + self.inward[0] * u,
            self.origin[1] + self.along[1] * s + self.inward[1] * u,
        ]
    }
    pub(super) fn yaw(&self) -> f32 {
        self.along[1].atan2(self.along[0])
    }
}

/// A cambered road between two intersections: crown on the centreline, gutters at
/// the curbs. `start` is on the centreline, `dir` along the street.
pub(super) fn road_strip(
    b: &mut Builder,
    start: [f32; 2],
    dir: [f32; 2],
    len: f32,
    hw: f32,
    crown: f32,
) {
    let right = [dir[1], -dir[0]];
    let p = |s: f32, u: f32, z: f32| {
        v3(
            start[0] + dir[0] * s + right[0] * u,
            start[1] + dir[1] * s + right[1] * u,
            z,
        )
    };
    let n = (len / 5.0).ceil().max(1.0) as usize;
    for k in 0..n {
        let (s0, s1) = (len * k as f32 / n as f32, len * (k + 1) as f32 / n as f32);
        for side in [-1.0f32, 1.0] {
            b.quad(
                p(s0, 0.0, crown),
                p(s1, 0.0, crown),
                p(s1, side * hw, 0.0),
                p(s0, side * hw, 0.0),
                S::ROAD,
                0,
            );
        }
    }
}

/// An intersection square: crown along both centrelines, falling to the corners,
/// so it meets the cambered strips on all four sides.
pub(super) fn intersection(b: &mut Builder, x: f32, y: f32, hw: f32, crown: f32) {
    let c = v3(x, y, crown);
    let mids = [
        v3(x + hw, y, crown),
        v3(x, y + hw, crown),
        v3(x - hw, y, crown),
        v3(x, y - hw, crown),
    ];
    let corners = [
        v3(x + hw, y + hw, 0.0),
        v3(x - hw, y + hw, 0.0),
        v3(x - hw, y - hw, 0.0),
        v3(x + hw, y - hw, 0.0),
    ];
    for q in 0..4 {
        b.tri(c, mids[q], corners[q], S::ROAD, 0);
        b.tri(c, corners[q], mids[(q + 1) % 4], S::ROAD, 0);
    }
}

/// A block: raised slab (sidewalk ring, terrain inside), curbs, and per side its
/// furniture, frontage and parked cars.
pub(super) fn block(
    b: &mut Builder,
    rng: &mut Rng,
    layout: &Layout,
    r: [f32; 4],
    actors: &mut Vec<Actor>,
) {
    let [x0, y0, x1, y1] = r;
    let (curb, sw) = (layout.curb_m, layout.sidewalk_m);
    // Interior terrain, tiled.
    let (ix0, iy0, ix1, iy1) = (x0 + sw, y0 + sw, x1 - sw, y1 - sw);
    let (nx, ny) = (
        ((ix1 - ix0) / 6.0).ceil().max(1.0) as usize,
        ((iy1 - iy0) / 6.0).ceil().max(1.0) as usize,
    );
    for a in 0..nx {
        for c in 0..ny {
            let xa = ix0 + (ix1 - ix0) * a as f32 / nx as f32;
            let xb = ix0 + (ix1 - ix0) * (a + 1) as f32 / nx as f32;
            let ya = iy0 + (iy1 - iy0) * c as f32 / ny as f32;
            let yb = iy0 + (iy1 - iy0) * (c + 1) as f32 / ny as f32;
            b.quad(
                v3(xa, ya, curb),
                v3(xb, ya, curb),
                v3(xb, yb, curb),
                v3(xa, yb, curb),
                S::TERRAIN,
                0,
            );
        }
    }
    let sides = [
        BlockSide {
            origin: [x0, y0],
            along: [1.0, 0.0],
            inward: [0.0, 1.0],
            len: x1 - x0,
            depth: (y1 - y0) / 2.0,
        },
        BlockSide {
            origin: [x1, y0],
            along: [0.0, 1.0],
            inward: [-1.0, 0.0],
            len: y1 - y0,
            depth: (x1 - x0) / 2.0,
        },
        BlockSide {
            origin: [x1, y1],
            along: [-1.0, 0.0],
            inward: [0.0, -1.0],
            len: x1 - x0,
            depth: (y1 - y0) / 2.0,
        },
        BlockSide {
            origin: [x0, y1],
            along: [0.0, -1.0],
            inward: [1.0, 0.0],
            len: y1 - y0,
            depth: (x1 - x0) / 2.0,
        },
    ];
    for side in &sides {
        let at3 = |s: f32, u: f32, z: f32| {
            let p = side.at(s, u);
            v3(p[0], p[1], z)
        };
        // Half the streets have a grass verge between curb and sidewalk.
        let verge = if rng.chance(0.5) {
            rng.range(1.2, 3.0)
        } else {
            0.0
        };
        if verge > 0.0 {
            b.tiled_quad(
                at3(0.0, 0.0, curb),
                at3(side.len, 0.0, curb),
                at3(side.len, verge, curb),
                at3(0.0, verge, curb),
                5.0,
                S::TERRAIN,
                0,
            );
        }
        // Sidewalk strip (corners overlap the neighbouring strip: harmless) and curb face.
        let (u0, u1) = (verge, verge + sw);
        b.tiled_quad(
            at3(0.0, u0, curb),
            at3(side.len, u0, curb),
            at3(side.len, u1, curb),
            at3(0.0, u1, curb),
            5.0,
            S::SIDEWALK,
            0,
        );
        b.tiled_quad(
            at3(0.0, 0.0, 0.0),
            at3(side.len, 0.0, 0.0),
            at3(side.len, 0.0, curb),
            at3(0.0, 0.0, curb),
            5.0,
            S::CURB,
            0,
        );
        let wide = Layout {
            sidewalk_m: u1,
            ..layout.clone()
        };
        side_furniture(b, rng, &wide, side, actors);
        frontage(b, rng, &wide, side);
        if layout.parking {
            parked_cars(b, rng, side);
        }
    }
}

pub(super) fn side_furniture(
    b: &mut Builder,
    rng: &mut Rng,
    layout: &Layout,
    side: &BlockSide,
    actors: &mut Vec<Actor>,
) {
    let (curb, sw) = (layout.curb_m, layout.sidewalk_m);
    // Street trees.
    if rng.chance(0.85) {
        let mut s = rng.range(3.0, 8.0);
        while s < side.len - 3.0 {
            let p = side.at(s, 0.9);
            let inst = b.instance();
            b.tree(rng, (p[0], p[1], curb), &TreeShape::STREET, inst);
            s += rng.range(6.0, 12.0);
        }
    }
    // Street lights.
    let mut s = rng.range(2.0, 20.0);
    while s < side.len - 1.0 {
        let p = side.at(s, 0.4);
        let inst = b.instance();
        let h = rng.range(5.0, 8.0);
        b.cylinder(p[0], p[1], curb, rng.range(0.07, 0.13), h, S::POLE, inst);
        // The arm reaches out over the road.
        let arm = side.at(s, -0.8);
        let (yaw, zc) = (side.yaw() + FRAC_PI_2, curb + h);
        b.oriented_box(
            [(p[0] + arm[0]) / 2.0, (p[1] + arm[1]) / 2.0],
            [0.6, 0.06],
            yaw,
            [zc - 0.12, zc],
            [S::POLE; 5],
            inst,
        );
        s += rng.range(22.0, 40.0);
    }
    // Traffic signs near the corners, facing oncoming traffic.
    for s in [rng.range(2.0, 8.0), side.len - rng.range(2.0, 8.0)] {
        if !rng.chance(0.5) {
            continue;
        }
        let p = side.at(s, 0.35);
        let inst = b.instance();
        b.cylinder(p[0], p[1], curb, 0.035, 2.7, S::POLE, inst);
        let yaw = side.yaw();
        let centre = side.at(s, 0.3);
        b.oriented_box(
            centre,
            [0.32, 0.015],
            yaw + FRAC_PI_2,
            [curb + 2.0, curb + 2.65],
            [
                S::SIGN_FACE,
                S::SIGN_BACK,
                S::SIGN_BACK,
                S::SIGN_BACK,
                S::SIGN_BACK,
            ],
            inst,
        );
    }
    // Pedestrians: some stand, some walk along the sidewalk.
    let people = rng.index(((side.len / 25.0) as usize).max(1) + 1);
    for _ in 0..people {
        let mut tb = Builder::new([0.0; 2]);
        let inst = b.instance();
        pedestrian_template(rng, &mut tb, inst);
        let u = rng.range(0.5, (sw - 0.5).max(0.6));
        let walking = rng.chance(0.7);
        let forward = rng.chance(0.5);
        let (start, dir) = if forward {
            (side.at(1.0, u), side.along)
        } else {
            (side.at(side.len - 1.0, u), [-side.along[0], -side.along[1]])
        };
        // Lift the template onto the sidewalk.
        for p in &mut tb.prims {
            lift_template(p, curb);
        }
        actors.push(Actor {
            template: tb.prims,
            start,
            dir,
            speed_mps: if walking { rng.range(0.9, 1.7) } else { 0.0 },
            phase_m: rng.range(0.0, (side.len - 2.0).max(0.0)),
            span_m: (side.len - 2.0).max(0.0),
        });
    }
}

pub(super) fn lift_template(p: &mut Primitive, dz: f32) {
    let up = v3(0.0, 0.0, dz);
    p.shape = match p.shape {
        Shape::Triangle { p0, e1, e2 } => Shape::Triangle {
            p0: p0 + up,
            e1,
            e2,
        },
        Shape::Ellipsoid { centre, radii } => Shape::Ellipsoid {
            centre: centre + up,
            radii,
        },
        Shape::Cylinder {
            base,
            radius,
            height,
        } => Shape::Cylinder {
            base: base + up,
            radius,
            height,
        },
    };
}

/// What stands behind the sidewalk: a row of buildings, a wall or fence with
/// gardens, or open green with bushes and trees.
pub(super) fn frontage(b: &mut Builder, rng: &mut Rng, layout: &Layout, side: &BlockSide) {
    let (curb, sw) = (layout.curb_m, layout.sidewalk_m);
    let style = rng.uniform();
    let max_depth = (side.depth - sw - 1.0).max(2.0);
    let facades = [S::PLASTER, S::BRICK, S::CONCRETE_WALL];
    let buildings = |b: &mut Builder, rng: &mut Rng, setback: [f32; 2]| {
        let mut s = rng.range(1.0, 4.0);
        while s < side.len - 6.0 {
            let w = rng.range(8.0, 25.0).min(side.len - 2.0 - s);
            let setback = rng.range(setback[0], setback[1]);
            let depth = rng.range(8.0, 18.0).min(max_depth - setback);
            if depth < 4.0 || w < 4.0 {
                break;
            }
            let angle = if rng.chance(0.2) {
                rng.range(-0.35, 0.35)
            } else {
                0.0
            };
            // Keep rotated footprints off the sidewalk.
            let extra = (angle.abs().sin() * w / 2.0).max(angle.abs().sin() * depth / 2.0);
            let u = sw + setback + extra + depth / 2.0;
            let centre = side.at(s + w / 2.0, u);
            let yaw = side.yaw() + angle;
            let height = rng.range(4.0, 16.0);
            let facade = facades[rng.index(3)];
            let inst = b.instance();
            b.oriented_box(
                centre,
                [w / 2.0, depth / 2.0],
                yaw,
                [0.0, curb + height],
                [facade; 5],
                inst,
            );
            // Window bands per floor on the street-facing facade (local -y face).
            let (sn, cs) = yaw.sin_cos();
            let local = |lx: f32, ly: f32, z: f32| {
                v3(
                    centre[0] + cs * lx - sn * ly,
                    centre[1] + sn * lx + cs * ly,
                    z,
                )
            };
            let ly = -depth / 2.0 - 0.03;
            let hx = w / 2.0 * rng.range(0.4, 0.7);
            let mut floor = 0.0;
            while floor + 3.0 <= height {
                let (za, zb) = (curb + floor + 1.0, curb + floor + 2.2);
                b.quad(
                    local(-hx, ly, za),
                    local(hx, ly, za),
                    local(hx, ly, zb),
                    local(-hx, ly, zb),
                    S::WINDOW,
                    inst,
                );
                floor += 3.0;
            }
            s += w + if rng.chance(0.5) {
                rng.range(1.5, 8.0)
            } else {
                0.0
            };
        }
    };
    if style < 0.2 {
        buildings(b, rng, [1.0, 8.0]);
    } else if style < 0.6 {
        // Wall or fence along the property line, gardens and houses behind.
        let wall = rng.chance(0.4);
        let h = if wall {
            rng.range(0.8, 2.0)
        } else {
            rng.range(1.0, 1.8)
        };
        let thick = if wall { 0.2 } else { 0.05 };
        let surf = if wall { S::WALL } else { S::FENCE };
        let mut s = 0.5;
        while s < side.len - 1.0 {
            let run = rng.range(6.0, 25.0).min(side.len - 0.5 - s);
            let inst = b.instance();
            b.oriented_box(
                side.at(s + run / 2.0, sw + 0.3),
                [run / 2.0, thick / 2.0],
                side.yaw(),
                [0.0, curb + h],
                [surf; 5],
                inst,
            );
            s += run
                + if rng.chance(0.4) {
                    rng.range(3.0, 5.0)
                } else {
                    0.0
                };
        }
        let mut s = rng.range(2.0, 6.0);
        while s < side.len - 2.0 {
            let p = side.at(s, sw + rng.range(1.5, 4.0));
            let inst = b.instance();
            let r = rng.range(0.6, 1.6);
            b.ellipsoid(
                v3(p[0], p[1], curb + r * 0.6),
                v3(r, r, r * 0.8),
                S::BUSH,
                inst,
            );
            s += rng.range(2.0, 6.0);
        }
        buildings(b, rng, [8.0, 18.0]);
    } else {
        // Open green: hedges, bushes and trees.
        if rng.chance(0.5) {
            let p = side.at(side.len / 2.0, sw + 0.8);
            let along = side.along;
            let half = side.len / 2.0 - 3.0;
            let inst = b.instance();
            let radii = v3(
                (along[0].abs() * half).max(0.6),
                (along[1].abs() * half).max(0.6),
                0.9,
            );
            b.ellipsoid(v3(p[0], p[1], curb + 0.6), radii, S::HEDGE, inst);
        }
        let n = (side.len * max_depth / 50.0) as usize;
        for _ in 0..n {
            let p = side.at(
                rng.range(2.0, side.len - 2.0),
                sw + rng.range(2.5, max_depth),
            );
            let inst = b.instance();
            if rng.chance(0.5) {
                b.tree(rng, (p[0], p[1], curb), &TreeShape::YARD, inst);
            } else {
                let r = rng.range(0.5, 1.8);
                b.ellipsoid(
                    v3(p[0], p[1], curb + r * 0.5),
                    v3(r, r * rng.range(0.7, 1.3), r * 0.7),
                    S::BUSH,
                    inst,
                );
            }
        }
    }
}

/// Cars parked along the curb in the parking lane, with gaps.
pub(super) fn parked_cars(b: &mut Builder, rng: &mut Rng, side: &BlockSide) {
    let mut s = rng.range(2.0, 8.0);
    while s < side.len - 5.0 {
        if rng.chance(0.18) {
            let mut tb = Builder::new([0.0; 2]);
            let inst = b.instance();
            car_template(rng, &mut tb, inst);
            let p = side.at(s + 2.3, -rng.range(1.0, 1.25));
            let yaw = side.yaw() + if rng.chance(0.5) { 0.0 } else { PI } + rng.range(-0.04, 0.04);
            let (sn, cs) = yaw.sin_cos();
            let place = |q: Vec3| v3(p[0] + cs * q.x - sn * q.y, p[1] + sn * q.x + cs * q.y, q.z);
            for prim in tb.prims {
                match prim.shape {
                    Shape::Triangle { p0, e1, e2 } => b.tri(
                        place(p0),
                        place(p0 + e1),
                        place(p0 + e2),
                        prim.surface,
                        inst,
                    ),
                    Shape::Ellipsoid { centre, radii } => {
                        b.ellipsoid(place(centre), radii, prim.surface, inst)
                    }
                    Shape::Cylinder {
                        base,
                        radius,
                        height,
                    } => {
                        let q = place(base);
                        b.cylinder(q.x, q.y, q.z, radius, height, prim.surface, inst)
                    }
                }
            }
        }
        s += rng.range(5.0, 8.0);
    }
}

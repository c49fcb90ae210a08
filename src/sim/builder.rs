//! Scene geometry as primitives: a builder that places triangles, boxes, cylinders and
//! ellipsoids on the sloped ground, and the templates of cars, pedestrians, cyclists and
//! trees that scenes instance.

use super::geometry::{Primitive, Shape, Vec3, v3};
use super::material::surface as S;
use crate::util::rng::Rng;

/// Ranges (low, high) of a tree's random dimensions.
pub(super) struct TreeShape {
    pub(super) trunk_height_m: (f32, f32),
    pub(super) trunk_radius_m: (f32, f32),
    pub(super) crown_radius_m: (f32, f32),
    pub(super) crown_elongation: (f32, f32),
}

impl TreeShape {
    /// Street trees between the curb and the sidewalk: young, small crowns.
    pub(super) const STREET: TreeShape = TreeShape {
        trunk_height_m: (1.2, 2.4),
        trunk_radius_m: (0.1, 0.22),
        crown_radius_m: (1.4, 3.0),
        crown_elongation: (0.9, 1.4),
    };
    /// Trees in yards and verges behind the sidewalk.
    pub(super) const YARD: TreeShape = TreeShape {
        trunk_height_m: (1.5, 4.0),
        trunk_radius_m: (0.12, 0.3),
        crown_radius_m: (1.5, 4.0),
        crown_elongation: (0.8, 1.3),
    };
}

/// Collects primitives, applying the global slope to everything it places.
pub(super) struct Builder {
    pub(super) prims: Vec<Primitive>,
    pub(super) slope: [f32; 2],
    pub(super) next_instance: u16,
}

impl Builder {
    pub(super) fn new(slope: [f32; 2]) -> Self {
        Builder {
            prims: Vec::new(),
            slope,
            next_instance: 1,
        }
    }
    pub(super) fn instance(&mut self) -> u16 {
        let id = self.next_instance;
        self.next_instance = self.next_instance.checked_add(1).unwrap_or(1);
        id
    }
    pub(super) fn lift(&self, p: Vec3) -> Vec3 {
        v3(p.x, p.y, p.z + self.slope[0] * p.x + self.slope[1] * p.y)
    }
    pub(super) fn tri(&mut self, a: Vec3, b: Vec3, c: Vec3, surface: u16, instance: u16) {
        let (a, b, c) = (self.lift(a), self.lift(b), self.lift(c));
        self.prims.push(Primitive {
            shape: Shape::triangle(a, b, c),
            surface,
            instance,
        });
    }
    pub(super) fn quad(&mut self, a: Vec3, b: Vec3, c: Vec3, d: Vec3, surface: u16, instance: u16) {
        self.tri(a, b, c, surface, instance);
        self.tri(a, c, d, surface, instance);
    }
    /// A quad tiled into pieces at most `step` long along a-b, so BVH boxes stay tight.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn tiled_quad(
        &mut self,
        a: Vec3,
        b: Vec3,
        c: Vec3,
        d: Vec3,
        step: f32,
        surface: u16,
        instance: u16,
    ) {
        let n = (((b - a).length().max((c - d).length())) / step)
            .ceil()
            .max(1.0) as usize;
        for k in 0..n {
            let (u0, u1) = (k as f32 / n as f32, (k + 1) as f32 / n as f32);
            let p = |u: f32, from: Vec3, to: Vec3| from + (to - from) * u;
            self.quad(
                p(u0, a, b),
                p(u1, a, b),
                p(u1, d, c),
                p(u0, d, c),
                surface,
                instance,
            );
        }
    }
    /// Eight corners (bottom 0-3, top 4-7, counter-clockwise) with a surface per
    /// face: [front(+x), back, right(-y), left(+y), top]; the bottom is never seen.
    pub(super) fn hexahedron(&mut self, c: [Vec3; 8], faces: [u16; 5], instance: u16) {
        self.quad(c[1], c[2], c[6], c[5], faces[0], instance);
        self.quad(c[0], c[4], c[7], c[3], faces[1], instance);
        self.quad(c[0], c[1], c[5], c[4], faces[2], instance);
        self.quad(c[3], c[7], c[6], c[2], faces[3], instance);
        self.quad(c[4], c[5], c[6], c[7], faces[4], instance);
    }
    /// An upright box: footprint centre, half length/width along `yaw`, z range.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn oriented_box(
        &mut self,
        centre: [f32; 2],
        half: [f32; 2],
        yaw: f32,
        z: [f32; 2],
        faces: [u16; 5],
        instance: u16,
    ) {
        let (s, co) = yaw.sin_cos();
        let corner = |lx: f32, ly: f32, z: f32| {
            v3(
                centre[0] + co * lx - s * ly,
                centre[1] + s * lx + co * ly,
                z,
            )
        };
        let (hx, hy) = (half[0], half[1]);
        let c = [
            corner(-hx, -hy, z[0]),
            corner(hx, -hy, z[0]),
            corner(hx, hy, z[0]),
            corner(-hx, hy, z[0]),
            corner(-hx, -hy, z[1]),
            corner(hx, -hy, z[1]),
            corner(hx, hy, z[1]),
            corner(-hx, hy, z[1]),
        ];
        self.hexahedron(c, faces, instance);
    }
    #[allow(clippy::too_many_arguments)]
    pub(super) fn cylinder(
        &mut self,
        x: f32,
        y: f32,
        z0: f32,
        radius: f32,
        height: f32,
        surface: u16,
        instance: u16,
    ) {
        let base = self.lift(v3(x, y, z0));
        self.prims.push(Primitive {
            shape: Shape::Cylinder {
                base,
                radius,
                height,
            },
            surface,
            instance,
        });
    }
    /// A trunk and an ellipsoid crown standing at `(x, y, ground)`; the shape's ranges are
    /// drawn in the order trunk height, trunk radius, crown radius, crown elongation.
    pub(super) fn tree(
        &mut self,
        rng: &mut Rng,
        (x, y, ground): (f32, f32, f32),
        shape: &TreeShape,
        instance: u16,
    ) {
        let trunk_h = rng.range(shape.trunk_height_m.0, shape.trunk_height_m.1);
        let trunk_r = rng.range(shape.trunk_radius_m.0, shape.trunk_radius_m.1);
        self.cylinder(x, y, ground, trunk_r, trunk_h + 0.5, S::TRUNK, instance);
        let r = rng.range(shape.crown_radius_m.0, shape.crown_radius_m.1);
        let elongation = rng.range(shape.crown_elongation.0, shape.crown_elongation.1);
        self.ellipsoid(
            v3(x, y, ground + trunk_h + r * 0.9),
            v3(r, r, r * elongation),
            S::FOLIAGE,
            instance,
        );
    }

    pub(super) fn ellipsoid(&mut self, centre: Vec3, radii: Vec3, surface: u16, instance: u16) {
        let centre = self.lift(centre);
        self.prims.push(Primitive {
            shape: Shape::Ellipsoid { centre, radii },
            surface,
            instance,
        });
    }
}

/// Templates in the actor's local frame (x forward, ground at z = 0).
pub(super) fn car_template(rng: &mut Rng, b: &mut Builder, instance: u16) {
    let len = rng.range(3.9, 4.9);
    let wid = rng.range(1.7, 1.9);
    let tall = rng.chance(0.2); // SUVs and vans
    let paint = match rng.index(10) {
        0..=3 => S::CAR_DARK,
        4..=7 => S::CAR_BRIGHT,
        _ => S::CAR_MID,
    };
    let (hl, hw) = (len / 2.0, wid / 2.0);
    let body_top = if tall { 1.15 } else { 0.95 };
    let roof = body_top + if tall { 0.65 } else { rng.range(0.45, 0.55) };
    for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        let c = [sx * (hl - 0.75), sy * (hw - 0.12)];
        b.oriented_box(c, [0.31, 0.12], 0.0, [0.0, 0.64], [S::TYRE; 5], instance);
    }
    b.oriented_box(
        [0.0, 0.0],
        [hl, hw],
        0.0,
        [0.3, body_top],
        [paint; 5],
        instance,
    );
    // Cabin: a trapezoid prism; sides, windscreen and rear window are glass.
    let (front_lo, front_hi) = (hl - 1.1, hl - 1.8);
    let (rear_lo, rear_hi) = (-hl + 0.35, -hl + if tall { 0.45 } else { 0.9 });
    let (w_lo, w_hi) = (hw - 0.05, hw - 0.22);
    let c = [
        v3(rear_lo, -w_lo, body_top),
        v3(front_lo, -w_lo, body_top),
        v3(front_lo, w_lo, body_top),
        v3(rear_lo, w_lo, body_top),
        v3(rear_hi, -w_hi, roof),
        v3(front_hi, -w_hi, roof),
        v3(front_hi, w_hi, roof),
        v3(rear_hi, w_hi, roof),
    ];
    b.hexahedron(
        c,
        [
            S::CAR_GLASS,
            S::CAR_GLASS,
            S::CAR_GLASS,
            S::CAR_GLASS,
            paint,
        ],
        instance,
    );
    // Number plates (retro-reflective), just proud of the body.
    for sx in [1.0f32, -1.0] {
        let x = sx * (hl + 0.01);
        b.quad(
            v3(x, -0.26, 0.38),
            v3(x, 0.26, 0.38),
            v3(x, 0.26, 0.5),
            v3(x, -0.26, 0.5),
            S::PLATE,
            instance,
        );
    }
}

pub(super) fn pedestrian_template(rng: &mut Rng, b: &mut Builder, instance: u16) {
    let h = rng.range(1.55, 1.9);
    b.cylinder(
        0.0,
        0.0,
        0.0,
        rng.range(0.17, 0.24),
        h - 0.24,
        S::PERSON,
        instance,
    );
    b.ellipsoid(
        v3(0.0, 0.0, h - 0.12),
        v3(0.11, 0.11, 0.12),
        S::PERSON,
        instance,
    );
}

pub(super) fn cyclist_template(rng: &mut Rng, b: &mut Builder, instance: u16) {
    for x in [-0.55f32, 0.55] {
        b.oriented_box(
            [x, 0.0],
            [0.33, 0.03],
            0.0,
            [0.02, 0.68],
            [S::BICYCLE; 5],
            instance,
        );
    }
    b.oriented_box(
        [0.0, 0.0],
        [0.5, 0.03],
        0.0,
        [0.55, 0.9],
        [S::BICYCLE; 5],
        instance,
    );
    b.oriented_box(
        [0.45, 0.0],
        [0.04, 0.3],
        0.0,
        [0.95, 1.0],
        [S::BICYCLE; 5],
        instance,
    );
    let h = rng.range(1.6, 1.85);
    b.cylinder(-0.1, 0.0, 0.3, 0.09, 0.55, S::BICYCLIST, instance);
    b.cylinder(
        -0.05,
        0.0,
        0.85,
        0.18,
        h - 0.85 - 0.2,
        S::BICYCLIST,
        instance,
    );
    b.ellipsoid(
        v3(0.0, 0.0, h - 0.1),
        v3(0.11, 0.11, 0.12),
        S::BICYCLIST,
        instance,
    );
}

/// A moving thing: a local-frame mesh (x forward, z up from the ground) driven
/// along a straight line, wrapping within its span.
#[derive(Debug, Clone)]
pub struct Actor {
    pub(super) template: Vec<Primitive>,
    pub(super) start: [f32; 2],
    pub(super) dir: [f32; 2],
    pub(super) speed_mps: f32,
    pub(super) phase_m: f32,
    pub(super) span_m: f32,
}

impl Actor {
    pub(super) fn position(&self, t_s: f32) -> [f32; 2] {
        let s = if self.span_m > 0.0 {
            (self.phase_m + self.speed_mps * t_s).rem_euclid(self.span_m)
        } else {
            0.0
        };
        [
            self.start[0] + self.dir[0] * s,
            self.start[1] + self.dir[1] * s,
        ]
    }
}

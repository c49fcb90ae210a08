//! Procedural street scenes from a seed: a grid of streets (cambered roads, curbs,
//! raised sidewalks, a global slope), blocks with building rows at varying setbacks
//! and angles (glass window bands), walls, fences, hedges, trees, bushes, poles,
//! traffic signs, parked cars, and moving actors (cars, pedestrians, cyclists),
//! plus the ego route through it. Static geometry goes into one BVH built once;
//! moving actors are instanced into a small BVH per scan time.

use std::f32::consts::{FRAC_PI_2, PI};

use super::bvh::Bvh;
use super::geometry::{Primitive, Ray, Shape, Vec3, v3};
use super::material::{SURFACES, Surface, surface as S};
use super::rng::{Rng, key_hash, unit_f32};
use super::trajectory::{PlanarPose, Trajectory};

/// What to generate: the seed, and the drive the scene must cover.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneConfig {
    pub seed: u64,
    /// Ego speed along the route, m/s.
    pub speed_mps: f32,
    /// Length of the drive in seconds (sets the route length).
    pub duration_s: f32,
    /// Objects are generated out to this distance (plus a margin) from the route.
    pub max_range_m: f32,
    /// Height of the sensor's origin above the road (KITTI: 1.73 m).
    pub sensor_height_m: f32,
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig {
            seed: 0,
            speed_mps: 10.0,
            duration_s: 10.0,
            max_range_m: 80.0,
            sensor_height_m: 1.73,
        }
    }
}

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

/// A moving thing: a local-frame mesh (x forward, z up from the ground) driven
/// along a straight line, wrapping within its span.
#[derive(Debug, Clone)]
pub struct Actor {
    template: Vec<Primitive>,
    start: [f32; 2],
    dir: [f32; 2],
    speed_mps: f32,
    phase_m: f32,
    span_m: f32,
}

impl Actor {
    fn position(&self, t_s: f32) -> [f32; 2] {
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

/// A first hit of a ray in the scene.
#[derive(Debug, Clone, Copy)]
pub struct SceneHit {
    pub t: f32,
    /// Unit surface normal, facing the ray's origin.
    pub normal: Vec3,
    pub surface: Surface,
    pub instance: u16,
}

/// A generated scene: layout, ego route, static BVH and moving actors.
#[derive(Debug, Clone)]
pub struct Scene {
    pub config: SceneConfig,
    pub layout: Layout,
    pub trajectory: Trajectory,
    static_bvh: Bvh,
    actors: Vec<Actor>,
}

/// Collects primitives, applying the global slope to everything it places.
/// Ranges (low, high) of a tree's random dimensions.
struct TreeShape {
    trunk_height_m: (f32, f32),
    trunk_radius_m: (f32, f32),
    crown_radius_m: (f32, f32),
    crown_elongation: (f32, f32),
}

impl TreeShape {
    /// Street trees between the curb and the sidewalk: young, small crowns.
    const STREET: TreeShape = TreeShape {
        trunk_height_m: (1.2, 2.4),
        trunk_radius_m: (0.1, 0.22),
        crown_radius_m: (1.4, 3.0),
        crown_elongation: (0.9, 1.4),
    };
    /// Trees in yards and verges behind the sidewalk.
    const YARD: TreeShape = TreeShape {
        trunk_height_m: (1.5, 4.0),
        trunk_radius_m: (0.12, 0.3),
        crown_radius_m: (1.5, 4.0),
        crown_elongation: (0.8, 1.3),
    };
}

struct Builder {
    prims: Vec<Primitive>,
    slope: [f32; 2],
    next_instance: u16,
}

impl Builder {
    fn new(slope: [f32; 2]) -> Self {
        Builder {
            prims: Vec::new(),
            slope,
            next_instance: 1,
        }
    }
    fn instance(&mut self) -> u16 {
        let id = self.next_instance;
        self.next_instance = self.next_instance.checked_add(1).unwrap_or(1);
        id
    }
    fn lift(&self, p: Vec3) -> Vec3 {
        v3(p.x, p.y, p.z + self.slope[0] * p.x + self.slope[1] * p.y)
    }
    fn tri(&mut self, a: Vec3, b: Vec3, c: Vec3, surface: u16, instance: u16) {
        let (a, b, c) = (self.lift(a), self.lift(b), self.lift(c));
        self.prims.push(Primitive {
            shape: Shape::triangle(a, b, c),
            surface,
            instance,
        });
    }
    fn quad(&mut self, a: Vec3, b: Vec3, c: Vec3, d: Vec3, surface: u16, instance: u16) {
        self.tri(a, b, c, surface, instance);
        self.tri(a, c, d, surface, instance);
    }
    /// A quad tiled into pieces at most `step` long along a-b, so BVH boxes stay tight.
    #[allow(clippy::too_many_arguments)]
    fn tiled_quad(
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
    fn hexahedron(&mut self, c: [Vec3; 8], faces: [u16; 5], instance: u16) {
        self.quad(c[1], c[2], c[6], c[5], faces[0], instance);
        self.quad(c[0], c[4], c[7], c[3], faces[1], instance);
        self.quad(c[0], c[1], c[5], c[4], faces[2], instance);
        self.quad(c[3], c[7], c[6], c[2], faces[3], instance);
        self.quad(c[4], c[5], c[6], c[7], faces[4], instance);
    }
    /// An upright box: footprint centre, half length/width along `yaw`, z range.
    #[allow(clippy::too_many_arguments)]
    fn oriented_box(
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
    fn cylinder(
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
    fn tree(
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

    fn ellipsoid(&mut self, centre: Vec3, radii: Vec3, surface: u16, instance: u16) {
        let centre = self.lift(centre);
        self.prims.push(Primitive {
            shape: Shape::Ellipsoid { centre, radii },
            surface,
            instance,
        });
    }
}

/// Templates in the actor's local frame (x forward, ground at z = 0).
fn car_template(rng: &mut Rng, b: &mut Builder, instance: u16) {
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

fn pedestrian_template(rng: &mut Rng, b: &mut Builder, instance: u16) {
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

fn cyclist_template(rng: &mut Rng, b: &mut Builder, instance: u16) {
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

/// One side of a block: points are `origin + along * s + inward * u`.
struct BlockSide {
    origin: [f32; 2],
    along: [f32; 2],
    inward: [f32; 2],
    len: f32,
    /// Free depth from the curb towards the block centre.
    depth: f32,
}

impl BlockSide {
    fn at(&self, s: f32, u: f32) -> [f32; 2] {
        [
            self.origin[0] + self.along[0] * s + self.inward[0] * u,
            self.origin[1] + self.along[1] * s + self.inward[1] * u,
        ]
    }
    fn yaw(&self) -> f32 {
        self.along[1].atan2(self.along[0])
    }
}

impl Scene {
    pub fn generate(config: SceneConfig) -> Scene {
        let seed = config.seed;
        let mut rng = Rng::new(seed, 1);
        let road_half_width_m = rng.range(3.6, 6.2);
        let layout = Layout {
            block_m: [rng.range(70.0, 130.0), rng.range(60.0, 110.0)],
            road_half_width_m,
            sidewalk_m: rng.range(2.0, 4.0),
            curb_m: rng.range(0.1, 0.18),
            camber: rng.range(0.01, 0.025),
            slope: [rng.range(-0.03, 0.03), rng.range(-0.03, 0.03)],
            lane_offset_m: 1.7,
            parking: road_half_width_m >= 5.0,
        };
        let length = config.speed_mps.max(0.0) * config.duration_s.max(0.0);
        let trajectory = Trajectory::on_grid(
            &mut Rng::new(seed, 2),
            layout.block_m,
            layout.lane_offset_m,
            8.0,
            length,
            config.speed_mps,
        );
        let margin = config.max_range_m + 25.0;
        let route: Vec<[f32; 2]> = sample_route(&trajectory, 4.0);
        let near = |x0: f32, y0: f32, x1: f32, y1: f32| {
            route.iter().any(|p| {
                let dx = (x0 - p[0]).max(p[0] - x1).max(0.0);
                let dy = (y0 - p[1]).max(p[1] - y1).max(0.0);
                dx * dx + dy * dy <= margin * margin
            })
        };
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for p in &route {
            for a in 0..2 {
                lo[a] = lo[a].min(p[a] - margin);
                hi[a] = hi[a].max(p[a] + margin);
            }
        }
        let [bx, by] = layout.block_m;
        let (i0, i1) = ((lo[0] / bx).floor() as i32, (hi[0] / bx).ceil() as i32);
        let (k0, k1) = ((lo[1] / by).floor() as i32, (hi[1] / by).ceil() as i32);
        let hw = layout.road_half_width_m;
        let mut b = Builder::new(layout.slope);
        let mut srng = Rng::new(seed, 3);
        let mut actors = Vec::new();

        // Roads: street segments between intersections, and the intersections.
        let crown = layout.camber * hw;
        for i in i0..=i1 {
            for k in k0..=k1 {
                let (x, y) = (i as f32 * bx, k as f32 * by);
                if near(x - hw, y - hw, x + hw, y + hw) {
                    intersection(&mut b, x, y, hw, crown);
                }
                // Street along x from this node to the next, and along y.
                if i < i1 && near(x + hw, y - hw, x + bx - hw, y + hw) {
                    road_strip(&mut b, [x + hw, y], [1.0, 0.0], bx - 2.0 * hw, hw, crown);
                }
                if k < k1 && near(x - hw, y + hw, x + hw, y + by - hw) {
                    road_strip(&mut b, [x, y + hw], [0.0, 1.0], by - 2.0 * hw, hw, crown);
                }
            }
        }
        // Blocks.
        for i in i0..i1 {
            for k in k0..k1 {
                let (x0, y0) = (i as f32 * bx + hw, k as f32 * by + hw);
                let (x1, y1) = ((i + 1) as f32 * bx - hw, (k + 1) as f32 * by - hw);
                if !near(x0, y0, x1, y1) {
                    continue;
                }
                block(&mut b, &mut srng, &layout, [x0, y0, x1, y1], &mut actors);
            }
        }
        // Moving cars and cyclists along whole street lines, never in the ego's
        // own lane direction on a street it drives.
        let ego_uses = |horizontal: bool, line: i32, positive: bool| {
            trajectory.street_segments.iter().any(|(a, c)| {
                if horizontal {
                    a[1] == c[1] && a[1] == line && ((c[0] > a[0]) == positive)
                } else {
                    a[0] == c[0] && a[0] == line && ((c[1] > a[1]) == positive)
                }
            })
        };
        let mut lines = Vec::new();
        for k in k0..=k1 {
            lines.push((
                true,
                k,
                [i0 as f32 * bx, k as f32 * by],
                (i1 - i0) as f32 * bx,
            ));
        }
        for i in i0..=i1 {
            lines.push((
                false,
                i,
                [i as f32 * bx, k0 as f32 * by],
                (k1 - k0) as f32 * by,
            ));
        }
        for (horizontal, line, start, span) in lines {
            for positive in [true, false] {
                let along = match (horizontal, positive) {
                    (true, true) => [1.0, 0.0],
                    (true, false) => [-1.0, 0.0],
                    (false, true) => [0.0, 1.0],
                    (false, false) => [0.0, -1.0],
                };
                let right = [along[1], -along[0]];
                let origin = if positive {
                    start
                } else {
                    [start[0] + along[0] * -span, start[1] + along[1] * -span]
                };
                let in_lane =
                    |offset: f32| [origin[0] + right[0] * offset, origin[1] + right[1] * offset];
                if !ego_uses(horizontal, line, positive) {
                    let cars = (span / 120.0 * srng.range(0.0, 2.0)).round() as usize;
                    for _ in 0..cars {
                        let mut tb = Builder::new([0.0; 2]);
                        let inst = b.instance();
                        car_template(&mut srng, &mut tb, inst);
                        actors.push(Actor {
                            template: tb.prims,
                            start: in_lane(layout.lane_offset_m),
                            dir: along,
                            speed_mps: srng.range(5.0, 14.0),
                            phase_m: srng.range(0.0, span),
                            span_m: span,
                        });
                    }
                }
                if !ego_uses(horizontal, line, positive) && srng.chance(0.35) {
                    let offset = if layout.parking { hw - 2.6 } else { hw - 0.8 };
                    let mut tb = Builder::new([0.0; 2]);
                    let inst = b.instance();
                    cyclist_template(&mut srng, &mut tb, inst);
                    actors.push(Actor {
                        template: tb.prims,
                        start: in_lane(offset),
                        dir: along,
                        speed_mps: srng.range(3.0, 6.0),
                        phase_m: srng.range(0.0, span),
                        span_m: span,
                    });
                }
            }
        }
        let static_bvh = Bvh::build(b.prims);
        Scene {
            config,
            layout,
            trajectory,
            static_bvh,
            actors,
        }
    }

    /// Number of static primitives (for reports).
    pub fn static_primitives(&self) -> usize {
        self.static_bvh.prims.len()
    }

    pub fn actor_count(&self) -> usize {
        self.actors.len()
    }

    /// The moving actors placed at time `t_s`, within `radius_m` of `centre`.
    pub fn dynamic_bvh(&self, t_s: f32, centre: [f32; 2], radius_m: f32) -> Bvh {
        let mut prims = Vec::new();
        for actor in &self.actors {
            let p = actor.position(t_s);
            if (p[0] - centre[0]).hypot(p[1] - centre[1]) > radius_m + 5.0 {
                continue;
            }
            let (s, c) = actor.dir[1].atan2(actor.dir[0]).sin_cos();
            let z = self.layout.ground_z(p[0], p[1]);
            let place = |q: Vec3| v3(p[0] + c * q.x - s * q.y, p[1] + s * q.x + c * q.y, q.z + z);
            for prim in &actor.template {
                let shape = match prim.shape {
                    Shape::Triangle { p0, e1, e2 } => {
                        Shape::triangle(place(p0), place(p0 + e1), place(p0 + e2))
                    }
                    Shape::Ellipsoid { centre, radii } => Shape::Ellipsoid {
                        centre: place(centre),
                        radii,
                    },
                    Shape::Cylinder {
                        base,
                        radius,
                        height,
                    } => Shape::Cylinder {
                        base: place(base),
                        radius,
                        height,
                    },
                };
                prims.push(Primitive { shape, ..*prim });
            }
        }
        Bvh::build(prims)
    }

    /// First hit along `ray` (unit direction) closer than `t_max`, in the static
    /// scene and in `dynamic`. `ray_key` seeds the free path inside porous media.
    pub fn cast(&self, dynamic: &Bvh, ray: &Ray, t_max: f32, ray_key: u64) -> Option<SceneHit> {
        let mut best = self
            .static_bvh
            .nearest(ray, 1e-4, t_max, |p, h| {
                accept_hit(&self.static_bvh, ray_key, 0, p, h)
            })
            .map(|h| (h, &self.static_bvh));
        let limit = best.map_or(t_max, |(h, _)| h.hit.t);
        if let Some(h) = dynamic.nearest(ray, 1e-4, limit, |p, h| {
            accept_hit(dynamic, ray_key, 1, p, h)
        }) {
            best = Some((h, dynamic));
        }
        best.map(|(h, bvh)| {
            let prim = &bvh.prims[h.prim as usize];
            let n = h.hit.normal;
            let normal = if n.dot(ray.dir) > 0.0 { -n } else { n };
            SceneHit {
                t: h.hit.t,
                normal,
                surface: SURFACES[prim.surface as usize],
                instance: prim.instance,
            }
        })
    }

    /// Ego pose at time `t_s`, with the ground height under it.
    pub fn ego_pose(&self, t_s: f32) -> (PlanarPose, f32) {
        let p = self.trajectory.pose_at(t_s);
        let crown =
            self.layout.camber * (self.layout.road_half_width_m - self.layout.lane_offset_m);
        (p, self.layout.ground_z(p.x, p.y) + crown)
    }
}

/// Distance at which a ray really stops on primitive `prim`: the surface for solid
/// shapes; inside porous media (tree crowns) after an exponential free path keyed
/// by the ray, or nowhere (None) if that lies beyond the exit.
fn accept_hit(
    bvh: &Bvh,
    ray_key: u64,
    salt: u64,
    prim: u32,
    hit: &super::geometry::ShapeHit,
) -> Option<f32> {
    let surface = &SURFACES[bvh.prims[prim as usize].surface as usize];
    if surface.mean_free_path_m <= 0.0 {
        return Some(hit.t);
    }
    let u = unit_f32(key_hash(&[ray_key, salt, prim as u64])).max(1e-7);
    let t = hit.t - surface.mean_free_path_m * u.ln();
    (t < hit.t_exit).then_some(t)
}

fn sample_route(traj: &Trajectory, step: f32) -> Vec<[f32; 2]> {
    let n = (traj.length_m() / step).ceil() as usize + 1;
    (0..=n)
        .map(|k| {
            let p = traj.pose_at_arc(k as f32 * step);
            [p.x, p.y]
        })
        .collect()
}

/// A cambered road between two intersections: crown on the centreline, gutters at
/// the curbs. `start` is on the centreline, `dir` along the street.
fn road_strip(b: &mut Builder, start: [f32; 2], dir: [f32; 2], len: f32, hw: f32, crown: f32) {
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
fn intersection(b: &mut Builder, x: f32, y: f32, hw: f32, crown: f32) {
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
fn block(b: &mut Builder, rng: &mut Rng, layout: &Layout, r: [f32; 4], actors: &mut Vec<Actor>) {
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

fn side_furniture(
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

fn lift_template(p: &mut Primitive, dz: f32) {
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
fn frontage(b: &mut Builder, rng: &mut Rng, layout: &Layout, side: &BlockSide) {
    let (curb, sw) = (layout.curb_m, layout.sidewalk_m);
    let style = rng.unit();
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
fn parked_cars(b: &mut Builder, rng: &mut Rng, side: &BlockSide) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenes_are_reproducible_and_vary_with_the_seed() {
        let cfg = |seed| SceneConfig {
            seed,
            duration_s: 3.0,
            ..Default::default()
        };
        let a = Scene::generate(cfg(5));
        let b = Scene::generate(cfg(5));
        let c = Scene::generate(cfg(6));
        assert_eq!(a.static_primitives(), b.static_primitives());
        assert_eq!(a.layout, b.layout);
        assert_ne!(a.layout, c.layout);
        assert!(a.static_primitives() > 1000, "{}", a.static_primitives());
        assert!(a.actor_count() > 0);
    }

    #[test]
    fn ground_below_the_ego_is_road_at_sensor_height() {
        let scene = Scene::generate(SceneConfig {
            seed: 3,
            duration_s: 2.0,
            ..Default::default()
        });
        let (pose, z) = scene.ego_pose(0.0);
        let dynamic = scene.dynamic_bvh(0.0, [pose.x, pose.y], 80.0);
        let origin = v3(pose.x + 4.0, pose.y, z + 1.73);
        let hit = scene
            .cast(&dynamic, &Ray::new(origin, v3(0.0, 0.0, -1.0)), 100.0, 0)
            .unwrap();
        assert_eq!(hit.surface.label, super::super::material::label::ROAD);
        assert!((hit.t - 1.73).abs() < 0.1, "{}", hit.t);
        assert!(hit.normal.z > 0.99);
    }
}

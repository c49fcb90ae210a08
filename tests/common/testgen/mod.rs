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
//!
//! The parts: [`rng`] (the seeded stream), [`shapes`] (surfaces and the analytic
//! primitives a ray hits), [`scene`] (the scene family and the nearest hit in a
//! scene), [`sensor`] (randomised sensors and the ideal scan they cast), [`effects`]
//! (the left-out effects drawn for a sensor) and [`pairs`] (concealed pairs, the
//! evaluation's plan and their diagnosis).
#![allow(dead_code)]

mod effects;
mod pairs;
mod rng;
mod scene;
mod sensor;
mod shapes;

// The names the includers use, each only some of them (`tests/diagnose.rs`,
// `examples/diagnose_eval.rs`).
#[allow(unused_imports)]
pub use effects::{EFFECTS, draw_effect};
#[allow(unused_imports)]
pub use pairs::{Pair, diagnose_pair, pair, pair_on, pair_with, plan};
#[allow(unused_imports)]
pub use rng::Rng;
#[allow(unused_imports)]
pub use scene::{Kind, Scene};
#[allow(unused_imports)]
pub use sensor::{SCANS, Sensor, cast_scan};

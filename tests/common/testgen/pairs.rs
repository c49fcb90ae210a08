//! Concealed sim/real pairs: both sides cast, the left-out effects on the real side, the
//! sim side's uniform dropout matching the drop rates, the features the diagnosis sees;
//! the evaluation's plan of pairs and the diagnosis of one.

use rangegan_mcap::diagnose::features::{FeatureOptions, ScanFeatures};
use rangegan_mcap::diagnose::{DiagnoseOptions, Diagnosis, diagnose};
use rangegan_mcap::lidar::project;
use rangegan_mcap::lidar::projection::choose_strategy;
use rangegan_mcap::lidar::sweep::Seam;
use rangegan_mcap::physics::dropout::UniformDropout;
use rangegan_mcap::physics::{Effect, Physics};
use rangegan_mcap::sim::SimScan;

use super::sensor::STRIDE_S;
use super::sensor::cloud;
use super::{EFFECTS, Kind, Rng, SCANS, Scene, Sensor, cast_scan, draw_effect};

/// One concealed pair and what it hides.
pub struct Pair {
    pub seed: u64,
    pub kind: Kind,
    pub sensor: Sensor,
    /// The real side's ego speed, m/s (the diagnosis is not told it).
    pub real_speed_mps: f32,
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
    /// Where the pair hides motion distortion: how many of the real side's seam steps (a
    /// row's first- and last-fired returns) it moved by 10 cm or more, with every other
    /// effect left out. Motion moves only surfaces that face it, so over open road it can
    /// leave nothing at the seam to see.
    pub motion_seam_steps: Option<usize>,
}

/// Seam steps of `cast` (a row's first- and last-fired returns, both kept) whose last return
/// `effect` alone moves by 10 cm or more.
fn moved_seam_steps(cast: &[SimScan], effect: Box<dyn Effect>, seed: u64) -> usize {
    let moved = applied(
        cast,
        &Physics {
            effects: vec![effect],
        },
        seed,
    );
    cast.iter()
        .zip(&moved)
        .map(|(before, after)| {
            let (h, w) = (before.image.height, before.image.width);
            let by_time = |k: &usize, m: &usize| before.time_s[*k].total_cmp(&before.time_s[*m]);
            let first = (0..w).min_by(by_time).unwrap_or(0);
            let last = (0..w).max_by(by_time).unwrap_or(0);
            (0..h)
                .filter(|row| {
                    let (a, b) = (row * w + first, row * w + last);
                    before.is_return(a)
                        && before.is_return(b)
                        && (after.image.range_m[b] - before.image.range_m[b]).abs() >= 0.1
                })
                .count()
        })
        .sum()
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

/// A scan as the diagnosis sees it: the cloud as the sensor's driver writes it (organized
/// or not, ring and time fields or not) projected onto the sensor's grid with the
/// automatic strategy, and its seam found as `diagnose` finds it.
fn features(scan: &SimScan, sensor: &Sensor) -> ScanFeatures {
    let cloud = cloud(scan, sensor);
    let strategy = choose_strategy(&cloud, &sensor.profile);
    let image = project(&cloud, &sensor.profile, strategy).expect("projection");
    let mut f = ScanFeatures::from_image(&image, &FeatureOptions::default());
    f.seam = Seam::find(&cloud, &image);
    f
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
    pair_on(seed, effects, beams, |sensor| {
        if let Some(o) = organized {
            sensor.organized = o;
        }
    })
}

/// As [`pair`], the drawn sensor changed by `setup` (how its driver writes the cloud, where
/// its sweep starts).
pub fn pair_on(seed: u64, effects: &[&str], beams: usize, setup: impl Fn(&mut Sensor)) -> Pair {
    let mut rng = Rng::new(seed);
    let kind = rng.pick(&Kind::ALL);
    let mut sensor = Sensor::random(&mut rng, beams);
    setup(&mut sensor);
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
    let mut again = effects_rng.clone();
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
    let motion_seam_steps = effects
        .iter()
        .position(|id| *id == "motion_distortion")
        .map(|i| {
            let mut again = effects_rng.clone();
            let drawn: Vec<Box<dyn Effect>> = (effects[..=i].iter())
                .map(|id| draw_effect(id, &mut again, &sensor))
                .collect();
            let motion = drawn.into_iter().last().expect("the motion effect");
            moved_seam_steps(&real_cast, motion, seed)
        });
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
        motion_seam_steps,
        real_speed_mps: real_scene.speed_mps,
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

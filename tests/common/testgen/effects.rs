//! The catalogue effects the diagnosis has a candidate for, and each one drawn with
//! parameters across the ranges real sensors show.

use std::collections::BTreeMap;

use rangegan_mcap::physics::Effect;
use rangegan_mcap::physics::dropout::{
    BeamDropout, IncidenceDropout, MaterialDropout, OcclusionSector, RangeDropout, SelfOcclusion,
};
use rangegan_mcap::physics::perturb::{MixedPixels, MotionDistortion, RangeNoise};
use rangegan_mcap::sim::Material;

use super::{Rng, Sensor};

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
            speed_mps: None,
        }),
        other => panic!("no generator for {other}"),
    }
}

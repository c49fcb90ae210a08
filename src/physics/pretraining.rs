//! Simulated range images for pretraining the GAN. The ~470 real KITTI scans are too few
//! for a discriminator not to memorise them; the simulator makes as many distinct scenes as
//! asked. Each scene is a procedural street drive ray-cast with the sensor's profile (KITTI's
//! HDL-64E unless another is given),
//! with the `realistic` physics whose strengths are drawn per scene (so the ray-drop output
//! x_n sees varied drop patterns, not one fixed simulator), and a randomised ego speed and
//! sensor height. Everything is keyed by (seed, scene, scan): the same arguments give the
//! same images on any number of threads.

use rayon::prelude::*;

use super::{PhysicsConfig, Preset};
use crate::lidar::SensorProfile;
use crate::model::data::{DepthRange, RangeDataset};
use crate::sim::{SceneConfig, Simulator};
use crate::util::rng::{key_hash, uniform};

/// What to simulate.
#[derive(Debug, Clone, PartialEq)]
pub struct PretrainingSet {
    /// Images in total.
    pub scans: usize,
    /// Images per scene, taken half a second apart along the drive.
    pub scans_per_scene: usize,
    /// The sensor ray-cast, at the images' columns; its valid range sets the units.
    pub profile: SensorProfile,
    pub seed: u64,
}

impl Default for PretrainingSet {
    fn default() -> Self {
        Self {
            scans: 10_000,
            scans_per_scene: 10,
            profile: SensorProfile::kitti_hdl64e().with_columns(512),
            seed: 0x5157,
        }
    }
}

/// Time between two images of one scene: far enough apart that they differ.
const SCAN_SPACING: u32 = 5;

impl PretrainingSet {
    /// Simulates the set (in parallel over scenes) as network-unit images.
    pub fn build(&self, progress: impl Fn(usize) + Sync) -> RangeDataset {
        let profile = &self.profile;
        let per_scene = self.scans_per_scene.max(1);
        let scenes = self.scans.div_ceil(per_scene);
        let images: Vec<Vec<f32>> = (0..scenes)
            .into_par_iter()
            .map(|scene| {
                let n = per_scene.min(self.scans - scene * per_scene);
                let images = self.scene_images(scene as u64, n, profile);
                progress(n);
                images
            })
            .collect();
        RangeDataset::from_images(profile.clone(), profile.angle_grid(), images.concat())
    }

    fn scene_images(&self, scene: u64, n: usize, profile: &SensorProfile) -> Vec<f32> {
        let key = |what: u64| [self.seed, scene, what];
        let scene_seed = key_hash(&key(0));
        let config = SceneConfig {
            seed: scene_seed,
            speed_mps: 15.0 * uniform(&key(1)),
            duration_s: (n as u32 * SCAN_SPACING) as f32 * 0.1 + 1.0,
            sensor_height_m: 1.73 + 0.15 * (uniform(&key(2)) - 0.5),
            ..Default::default()
        };
        let sim = Simulator::new(config, profile.clone());
        let physics = randomised_realistic(profile.beams(), scene_seed).effects();
        let units = DepthRange::of(profile);
        let mut out = Vec::with_capacity(n * profile.angle_grid().len());
        for i in 0..n as u32 {
            let mut scan = sim.scan(i * SCAN_SPACING);
            physics.apply(&mut scan, scene_seed);
            out.extend(units.to_network(&scan.image.range_m));
        }
        out
    }
}

/// The `realistic` preset with every effect's strength scaled by a factor drawn from `seed`
/// (log-uniform, 1/2 to 2 for drop rates), so pretraining covers the range of real sensors.
pub fn randomised_realistic(beams: usize, seed: u64) -> PhysicsConfig {
    let factor =
        |what: u64, spread: f32| -> f32 { spread.powf(2.0 * uniform(&[seed, 0xfac7, what]) - 1.0) };
    let mut c = Preset::Realistic.config_for_beams(beams);
    if let Some(b) = c.beam_dropout.as_mut()
        && let Some(rates) = b.rates.as_mut()
    {
        let f = factor(1, 2.0);
        rates.iter_mut().for_each(|r| *r = (*r * f).min(1.0));
    }
    if let Some(r) = c.range_dropout.as_mut() {
        r.range_50_m *= factor(2, 1.6);
    }
    if let Some(i) = c.incidence_dropout.as_mut() {
        i.cos_50 = (i.cos_50 * factor(3, 3.0)).min(0.5);
    }
    if let Some(m) = c.material_dropout.as_mut() {
        let f = factor(4, 2.0);
        m.drop_prob
            .values_mut()
            .for_each(|p| *p = (*p * f).min(1.0));
    }
    if let Some(u) = c.uniform_dropout.as_mut() {
        u.prob = (u.prob * factor(5, 2.0)).min(1.0);
    }
    if let Some(o) = c.self_occlusion.as_mut() {
        // Other cars, other mounts: the blind spots' depth varies by a few degrees.
        let shift = 3.0 * (2.0 * uniform(&[seed, 0xfac7, 6]) - 1.0);
        o.sectors
            .iter_mut()
            .for_each(|s| s.elevation_max_deg += shift);
    }
    if let Some(n) = c.range_noise.as_mut() {
        n.sigma0_m *= factor(7, 2.0);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pretraining_set_is_deterministic_varied_and_in_network_units() {
        let set = PretrainingSet {
            scans: 5,
            scans_per_scene: 2,
            profile: SensorProfile::kitti_hdl64e().with_columns(64),
            seed: 9,
        };
        let a = set.build(|_| {});
        assert_eq!((a.len(), a.height, a.width), (5, 64, 64));
        assert_eq!(a, set.build(|_| {}));
        assert_eq!(a.profile, set.profile);
        assert!(a.images.iter().all(|v| (-1.0..=1.0).contains(v)));
        // Images differ (other scenes, other times) and have returns and drops.
        assert_ne!(a.image(0), a.image(1));
        assert_ne!(a.image(0), a.image(2));
        for i in 0..a.len() {
            let returns = a.image(i).iter().filter(|&&v| v > -1.0).count();
            assert!(returns > a.image(i).len() / 2 && returns < a.image(i).len());
        }
    }

    /// Another sensor's set is ray-cast on its beams and in its range: an Ouster's 0.3 m
    /// returns are returns, not drops.
    #[test]
    fn a_set_renders_the_sensor_it_is_given() {
        let profile = SensorProfile::builtin("os1-32")
            .expect("os1-32")
            .with_columns(128);
        let set = PretrainingSet {
            scans: 2,
            scans_per_scene: 2,
            profile: profile.clone(),
            seed: 3,
        };
        let a = set.build(|_| {});
        assert_eq!((a.height, a.width), (32, 128));
        assert_eq!(a.angles, profile.angle_grid());
        assert_eq!(a.depth_range(), DepthRange::of(&profile));
        let returns = a.images.iter().filter(|&&v| v > -1.0).count();
        assert!(
            returns > a.images.len() / 3,
            "{returns} of {}",
            a.images.len()
        );
    }

    #[test]
    fn randomised_physics_varies_by_seed_and_stays_valid() {
        let a = randomised_realistic(64, 1);
        let b = randomised_realistic(64, 2);
        assert_ne!(a, b);
        for c in [&a, &b] {
            c.validate("randomised", Some(64)).expect("valid physics");
        }
    }
}

//! Completion of dropped pixels for the Sim2Real diagnosis: real dropped
//! rays have no geometry, so before incidence and edges can be computed they are
//! completed, either by the cheap neighbour fill of `features` or by the
//! range-image GAN: each scan is auto-decoded (`crate::decode`, `fast` quality,
//! seeded from its topic and log time), the decoded scene rendered on the scan's
//! own grid, and its completed depth x_d used for the dropped pixels of the lower
//! half that no measured surface spans (a hole bridged by one surface keeps that
//! geometry; above, where a drop mostly met nothing, the neighbour fill stays).

use rayon::prelude::*;

use super::features::{FeatureOptions, ScanFeatures};
use crate::decode::{Decoder, PreparedGrid, Rendered};
use crate::lidar::RangeImage;

/// How dropped pixels get their geometry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Completion {
    /// Mean range of the nearest returns (`ScanFeatures::from_image`).
    Neighbour,
    /// The GAN's completed depth x_d from auto-decoding.
    Gan,
}

impl Completion {
    /// The name `report.json` gives (`inputs.completion`).
    pub fn name(self) -> &'static str {
        match self {
            Completion::Neighbour => "neighbour-fill",
            Completion::Gan => "gan",
        }
    }
}

/// Features of a recording's scans and which scans fell back to the neighbour fill.
#[derive(Debug, Clone)]
pub struct Completed {
    pub features: Vec<ScanFeatures>,
    /// (scan index, why) for every scan the GAN could not decode.
    pub fallbacks: Vec<(usize, String)>,
}

/// Auto-decodes one scan and renders the decoded scene on the scan's own grid.
/// `grid` must be `decoder.prepare(&image.angles)`.
pub fn gan_render(
    decoder: &Decoder,
    grid: &PreparedGrid,
    image: &RangeImage,
    seed: u64,
) -> anyhow::Result<Rendered> {
    let decoded = decoder.decode(image, seed)?;
    if image.angles == *decoder.model_grid() {
        return Ok(decoded.model);
    }
    Ok(decoded.render_prepared(grid))
}

/// [`gan_render`] of every scan, rayon over scans (each decode runs on one thread,
/// so the results do not depend on the thread count), mapped by `f`; a scan that
/// cannot be decoded gives the reason.
pub fn par_gan_render<T: Send>(
    decoder: &Decoder,
    images: &[RangeImage],
    seeds: &[u64],
    f: impl Fn(&RangeImage, Rendered) -> T + Sync,
) -> Vec<Result<T, String>> {
    assert_eq!(images.len(), seeds.len(), "one seed per scan");
    let first = images.first().map(|img| decoder.prepare(&img.angles));
    images
        .par_iter()
        .zip(seeds)
        .map(|(img, &seed)| {
            let own;
            let grid = match &first {
                Some(g) if g.grid == img.angles => g,
                _ => {
                    own = decoder.prepare(&img.angles);
                    &own
                }
            };
            gan_render(decoder, grid, img, seed)
                .map(|r| f(img, r))
                .map_err(|e| e.to_string())
        })
        .collect()
}

/// Features with neighbour fill (`Completion::Neighbour`), rayon over scans.
pub fn neighbour_features(images: &[RangeImage], options: &FeatureOptions) -> Vec<ScanFeatures> {
    images
        .par_iter()
        .map(|img| ScanFeatures::from_image(img, options))
        .collect()
}

/// Features with GAN completion, rayon over scans (each decode runs on one
/// thread, so the result does not depend on the thread count). `seeds[i]` seeds
/// scan i (use `crate::decode::scan_seed(topic, log_time)`). A scan that cannot be
/// decoded (e.g. no return on the model grid) is completed by the neighbour fill
/// and listed in `fallbacks`.
pub fn gan_features(
    decoder: &Decoder,
    images: &[RangeImage],
    seeds: &[u64],
    options: &FeatureOptions,
) -> Completed {
    let results = par_gan_render(decoder, images, seeds, |img, r| {
        ScanFeatures::from_image_completed(img, Some(&r.depth_m), options)
    });
    let mut out = Completed {
        features: Vec::with_capacity(results.len()),
        fallbacks: Vec::new(),
    };
    for (i, (result, img)) in results.into_iter().zip(images).enumerate() {
        match result {
            Ok(f) => out.features.push(f),
            Err(why) => {
                out.features.push(ScanFeatures::from_image(img, options));
                out.fallbacks.push((i, why));
            }
        }
    }
    out
}

/// A `fast` decoder of the shipped weights with `tune_steps` pivotal-tuning steps
/// (0 or 2), shared by the tests.
#[cfg(test)]
pub(crate) fn test_decoder(tune_steps: usize) -> &'static Decoder {
    use std::sync::OnceLock;
    static DECODERS: [OnceLock<Decoder>; 2] = [OnceLock::new(), OnceLock::new()];
    let slot = match tune_steps {
        0 => &DECODERS[0],
        2 => &DECODERS[1],
        n => panic!("no shared test decoder with {n} tuning steps"),
    };
    slot.get_or_init(|| {
        let device = burn::tensor::Device::flex();
        let mut opts = crate::decode::DecodeOptions::new(crate::decode::Quality::Fast);
        opts.schedule.set_tune_steps(tune_steps);
        Decoder::new(
            crate::model::weights::Model::shipped(&device).expect("shipped model"),
            opts,
        )
        .expect("decoder")
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decode::scan_seed;
    use crate::diagnose::features::simulated_images_with;
    use crate::physics::dropout::UniformDropout;

    /// Two simulated HDL-64E scans with 20 % of the rays dropped.
    fn scans() -> Vec<RangeImage> {
        let profile = crate::lidar::SensorProfile::kitti_hdl64e().with_columns(512);
        simulated_images_with(
            &profile,
            41,
            2,
            vec![Box::new(UniformDropout {
                enabled: true,
                prob: 0.2,
            })],
        )
    }

    /// Range and incidence bits, edges, classes and kept flags of one scan.
    type Bits = (Vec<u32>, Vec<u32>, Vec<u8>, Vec<u32>, Vec<bool>);

    /// Every feature as bits (NaN compares equal to NaN).
    fn bits(scans: &[ScanFeatures]) -> Vec<Bits> {
        let b = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        scans
            .iter()
            .map(|f| {
                (
                    b(&f.range_m),
                    b(&f.incidence_rad),
                    f.edge_px.clone(),
                    f.class.clone(),
                    f.kept.clone(),
                )
            })
            .collect()
    }

    fn in_pool<R: Send>(threads: usize, op: impl FnOnce() -> R + Send) -> R {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(op)
    }

    #[test]
    fn gan_completion_fills_dropped_pixels_differently_and_deterministically() {
        let mut images = scans();
        // A wide hole down to the bottom row, which no surface spans.
        for img in &mut images {
            for i in img.height - 20..img.height {
                for j in 100..140 {
                    img.range_m[i * img.width + j] = 0.0;
                }
            }
        }
        let seeds: Vec<u64> = (0..images.len() as u64)
            .map(|i| scan_seed("/sim", 100 * i))
            .collect();
        let options = FeatureOptions::default();
        let decoder = test_decoder(2);
        let gan = in_pool(1, || gan_features(decoder, &images, &seeds, &options));
        assert!(gan.fallbacks.is_empty(), "{:?}", gan.fallbacks);
        let neighbour = neighbour_features(&images, &options);
        let (mut dropped, mut differ) = (0usize, 0usize);
        for ((g, n), img) in gan.features.iter().zip(&neighbour).zip(&images) {
            assert_eq!(g.kept, n.kept);
            assert_eq!(g.class, n.class, "classes come from the neighbours");
            for k in 0..g.len() {
                if g.kept[k] {
                    assert_eq!(g.range_m[k], img.range_m[k], "measured range kept");
                    continue;
                }
                let lower = k / g.width >= g.height / 2;
                if lower {
                    // Every dropped pixel of the lower half has geometry.
                    assert!(g.range_m[k].is_finite() && g.range_m[k] > 0.0, "k={k}");
                    assert!(
                        g.incidence_rad[k].is_nan()
                            || (0.0..=std::f32::consts::FRAC_PI_2).contains(&g.incidence_rad[k])
                    );
                }
                if lower && n.range_m[k].is_finite() && g.range_m[k].is_finite() {
                    dropped += 1;
                    let rel = (g.range_m[k] - n.range_m[k]).abs() / n.range_m[k];
                    differ += usize::from(rel > 0.01);
                }
            }
            let finite = g.incidence_rad.iter().filter(|a| a.is_finite()).count();
            assert!(finite as f64 > 0.5 * g.len() as f64, "{finite} finite");
            assert!(g.edge_px.iter().all(|e| *e <= options.max_edge_px));
        }
        assert!(dropped > 1000, "{dropped} dropped pixels compared");
        // Holes that one surface spans keep its geometry under both; the GAN answers
        // the rest of the lower half (the wide hole, gaps between surfaces), agreeing
        // with the fill's ground within 1 % on part of it.
        assert!(
            differ as f64 > 0.05 * dropped as f64,
            "GAN and neighbour fill differ on {differ} of {dropped} dropped pixels"
        );
        // Deterministic, whatever the thread count.
        let again = in_pool(2, || gan_features(decoder, &images, &seeds, &options));
        assert!(bits(&gan.features) == bits(&again.features));
    }

    #[test]
    fn an_undecodable_scan_falls_back_to_neighbour_fill() {
        let mut images = scans();
        images.truncate(1);
        images[0].range_m.fill(0.0);
        let options = FeatureOptions::default();
        let done = gan_features(test_decoder(0), &images, &[7], &options);
        assert_eq!(done.fallbacks.len(), 1);
        assert_eq!(done.fallbacks[0].0, 0);
        assert!(bits(&done.features) == bits(&neighbour_features(&images, &options)));
    }
}

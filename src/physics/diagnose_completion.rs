//! Completion of dropped pixels for the Sim2Real diagnosis (issue 6): real dropped
//! rays have no geometry, so before incidence and edges can be computed they are
//! completed, either by the cheap neighbour fill of `diagnose_features` or by the
//! range-image GAN: each scan is auto-decoded (`crate::decode`, `fast` quality,
//! seeded from its topic and log time), the decoded scene rendered on the scan's
//! own grid, and its completed depth x_d used for the dropped pixels.

use rayon::prelude::*;

use super::diagnose_features::{FeatureOptions, ScanFeatures};
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

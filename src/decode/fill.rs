//! What the upsampled, other-sensor and restored grids hold ([`Fill`]): the decoded scene's
//! own rendering, or the observation interpolated onto the grid (nearest, bilinear,
//! edge-aware, or guided by the decoded scene), completed by the rendering where no
//! observed return reaches. Chosen by measurement on held-out KITTI (BENCHMARKS.md,
//! "Guided upsampling and restoration", "A learned correction of restored rows").

use super::hole_fill::{COMPLETION_REACH, HoleFill};
use super::row_fill::{RowFill, rows_image};
use super::{Decoded, PreparedGrid, Rendered, Sparsify};
use crate::lidar::holes;
use crate::lidar::{
    AngleGrid, Guide, Interpolation, RangeImage, ScatterFill, SurfaceRule, fill_scattered,
    fill_scattered_where, resample_by_surface, resample_image,
};

/// How a grid other than the observed one is filled.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum Fill {
    /// Measured returns kept; a new pixel interpolated only from the neighbouring returns on
    /// its own surface ([`SurfaceRule`]): across a trusted depth edge (adjacent pixels) the
    /// nearest return's surface, else the blend; inverse depth within a surface. From
    /// scattered returns: an inverse-depth plane where one explains the returns around the
    /// pixel, else the side of a depth edge the pixel lies in.
    EdgeAware,
    /// As edge-aware (as guided in the completed scan), then each row restored between two kept beams (`--restore-lines`) moved
    /// along its ray by a small network that reads the kept returns around it
    /// ([`super::row_fill`], trained on KITTI): whether a pixel between beams at different
    /// depths lies on the near surface or the far one. In the completed scan, each dropped
    /// ray is moved by another ([`super::hole_fill`]), which also reads the decoded scene.
    Learned,
    /// The same as edge-aware, but the decoded scene may pick the surface where its depth
    /// clearly agrees with one surface rather than with the blend.
    Guided,
    /// Bilinear between rows and columns; inverse-distance weighting for scattered points.
    Bilinear,
    /// The nearest observed return.
    Nearest,
    /// The decoded scene's completed depth x_d everywhere.
    Gan,
}

impl Fill {
    /// The best measured (BENCHMARKS.md).
    pub const DEFAULT: Fill = Fill::Learned;

    pub fn name(self) -> &'static str {
        match self {
            Fill::Learned => "learned",
            Fill::Guided => "guided",
            Fill::EdgeAware => "edge-aware",
            Fill::Bilinear => "bilinear",
            Fill::Nearest => "nearest",
            Fill::Gan => "gan",
        }
    }
}

impl Default for Fill {
    fn default() -> Self {
        Fill::DEFAULT
    }
}

/// `source` resampled onto `target.grid` by `fill`, guided by `guide_source` (on the source
/// grid) and `target.depth_m`; 0 where no observed return reaches.
fn resample(
    source: &RangeImage,
    guide_source: &[f32],
    target: &Rendered,
    fill: Fill,
    rule: &SurfaceRule,
) -> Vec<f32> {
    let grid = &target.grid;
    let out = match fill {
        Fill::Gan => return target.depth_m.clone(),
        Fill::Nearest => resample_image(source, grid, Interpolation::Nearest),
        Fill::Bilinear => resample_image(source, grid, Interpolation::Bilinear),
        Fill::EdgeAware | Fill::Learned => resample_by_surface(source, grid, rule, None),
        Fill::Guided => resample_by_surface(
            source,
            grid,
            rule,
            Some(Guide {
                target_m: &target.depth_m,
                source_m: guide_source,
            }),
        ),
    };
    out.range_m
}

/// How scattered returns are filled by `fill`, `guide` (the rendering on the same grid)
/// picking the surface at a depth edge for guided fills ([`Fill::Gan`]: as guided).
fn scatter_fill<'a>(fill: Fill, guide: &'a [f32], rule: &SurfaceRule) -> ScatterFill<'a> {
    match fill {
        Fill::Nearest => ScatterFill::Nearest,
        Fill::Bilinear => ScatterFill::Idw,
        Fill::EdgeAware | Fill::Learned => ScatterFill::Surfaces {
            guide: None,
            guide_jump: rule.guide_jump,
        },
        Fill::Guided | Fill::Gan => ScatterFill::Surfaces {
            guide: Some(guide),
            guide_jump: rule.guide_jump,
        },
    }
}

/// The completed scan on its own grid, `rendered` being the decoded scene there: each
/// measured return of `observed` as measured (at any range the sensor gives), each dropped
/// ray within [`COMPLETION_REACH`] steps of a return filled from the returns around it by
/// `fill` (guided by the rendering, as on the model grid), and the rendering x_d farther in;
/// [`Fill::Learned`] then moves each dropped ray's depth by the learned hole fill
/// ([`HoleFill`]). [`Fill::Gan`] gives the rendering everywhere.
pub fn complete_observed(observed: &RangeImage, rendered: Rendered, fill: Fill) -> Rendered {
    completed(&observed.range_m, &observed.angles, rendered, fill)
}

/// The fill that completes dropped rays near returns for `fill` (`learned` fills as
/// `guided`, then corrects); `None` for [`Fill::Gan`], which fills nothing.
fn completion_fill(fill: Fill) -> Option<Fill> {
    match fill {
        Fill::Gan => None,
        Fill::Learned => Some(Fill::Guided),
        other => Some(other),
    }
}

/// Each dropped ray of `observed` (on `angles`) within [`COMPLETION_REACH`] steps of a
/// return (`distance`, [`holes::distance_to_returns`]) filled by `how`, guided by the
/// rendering `guide`; 0 farther in.
fn fill_near_returns(
    observed: &[f32],
    angles: &AngleGrid,
    guide: &[f32],
    how: Fill,
    distance: &[u32],
) -> Vec<f32> {
    let how = scatter_fill(how, guide, &SurfaceRule::default());
    fill_scattered_where(observed, angles, how, |k| distance[k] <= COMPLETION_REACH)
}

/// [`complete_observed`] of the depths `observed` on `angles`.
fn completed(observed: &[f32], angles: &AngleGrid, rendered: Rendered, fill: Fill) -> Rendered {
    let Some(how) = completion_fill(fill) else {
        return rendered;
    };
    let size = (angles.height, angles.width);
    let distance = holes::distance_to_returns(observed, size.0, size.1);
    let values = fill_near_returns(observed, angles, &rendered.depth_m, how, &distance);
    if fill != Fill::Learned {
        return complete(rendered, &values);
    }
    let x_d = rendered.depth_m.clone();
    let mut out = complete(rendered, &values);
    let images = (observed, &out.depth_m[..], &x_d[..]);
    out.depth_m = HoleFill::shipped().refine(images, &distance, size);
    out
}

/// `rendered`'s grid (denser than `source`'s, or another sensor's) filled from the scan
/// `source` by `fill`, guided by `guide_source` (the rendering on `source`'s grid) and the
/// rendering itself; the rendering where no observed return reaches. [`Fill::Gan`] gives
/// the rendering.
pub fn fill_from(
    source: &RangeImage,
    guide_source: &[f32],
    rendered: Rendered,
    fill: Fill,
) -> Rendered {
    if fill == Fill::Gan {
        return rendered;
    }
    let values = resample(
        source,
        guide_source,
        &rendered,
        fill,
        &SurfaceRule::default(),
    );
    complete(rendered, &values)
}

/// The rendering `r` with `values` wherever they are set (> 0).
fn complete(mut r: Rendered, values: &[f32]) -> Rendered {
    for (d, v) in r.depth_m.iter_mut().zip(values) {
        if *v > 0.0 {
            *d = *v;
        }
    }
    r
}

impl Decoded {
    /// The model-grid depth restored from the observation the decode saw (after
    /// `--restore-*`; observed pixels keep their depth exactly) by `fill`, 0 where no observed
    /// return reaches; the full observation when decoding was not sparse. [`Fill::Gan`]
    /// gives the rendering x_d.
    pub fn interpolate_restored(&self, fill: Fill, rule: &SurfaceRule) -> Vec<f32> {
        let grid = &self.model.grid;
        match (fill, self.restore) {
            (Fill::Gan, _) => self.model.depth_m.clone(),
            (_, None) => self.observed_m.clone(),
            (_, Some(Sparsify::Lines(n))) => {
                let kept = Sparsify::kept_rows(n, grid.height);
                let source = rows_image(grid, &self.observed_m, &kept);
                let guide_source = rows_image(grid, &self.model.depth_m, &kept).range_m;
                let filled = resample(&source, &guide_source, &self.model, fill, rule);
                match fill {
                    Fill::Learned => {
                        RowFill::shipped().refine(&self.observed_m, &filled, grid, &kept)
                    }
                    _ => filled,
                }
            }
            (_, Some(Sparsify::Fraction(_))) => {
                fill_scattered(&self.observed_m, grid, self.scatter_fill(fill, rule))
            }
        }
    }

    /// How scattered returns on the model grid are filled by `fill`, the rendering x_d as
    /// the guide ([`scatter_fill`]).
    fn scatter_fill(&self, fill: Fill, rule: &SurfaceRule) -> ScatterFill<'_> {
        scatter_fill(fill, &self.model.depth_m, rule)
    }

    /// The completed scan on the model grid: each measured return as measured, and each
    /// dropped ray within [`COMPLETION_REACH`] steps of a return filled from the returns
    /// around it; 0 farther in, where the rendering x_d is the better guess. `learned` and
    /// `guided` let the rendering pick the surface at a depth edge, `edge-aware` does not;
    /// [`Fill::Gan`] fills nothing. Chosen on the validation drive (BENCHMARKS.md,
    /// "Completion of dropped rays").
    pub fn completed_observation(&self, fill: Fill) -> Vec<f32> {
        let Some(how) = completion_fill(fill) else {
            return self.observed_m.clone();
        };
        let grid = &self.model.grid;
        let distance = holes::distance_to_returns(&self.observed_m, grid.height, grid.width);
        fill_near_returns(&self.observed_m, grid, &self.model.depth_m, how, &distance)
    }

    /// The observation (restored first by [`Decoded::interpolate_restored`] when decoding
    /// was sparse) interpolated onto `rendered`'s grid by `fill`, guided by this scene's
    /// rendering there; 0 where no observed return reaches. [`Fill::Gan`] gives
    /// `rendered.depth_m`.
    pub fn interpolate_on(&self, rendered: &Rendered, fill: Fill, rule: &SurfaceRule) -> Vec<f32> {
        if fill == Fill::Gan {
            return rendered.depth_m.clone();
        }
        let mut source = RangeImage::empty(self.model.grid.clone());
        source.range_m = self.interpolate_restored(fill, rule);
        self.mark_measured(&mut source);
        resample(&source, &self.model.depth_m, rendered, fill, rule)
    }

    /// Gives the observed pixels of `source` (model grid) their measured points, where the
    /// scan was observed on the model grid: a finer grid then keeps each return in the pixel
    /// it was measured in.
    fn mark_measured(&self, source: &mut RangeImage) {
        let Some(points) = &self.observed_points else {
            return;
        };
        for k in 0..source.range_m.len().min(points.range_m.len()) {
            if self.observed_m[k] > 0.0 && source.range_m[k] == self.observed_m[k] {
                source.xyz[k] = points.xyz[k];
                source.point_index[k] = points.point_index[k];
            }
        }
    }

    /// What `convert` writes on the model grid as `depth`: the completed scan (measured
    /// returns kept, dropped rays filled from the returns around them by `fill`, then for
    /// [`Fill::Learned`] moved by the learned hole fill), or after
    /// `--restore-*` the restoration by `fill`; completed by the rendering x_d where no
    /// observed return reaches. [`Fill::Gan`] gives x_d everywhere.
    pub fn model_output(&self, fill: Fill) -> Rendered {
        match (self.restore, fill) {
            (_, Fill::Gan) => self.model.clone(),
            (Some(_), _) => complete(
                self.model.clone(),
                &self.interpolate_restored(fill, &SurfaceRule::default()),
            ),
            (None, _) => completed(&self.observed_m, &self.model.grid, self.model.clone(), fill),
        }
    }

    /// What `convert` writes on an extra grid (upsampled, another sensor's): the observation
    /// interpolated by `fill`, completed by the rendering where no observed return reaches
    /// (x_n is the rendering's everywhere).
    pub fn render_output(&self, grid: &PreparedGrid, fill: Fill) -> Rendered {
        let rendered = self.render_prepared(grid);
        if fill == Fill::Gan {
            return rendered;
        }
        let values = self.interpolate_on(&rendered, fill, &SurfaceRule::default());
        complete(rendered, &values)
    }
}

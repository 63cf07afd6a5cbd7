//! Relighting under a projector (held out or not): the irradiance of its pattern on the surface,
//! the direct part from a per-pixel direct albedo, and the subsurface part from the layer model.
//!
//! Conventions as in [`super::profiles`] (irradiance units, projector coordinates).

use nalgebra::Vector3;

use super::profiles::{ProjectorView, irradiance};
use super::render::{LayerModel, RenderError, RenderOptions, render_global};
use super::surface::{Surface, ViewRay, shift_per_depth};
use crate::capture::Pattern;

/// Per-pixel irradiance of `view` showing `pattern` (0 where the projector does not reach), with
/// the projector's response: `black + (1 - black) * level` (levels are linear after photometric
/// calibration).
pub fn pattern_irradiance(
    surface: &Surface,
    view: &ProjectorView,
    pattern: &Pattern,
    black_level: f32,
) -> Vec<f32> {
    (0..surface.len())
        .map(|i| {
            let Some((u, v)) = view.coords[i] else {
                return 0.0;
            };
            if !surface.mask[i] {
                return 0.0;
            }
            let (pu, pv) = (u.round().max(0.0) as u32, v.round().max(0.0) as u32);
            let level = black_level + (1.0 - black_level) * pattern.value(pu, pv);
            let e = irradiance(&surface.points[i], &surface.normals[i], &view.centre);
            (f64::from(level) * e) as f32
        })
        .collect()
}

/// `t_i + t_o` per pixel for a light at `centre`.
pub fn shifts(
    surface: &Surface,
    centre: &Vector3<f64>,
    eta: f64,
    view_ray: ViewRay,
) -> Vec<Option<Vector3<f64>>> {
    (0..surface.len())
        .map(|i| {
            if !surface.mask[i] {
                return None;
            }
            shift_per_depth(
                &surface.points[i],
                &surface.normals[i],
                centre,
                &surface.camera_centre,
                eta,
                view_ray,
            )
        })
        .collect()
}

/// Direct albedo per pixel and channel: the median over the training projectors of the direct
/// component under white divided by that projector's irradiance.
pub fn direct_albedo(white_irradiance: &[Vec<f32>], direct_white: &[&[[f32; 3]]]) -> Vec<[f32; 3]> {
    let n = white_irradiance.first().map_or(0, Vec::len);
    (0..n)
        .map(|i| {
            let mut out = [0.0f32; 3];
            for (c, o) in out.iter_mut().enumerate() {
                let mut ratios: Vec<f32> = white_irradiance
                    .iter()
                    .zip(direct_white)
                    .filter(|(e, _)| e[i] > 1e-6)
                    .map(|(e, d)| d[i][c] / e[i])
                    .collect();
                if ratios.is_empty() {
                    continue;
                }
                ratios.sort_by(f32::total_cmp);
                *o = ratios[ratios.len() / 2];
            }
            out
        })
        .collect()
}

/// A relit image split in its parts.
#[derive(Debug, Clone, PartialEq)]
pub struct Relit {
    pub direct: Vec<[f32; 3]>,
    pub global: Vec<[f32; 3]>,
}

impl Relit {
    /// Direct plus global.
    pub fn total(&self) -> Vec<[f32; 3]> {
        self.direct
            .iter()
            .zip(&self.global)
            .map(|(d, g)| [d[0] + g[0], d[1] + g[1], d[2] + g[2]])
            .collect()
    }
}

/// Renders the light `view` showing `pattern` with `model` (global) and `albedo` (direct).
#[allow(clippy::too_many_arguments)]
pub fn relight(
    surface: &Surface,
    view: &ProjectorView,
    pattern: &Pattern,
    black_level: f32,
    model: &LayerModel,
    albedo: &[[f32; 3]],
    eta: f64,
    view_ray: ViewRay,
    opts: &RenderOptions,
) -> Result<Relit, RenderError> {
    let e = pattern_irradiance(surface, view, pattern, black_level);
    let shift = shifts(surface, &view.centre, eta, view_ray);
    let global = render_global(surface, &e, &shift, model, opts)?;
    let direct = e
        .iter()
        .zip(albedo)
        .map(|(&e, a)| [a[0] * e, a[1] * e, a[2] * e])
        .collect();
    Ok(Relit { direct, global })
}

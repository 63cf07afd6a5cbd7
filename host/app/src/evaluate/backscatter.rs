//! Back-scatter: how much of the held-out projector's slit light emerges on the side of the slit
//! the light came from, in the truth and in each renderer (the paper's stated failure: its Fig. 10
//! reproduces the forward side, not the side toward the light).
//!
//! Conventions
//! - For every compared pixel and each slit axis, `s` is the signed distance (mm on the surface)
//!   from the centre of the nearest lit slit along the profile axis (the surface gradient of the
//!   projector coordinate), oriented so that `s < 0` lies toward the light (the in-plane
//!   direction to the projector, `-t_i`) and `s > 0` away from it. Pixels whose profile axis is
//!   nearly perpendicular to the light's in-plane direction (`|cos| < 0.3`) or lit almost along the
//!   normal (`|t_i| < 0.05`) have no meaningful side and are left out.
//! - Values: the simulator's true global (subsurface) image of the slit frame with offset 0 and
//!   each renderer's global part, mean of R, G, B.
//! - "toward" and "away" sides exclude the slit itself (`|s| <= W / 2`).

use std::collections::BTreeMap;

use nalgebra::{Matrix2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::holdout::HeldOutSlit;
use crate::report::plot::{Plot, Style};
use mlsss_core::capture::{Axis, Pattern};
use mlsss_core::imageio::ImageIoError;
use mlsss_layer_model::model_file::{Baseline, ModelFileError, SubsurfaceModel};
use mlsss_layer_model::profiles::slit_distance_px;
use mlsss_layer_model::surface::refracted_tangent;

/// Errors of the back-scatter evaluation.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BackscatterError {
    /// A truth image could not be read.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// Rendering (or the projector's coordinates) failed.
    #[error(transparent)]
    Model(#[from] ModelFileError),
}

/// The renderers compared with the truth.
const RENDERERS: [(Baseline, &str); 3] = [
    (Baseline::Mlsss, "mlsss"),
    (Baseline::Homogeneous, "homogeneous"),
    (Baseline::Dipole, "dipole"),
];

/// Bin width of the mean profile (mm).
const BIN_MM: f64 = 0.5;

/// One compared pixel sample: signed distance, half slit width (mm), truth and renders.
#[derive(Debug, Clone)]
struct Sample {
    s: f64,
    half_width: f64,
    truth: f64,
    renders: Vec<f64>,
}

/// The result: the `relight.backscatter` report object and its plot.
#[derive(Debug, Clone)]
pub struct Backscatter {
    pub report: BackscatterReport,
    pub plot: Plot,
}

/// The `relight.backscatter` report object. Per-renderer maps are keyed `truth`, `mlsss`,
/// `homogeneous`, `dipole` (renderers without a finite value are left out).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BackscatterReport {
    pub projector: usize,
    /// Compared pixel samples (both slit axes).
    pub pixels: usize,
    pub toward_light: SideErrors,
    pub away_from_light: SideErrors,
    /// Light emerging toward the light per unit emerging away from it.
    pub asymmetry_toward_over_away: BTreeMap<String, f64>,
    /// Bin centres of the mean profile, mm (< 0 toward the light).
    pub profile_mm: Vec<f64>,
    /// Mean global radiance per bin.
    pub profile: BTreeMap<String, Vec<f64>>,
}

/// The renderers' errors on one side of the slits.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SideErrors {
    pub pixels: usize,
    /// Relative RMS error per renderer (null when the truth is dark there).
    pub rel_rmse: BTreeMap<String, Option<f64>>,
}

/// The profile axis of coordinate `which` (0 = u, 1 = v) at pixel `i`: projector pixels per mm
/// and the unit surface direction along which the coordinate grows.
fn profile_axis(
    model: &SubsurfaceModel,
    coords: &[Option<(f32, f32)>],
    i: usize,
    which: usize,
) -> Option<(f64, Vector3<f64>)> {
    let (w, h) = (model.header.width, model.header.height);
    let (x, y) = (i % w, i / w);
    let at = |x: usize, y: usize| -> Option<f64> {
        let (u, v) = coords.get(y * w + x).copied().flatten()?;
        Some(f64::from(if which == 0 { u } else { v }))
    };
    let here = at(x, y)?;
    let diff = |back: Option<f64>, fwd: Option<f64>| match (back, fwd) {
        (Some(a), Some(b)) => Some((b - a) / 2.0),
        (None, Some(b)) => Some(b - here),
        (Some(a), None) => Some(here - a),
        (None, None) => None,
    };
    let gx = diff(
        x.checked_sub(1).and_then(|x| at(x, y)),
        (x + 1 < w).then(|| at(x + 1, y)).flatten(),
    )?;
    let gy = diff(
        y.checked_sub(1).and_then(|y| at(x, y)),
        (y + 1 < h).then(|| at(x, y + 1)).flatten(),
    )?;
    let fp = model.surface.footprint(i)?;
    let gram = Matrix2::new(
        fp.dx.dot(&fp.dx),
        fp.dx.dot(&fp.dy),
        fp.dy.dot(&fp.dx),
        fp.dy.dot(&fp.dy),
    );
    let a = gram.try_inverse()? * Vector2::new(gx, gy);
    let grad = fp.dx * a.x + fp.dy * a.y;
    let norm = grad.norm();
    (norm > 1e-9).then(|| (norm, grad / norm))
}

/// Samples of one slit axis from the held-out evaluation's truth and renders of that slit
/// (`holdout::evaluate_holdout` keeps them); none when the evaluation had no such slit.
fn axis_samples(
    model: &SubsurfaceModel,
    k: usize,
    axis: Axis,
    slits: &[HeldOutSlit],
) -> Result<Vec<Sample>, BackscatterError> {
    let Some(slit) = slits
        .iter()
        .find(|s| matches!(s.pattern, Pattern::Slit { axis: a, offset: 0, .. } if a == axis))
    else {
        return Ok(Vec::new());
    };
    let Pattern::Slit { width, period, .. } = slit.pattern else {
        return Ok(Vec::new());
    };
    let n = model.header.width * model.header.height;
    if slit.truth.len() != n {
        return Ok(Vec::new());
    }
    let truth = &slit.truth;
    let renders: Vec<Option<&Vec<[f32; 3]>>> = RENDERERS
        .iter()
        .map(|(baseline, _)| {
            slit.renders
                .iter()
                .find(|(b, img)| b == baseline && img.len() == n)
                .map(|(_, img)| img)
        })
        .collect();
    let coords = model.projector_coords(k)?;
    let light = Vector3::from(model.header.projectors[k].centre);
    let which = usize::from(axis == Axis::Y);
    let mean = |p: &[f32; 3]| f64::from(p[0] + p[1] + p[2]) / 3.0;
    let mut out = Vec::new();
    for (i, c) in coords.iter().enumerate() {
        let Some((u, v)) = *c else { continue };
        let (point, normal) = (&model.surface.points[i], &model.surface.normals[i]);
        let Some(t_i) = refracted_tangent(&(light - point).normalize(), normal, model.header.eta)
        else {
            continue;
        };
        if t_i.norm() < 0.05 {
            continue;
        }
        let Some((px_per_mm, s_hat)) = profile_axis(model, &coords, i, which) else {
            continue;
        };
        let toward_light = -t_i / t_i.norm();
        let cos = s_hat.dot(&toward_light);
        if cos.abs() < 0.3 {
            continue;
        }
        let coord = f64::from(if which == 0 { u } else { v });
        let d_px = slit_distance_px(coord, width, period, 0);
        out.push(Sample {
            s: -cos.signum() * d_px / px_per_mm,
            half_width: f64::from(width) / 2.0 / px_per_mm,
            truth: mean(&truth[i]),
            renders: renders
                .iter()
                .map(|r| r.as_ref().map_or(f64::NAN, |r| mean(&r[i])))
                .collect(),
        });
    }
    Ok(out)
}

/// Relative RMS error of each renderer against the truth over `samples`.
fn side_errors(samples: &[&Sample]) -> SideErrors {
    let den: f64 = samples.iter().map(|s| s.truth * s.truth).sum();
    let rel_rmse = RENDERERS
        .iter()
        .enumerate()
        .filter(|(r, _)| samples.iter().all(|s| s.renders[*r].is_finite()))
        .map(|(r, (_, name))| {
            let num: f64 = samples
                .iter()
                .map(|s| (s.renders[r] - s.truth).powi(2))
                .sum();
            let v = (den > 0.0).then(|| (num / den).sqrt());
            ((*name).to_owned(), v)
        })
        .collect();
    SideErrors {
        pixels: samples.len(),
        rel_rmse,
    }
}

/// Back-scatter of held-out projector `k` against the truth in `truth_dir`; `None` without slit
/// truth images (a real capture) or without usable pixels.
pub fn evaluate_backscatter(
    model: &SubsurfaceModel,
    k: usize,
    slits: &[HeldOutSlit],
) -> Result<Option<Backscatter>, BackscatterError> {
    let mut samples = axis_samples(model, k, Axis::X, slits)?;
    samples.extend(axis_samples(model, k, Axis::Y, slits)?);
    if samples.is_empty() {
        return Ok(None);
    }
    let toward: Vec<&Sample> = samples.iter().filter(|s| s.s < -s.half_width).collect();
    let away: Vec<&Sample> = samples.iter().filter(|s| s.s > s.half_width).collect();
    let sum = |set: &[&Sample], r: Option<usize>| -> f64 {
        set.iter()
            .map(|s| r.map_or(s.truth, |r| s.renders[r]))
            .sum()
    };
    // Light emerging toward the light per unit emerging away from it.
    let mut asymmetry = BTreeMap::new();
    asymmetry.insert("truth".into(), sum(&toward, None) / sum(&away, None));
    for (r, (_, name)) in RENDERERS.iter().enumerate() {
        let ratio = sum(&toward, Some(r)) / sum(&away, Some(r));
        if ratio.is_finite() {
            asymmetry.insert((*name).into(), ratio);
        }
    }
    // Mean profile in bins of BIN_MM over half the typical period.
    let mut reach: Vec<f64> = samples.iter().map(|s| s.s.abs()).collect();
    reach.sort_by(f64::total_cmp);
    let half_range = reach[reach.len() * 95 / 100].clamp(BIN_MM, 10.0);
    let bins = (2.0 * half_range / BIN_MM).ceil() as usize;
    let mut acc = vec![(0usize, 0.0f64, vec![0.0f64; RENDERERS.len()]); bins];
    for s in &samples {
        let b = ((s.s + half_range) / BIN_MM).floor();
        if b < 0.0 || b as usize >= bins {
            continue;
        }
        let e = &mut acc[b as usize];
        e.0 += 1;
        e.1 += s.truth;
        for (a, v) in e.2.iter_mut().zip(&s.renders) {
            *a += v;
        }
    }
    let centre = |b: usize| -half_range + (b as f64 + 0.5) * BIN_MM;
    let filled: Vec<usize> = (0..bins).filter(|&b| acc[b].0 >= 5).collect();
    let truth_profile: Vec<(f64, f64)> = filled
        .iter()
        .map(|&b| (centre(b), acc[b].1 / acc[b].0 as f64))
        .collect();
    let mut plot = Plot::new(
        &format!("Back-scatter, held-out projector {k}"),
        "mm from the slit centre, < 0 toward the light",
        "mean global radiance",
    )
    .with_series("truth", truth_profile.clone(), Style::LineAndPoints);
    let mut profiles = BTreeMap::new();
    profiles.insert(
        "truth".into(),
        truth_profile.iter().map(|p| p.1).collect::<Vec<_>>(),
    );
    for (r, (_, name)) in RENDERERS.iter().enumerate() {
        let points: Vec<(f64, f64)> = filled
            .iter()
            .map(|&b| (centre(b), acc[b].2[r] / acc[b].0 as f64))
            .collect();
        if points.iter().all(|p| p.1.is_finite()) {
            profiles.insert(
                (*name).into(),
                points.iter().map(|p| p.1).collect::<Vec<_>>(),
            );
            plot = plot.with_series(name, points, Style::Line);
        }
    }
    let report = BackscatterReport {
        projector: k,
        pixels: samples.len(),
        toward_light: side_errors(&toward),
        away_from_light: side_errors(&away),
        asymmetry_toward_over_away: asymmetry,
        profile_mm: filled.iter().map(|&b| centre(b)).collect(),
        profile: profiles,
    };
    Ok(Some(Backscatter { report, plot }))
}

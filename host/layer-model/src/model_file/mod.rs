//! The fitted model as one file (`OUT/fit/model.mlsss`), and rendering a projector's pattern from
//! it: everything `mlsss render`, `mlsss eval` and the demo need, with no other artefact.
//!
//! File layout: 8-byte magic [`MAGIC`], `u32` LE format version, then gzip data (one or more
//! gzip members, concatenated: one gzip stream to `gunzip`) holding a
//! `u32` LE header length, the UTF-8 JSON [`ModelHeader`], and little-endian binary sections in
//! this order (`n` = width x height camera pixels, row-major, pixel `i = y * width + x`):
//! points `n x 3 f32` (world mm), normals `n x 3 f32`, mask `n u8`, direct albedo `n x 3 f32`,
//! white albedo `n x 3 f32`,
//! visibility `projectors x n u8`, the layer model, a `u8` flag and, when set, the dipole baseline
//! in the same layout. Binary because the layer model of a full-size capture is tens of millions
//! of numbers; gzip because most pixels are background or share few layers.
//!
//! Layer model section, format 2: the layer count of every pixel and channel (`n x 3 u16`, row
//! `i * 3 + c`); a palette of the distinct `(index, sigma_mm, depth_mm)` triples (`u32` count,
//! then `u16 index, f32 sigma_mm, f32 depth_mm` each); the layer count `u32`; the byte width of a
//! palette id (`u8`: 1, 2 or 4) and every layer's palette id; every layer's `f32 weight` as four
//! byte planes (all first bytes, then all second bytes, ...). Why: with the spatial prior most
//! pixels share one shape, so the ids repeat and the planes of the weights' high bytes compress,
//! where format 1 (offsets `n x 3 + 1 u32`, layer count `u32`, layers `u16 index, f32 weight,
//! f32 sigma_mm, f32 depth_mm`) stored 14 incompressible bytes per layer (383 MB at full size).
//! Format 1 files are still read.
//!
//! Conventions: as [`super::surface`] and [`super::profiles`]; radiance in the frames' linear
//! units. A render holds projector `k`'s light only (its black level included, the stray light of
//! the other projectors' black level not).

mod file_format;
#[cfg(test)]
mod tests;

use std::path::PathBuf;

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::fit::{EmVariant, FitStats};
use super::profiles::{Falloff, ProjectorIllumination};
use super::relight::{LitPatterns, Relit};
use super::render::{LayerModel, RenderError, RenderOptions, SplatLayer};
use super::surface::{Surface, ViewRay};
use mlsss_core::booth::PatternSpec;
use mlsss_core::calibration::Calibration;
use mlsss_core::capture::Pattern;

/// First bytes of a model file.
pub const MAGIC: &[u8; 8] = b"MLSSSMDL";
/// Version of the layout written by this code.
pub const FORMAT_VERSION: u32 = 2;
/// Oldest layout this code still reads (its layer sections differ, see the module doc).
pub const OLDEST_READABLE_VERSION: u32 = 1;

/// Errors reading, writing or rendering a model file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ModelFileError {
    /// The file could not be read or written.
    #[error("model file {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The file is not a model file (wrong magic) or is of another version.
    #[error(
        "{path} is not an mlsss model file of format version {OLDEST_READABLE_VERSION} to \
         {FORMAT_VERSION} ({reason}); write one with `mlsss process CAPTURE --calib ... --until fit`"
    )]
    NotAModel { path: PathBuf, reason: String },
    /// The file ends early or its sections disagree with the header.
    #[error("model file {path} is corrupt: {reason}")]
    Corrupt { path: PathBuf, reason: String },
    /// The model has no such projector.
    #[error("projector {requested} is not in the model (it has {count} projectors: 0..{count})")]
    NoSuchProjector { requested: usize, count: usize },
    /// The dipole baseline was asked for but the model was saved without it.
    #[error("the model has no dipole baseline (fitted with dipole disabled)")]
    NoDipole,
    /// The in-memory model is inconsistent (sizes of its parts).
    #[error("inconsistent model: {0}")]
    Inconsistent(String),
    /// The renderer refused its input.
    #[error(transparent)]
    Render(#[from] RenderError),
}

/// One projector as a light of the model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProjectorLight {
    /// Optical centre, world mm.
    pub centre: [f64; 3],
    pub falloff: Falloff,
    /// Fraction of white the projector emits for level 0.
    pub black_level: f32,
    /// Blur of its pattern edges seen by a camera pixel (projector px, standard deviation).
    pub blur_px: f32,
}

/// Metadata of a model (the JSON header of the file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelHeader {
    pub format_version: u32,
    pub width: usize,
    pub height: usize,
    pub em: EmVariant,
    /// Components requested per fit (the paper: 20).
    pub components: usize,
    /// Layer spacing D (mm), subject-wide.
    pub depth_spacing_mm: f64,
    pub eta: f64,
    pub view_ray: ViewRay,
    pub training_projectors: Vec<usize>,
    pub holdout: Option<usize>,
    /// Every projector of the capture as a light, index = projector number.
    pub projectors: Vec<ProjectorLight>,
    /// The calibration the model was built with (projections for rendering).
    pub calibration: Calibration,
    /// The booth's pattern geometry (slit width and period, stripes) the capture used.
    pub patterns: PatternSpec,
    pub camera_centre: [f64; 3],
    pub stats: FitStats,
}

/// Which model renders the subsurface light.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Baseline {
    /// The fitted multi-layer model, per pixel.
    Mlsss,
    /// Its layers averaged over the skin (paper Fig. 11d).
    Homogeneous,
    /// A per-pixel isotropic dipole (Jensen 2001).
    Dipole,
    /// No subsurface light at all.
    Direct,
}

/// A fitted model and what rendering needs.
#[derive(Debug, Clone, PartialEq)]
pub struct SubsurfaceModel {
    pub header: ModelHeader,
    pub surface: Surface,
    /// Direct radiance per unit irradiance, RGB per pixel: the part of the light the layer model
    /// does not hold (zero when the profiles kept all light, `DirectPart::None`).
    pub albedo: Vec<[f32; 3]>,
    /// All light (direct + subsurface) per unit irradiance under white, RGB per pixel: the
    /// direct-only baseline re-emits it where it entered (no subsurface transport).
    pub white_albedo: Vec<[f32; 3]>,
    /// Per projector: pixels it lights (decoded, not shadowed).
    pub visibility: Vec<Vec<bool>>,
    pub layers: LayerModel,
    pub dipole: Option<LayerModel>,
}

impl SubsurfaceModel {
    /// Checks that the parts agree in size.
    pub fn check(&self) -> Result<(), ModelFileError> {
        let n = self.header.width * self.header.height;
        let bad = |what: &str| Err(ModelFileError::Inconsistent(what.to_owned()));
        if self.surface.width != self.header.width || self.surface.height != self.header.height {
            return bad("surface size differs from the header");
        }
        if self.surface.points.len() != n
            || self.surface.normals.len() != n
            || self.surface.mask.len() != n
            || self.albedo.len() != n
            || self.white_albedo.len() != n
        {
            return bad("per-pixel arrays differ from width x height");
        }
        if self.visibility.len() != self.header.projectors.len()
            || self.visibility.iter().any(|v| v.len() != n)
        {
            return bad("visibility maps differ from the projectors or the image size");
        }
        for m in std::iter::once(&self.layers).chain(self.dipole.as_ref()) {
            if m.width != self.header.width || m.height != self.header.height {
                return bad("a layer model differs from the image size");
            }
        }
        Ok(())
    }

    /// The homogeneous baseline: layers averaged over the pixels that have a fit, applied to the
    /// whole surface.
    pub fn homogeneous(&self) -> LayerModel {
        let (w, h) = (self.header.width, self.header.height);
        LayerModel::uniform(w, h, &self.homogeneous_layers(), &self.surface.mask)
    }

    /// The layers every skin pixel of [`SubsurfaceModel::homogeneous`] gets, per channel: the
    /// mean over the fitted pixels.
    pub fn homogeneous_layers(&self) -> [Vec<SplatLayer>; 3] {
        self.layers.mean_layers(&self.layers.fitted())
    }

    /// The model of image rows `rows` alone (clamped to the image): renders it gives agree with
    /// the whole model's on the rows [`SubsurfaceModel::rows_reaching`] says they need.
    pub fn rows(&self, rows: std::ops::Range<usize>) -> Self {
        Self {
            dipole: self
                .dipole
                .as_ref()
                .map(|d| d.rows(self.clamped(rows.clone()))),
            ..self.rows_without_dipole(rows)
        }
    }

    /// As [`SubsurfaceModel::rows`] without the dipole baseline: for renders of the other
    /// baselines, which never read it (Fig. 10 copied the full-size dipole's rows for nothing).
    pub fn rows_without_dipole(&self, rows: std::ops::Range<usize>) -> Self {
        let rows = self.clamped(rows);
        let (start, end) = (rows.start, rows.end);
        let span = start * self.header.width..end * self.header.width;
        Self {
            header: ModelHeader {
                height: end - start,
                ..self.header.clone()
            },
            surface: self.surface.rows(start..end),
            albedo: self.albedo[span.clone()].to_vec(),
            white_albedo: self.white_albedo[span.clone()].to_vec(),
            visibility: self
                .visibility
                .iter()
                .map(|v| v[span.clone()].to_vec())
                .collect(),
            layers: self.layers.rows(start..end),
            dipole: None,
        }
    }

    /// `rows` clamped to the image.
    fn clamped(&self, rows: std::ops::Range<usize>) -> std::ops::Range<usize> {
        let end = rows.end.min(self.header.height);
        rows.start.min(end)..end
    }

    /// The rows a render with `opts` needs to get rows `rows` right when pixel `i` is rendered
    /// with layers of `extent(i)` (widest sigma, deepest layer; mm): every source whose light
    /// can reach them (its widest layer, shifted by the steepest refracted incidence `eta`
    /// allows plus its own view term, over its smallest stretch), widened to the pyramid's grid
    /// so every level is sampled as on the whole image. Serves figures that show a scanline.
    pub fn rows_reaching(
        &self,
        rows: std::ops::Range<usize>,
        extent: impl Fn(usize) -> (f64, f64) + Sync,
        opts: &RenderOptions,
    ) -> std::ops::Range<usize> {
        let height = self.header.height;
        let eta = self.header.eta;
        if eta.is_nan() || eta <= 1.0 {
            return 0..height;
        }
        // Shift per depth: a refracted incident ray at most tan(asin(1 / eta)); the view term
        // as `ViewRay` says, from the pixel's own view angle.
        let incident = 1.0 / (eta * eta - 1.0).sqrt();
        let view_term = |i: usize| {
            let to_camera = (self.surface.camera_centre - self.surface.points[i]).normalize();
            let cos = self.surface.normals[i].dot(&to_camera).abs().min(1.0);
            let sin = (1.0 - cos * cos).sqrt();
            match self.header.view_ray {
                ViewRay::ExitPoint => 0.0,
                ViewRay::Unrefracted => sin / cos,
                ViewRay::Refracted => (sin / eta) / (1.0 - (sin / eta).powi(2)).sqrt(),
            }
        };
        let width = self.header.width;
        // Per image row: how far its sources' light can travel (0 without sources), and the
        // coarsest pyramid level they use.
        let per_row: Vec<(f64, usize)> = (0..height)
            .into_par_iter()
            .map(|y| {
                (y * width..(y + 1) * width)
                    .filter_map(|i| {
                        let stretch = self.surface.footprint(i)?.smallest_stretch();
                        let (sigma, depth) = extent(i);
                        if stretch <= 0.0 {
                            return Some((f64::INFINITY, usize::MAX));
                        }
                        let shift = (incident + view_term(i)) * depth;
                        let sigma_px = sigma / stretch;
                        Some((
                            opts.reach_px(sigma_px, shift / stretch),
                            opts.level_factor(sigma_px),
                        ))
                    })
                    .fold((0.0f64, 1usize), |a, b| (a.0.max(b.0), a.1.max(b.1)))
            })
            .collect();
        // A row is needed when its light reaches one of `rows` (plus two rows: a crop's edge
        // rows see their surface one-sidedly).
        let reaches = |y: usize| {
            let (reach, _) = per_row[y];
            let gap = if y < rows.start {
                rows.start - y
            } else {
                y.saturating_sub(rows.end.saturating_sub(1))
            };
            gap as f64 <= reach + 2.0
        };
        let (Some(first), Some(last)) = (
            (0..height).find(|&y| reaches(y)),
            (0..height).rev().find(|&y| reaches(y)),
        ) else {
            return rows.start.min(height)..rows.end.min(height);
        };
        let factor = per_row[first..=last].iter().map(|r| r.1).max().unwrap_or(1);
        if factor > height {
            return 0..height;
        }
        let start = first.min(rows.start) / factor * factor;
        start..(last + 1).max(rows.end).min(height)
    }

    /// Projector `k`'s coordinates of every visible surface pixel, projected through the
    /// calibration (distortion included).
    pub fn projector_coords(&self, k: usize) -> Result<Vec<Option<(f32, f32)>>, ModelFileError> {
        let count = self.header.projectors.len();
        let (Some(device), Some(visible)) = (
            self.header.calibration.projectors.get(k),
            self.visibility.get(k),
        ) else {
            return Err(ModelFileError::NoSuchProjector {
                requested: k,
                count,
            });
        };
        let device = &device.device;
        Ok(self
            .surface
            .points
            .iter()
            .zip(visible)
            .zip(&self.surface.mask)
            .map(|((p, &vis), &on)| {
                if !(vis && on) {
                    return None;
                }
                device
                    .project(&Point3::from(*p))
                    .map(|q| (q.x as f32, q.y as f32))
            })
            .collect())
    }
}

/// Renders projector `k` showing `pattern` with the chosen model: the direct part from the
/// albedo, the subsurface part from the layers. [`Baseline::Direct`] has no subsurface part: all
/// light (the white albedo) is re-emitted where it enters. Pure function of the model: no files.
pub fn render_projector(
    model: &SubsurfaceModel,
    k: usize,
    pattern: &Pattern,
    baseline: Baseline,
    opts: &RenderOptions,
) -> Result<Relit, ModelFileError> {
    let black_level = |light: &ProjectorLight| light.black_level;
    render_with_black_level(model, k, pattern, baseline, opts, black_level)
}

/// As [`render_projector`] with the projector's black level taken as 0: the pattern's own light
/// alone (for a slit, what `(G_slit - b G_white) / (1 - b)` gives from two renders with the
/// black level `b`; the renderer is linear in the irradiance), in one render.
pub fn render_pattern_alone(
    model: &SubsurfaceModel,
    k: usize,
    pattern: &Pattern,
    baseline: Baseline,
    opts: &RenderOptions,
) -> Result<Relit, ModelFileError> {
    render_with_black_level(model, k, pattern, baseline, opts, |_| 0.0)
}

/// [`render_projector`] under several patterns: the same frames, each as [`render_projector`]
/// renders it, for much less than one render per pattern (the baseline's layers, the
/// projector's coordinates, the shifts and the splat positions are found once).
pub fn render_projector_patterns(
    model: &SubsurfaceModel,
    k: usize,
    patterns: &[Pattern],
    baseline: Baseline,
    opts: &RenderOptions,
) -> Result<Vec<Relit>, ModelFileError> {
    ProjectorPatterns::new(model, k, patterns)?.render(baseline, opts)
}

/// Projector `k` showing several patterns, made ready to render with any baseline: the
/// projector's coordinates, the patterns' irradiance and the shifts are found once, so each
/// baseline costs only its own splats ([`ProjectorPatterns::render`] gives the frames
/// [`render_projector_patterns`] gives).
pub struct ProjectorPatterns<'m> {
    model: &'m SubsurfaceModel,
    lit: LitPatterns,
}

impl<'m> ProjectorPatterns<'m> {
    pub fn new(
        model: &'m SubsurfaceModel,
        k: usize,
        patterns: &[Pattern],
    ) -> Result<Self, ModelFileError> {
        Self::with_black_level(model, k, patterns, |light| light.black_level)
    }

    /// As [`ProjectorPatterns::new`] with the projector's black level given by `black_level`.
    fn with_black_level(
        model: &'m SubsurfaceModel,
        k: usize,
        patterns: &[Pattern],
        black_level: impl Fn(&ProjectorLight) -> f32,
    ) -> Result<Self, ModelFileError> {
        let (light, coords) = projector_light(model, k)?;
        let view = ProjectorIllumination {
            centre: Vector3::from(light.centre),
            falloff: light.falloff,
            coords: &coords,
        };
        let lit = LitPatterns::new(
            &model.surface,
            &view,
            patterns,
            black_level(light),
            light.blur_px,
            model.header.eta,
            model.header.view_ray,
        );
        Ok(Self { model, lit })
    }

    /// Every pattern rendered with `baseline`.
    pub fn render(
        &self,
        baseline: Baseline,
        opts: &RenderOptions,
    ) -> Result<Vec<Relit>, ModelFileError> {
        let (layers, albedo) = baseline_layers(self.model, baseline)?;
        Ok(self
            .lit
            .relight(&self.model.surface, &layers, albedo, opts)?)
    }
}

/// A projector's coordinates of every surface pixel (`None` where it is not seen).
type ProjectorCoords = Vec<Option<(f32, f32)>>;

/// Projector `k`'s light and its coordinates of every visible surface pixel.
fn projector_light(
    model: &SubsurfaceModel,
    k: usize,
) -> Result<(&ProjectorLight, ProjectorCoords), ModelFileError> {
    let light = model
        .header
        .projectors
        .get(k)
        .ok_or(ModelFileError::NoSuchProjector {
            requested: k,
            count: model.header.projectors.len(),
        })?;
    Ok((light, model.projector_coords(k)?))
}

/// The layers and direct albedo a baseline renders with.
fn baseline_layers(
    model: &SubsurfaceModel,
    baseline: Baseline,
) -> Result<(std::borrow::Cow<'_, LayerModel>, &[[f32; 3]]), ModelFileError> {
    use std::borrow::Cow;
    Ok(match baseline {
        Baseline::Mlsss => (Cow::Borrowed(&model.layers), &model.albedo),
        Baseline::Homogeneous => (Cow::Owned(model.homogeneous()), &model.albedo),
        Baseline::Dipole => (
            Cow::Borrowed(model.dipole.as_ref().ok_or(ModelFileError::NoDipole)?),
            &model.albedo,
        ),
        Baseline::Direct => (
            Cow::Owned(LayerModel::from_fn(
                model.header.width,
                model.header.height,
                |_, _| Vec::new(),
            )),
            &model.white_albedo,
        ),
    })
}

fn render_with_black_level(
    model: &SubsurfaceModel,
    k: usize,
    pattern: &Pattern,
    baseline: Baseline,
    opts: &RenderOptions,
    black_level: impl Fn(&ProjectorLight) -> f32,
) -> Result<Relit, ModelFileError> {
    let patterns = std::slice::from_ref(pattern);
    let mut frames = ProjectorPatterns::with_black_level(model, k, patterns, black_level)?
        .render(baseline, opts)?;
    // One frame per pattern.
    Ok(frames.pop().unwrap_or_default())
}

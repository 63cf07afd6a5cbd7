//! The fit stage (DESIGN stage 7): per pixel and channel, the layer model from the slit profiles of
//! the training projectors, as a [`LayerModel`] the renderer consumes.
//!
//! - `Layered` (default): one joint fit of the 6 profiles (3 projectors x 2 axes) with the layer
//!   spacing `D` fixed to a subject-wide estimate ([`super::layer_depth`]).
//! - `Free` (the paper): each profile fitted on its own; components ranked by mean, weights and
//!   sigmas averaged over the profiles per rank, and the depth of rank `r` implied by its means,
//!   `z_r = sum_p mu_pr c_p / sum_p c_p^2` (least squares, clamped to >= 0).
//!
//! Absolute weights: a slit of width `W` (mm) under irradiance `E` gives a profile of flux
//! `F = E W sum_l w_l`, so `w_l = pi_l sum_p F_p / sum_p E_p W_p`.
//!
//! Skipped: pixels off the subject, not lit by any training projector, or with no light in their
//! profiles. `block > 1` fits one pixel per `block x block` tile (its centre) and gives every pixel
//! of the tile that shape with its own amplitude (the profile-sampling knob of `bench`).

use rayon::prelude::*;

use super::em_free::{self, Component};
use super::em_layered::{self, DepthSpacing, LayeredParams};
use super::layer_depth::{self, LayerDepthError, SpacingEstimate};
use super::mixture::{EmError, Profile};
use super::profiles::{GeometryMap, SlitSweep, pixel_profiles};
use super::render::{LayerModel, RowSource, SplatLayer};
use super::surface::Surface;

pub use super::fit_options::{EmVariant, FitOptions};

/// Errors of the fit stage.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum FitError {
    /// An EM fit failed on something other than an unlit pixel.
    #[error("pixel {pixel}: {source}")]
    Em { pixel: usize, source: EmError },
    /// No pixel has light in its profiles (wrong frames, or all shadowed).
    #[error("no pixel has light in its slit profiles: nothing to fit")]
    NothingToFit,
    /// The layer spacing could not be estimated.
    #[error(transparent)]
    Depth(#[from] LayerDepthError),
    /// The amplitudes handed to the dipole fit are not one per pixel.
    #[error("{got} pixel amplitudes for {want} pixels")]
    AmplitudeCount { got: usize, want: usize },
    /// The per-projector inputs disagree in number.
    #[error("{geometries} projector geometries but {sweeps} slit sweeps")]
    ProjectorCount { geometries: usize, sweeps: usize },
}

/// What the fit did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FitStats {
    pub depth_spacing_mm: f64,
    /// How the spacing was estimated (`subsurface::layer_depth`).
    #[serde(default)]
    pub depth: SpacingEstimate,
    /// Pixel-channel fits run, and skipped for lack of light.
    pub fits: usize,
    pub skipped: usize,
    pub mean_layers: f64,
    pub mean_iterations: f64,
}

/// The fitted model.
#[derive(Debug, Clone, PartialEq)]
pub struct FitResult {
    pub model: LayerModel,
    pub stats: FitStats,
    /// Every pixel's measured amplitude per channel, `sum_p F_p / sum_p E_p W_p` (0 off the
    /// lit surface): what scales its layer weights, and the dipole's total reflectance.
    pub amplitudes: Vec<[f32; 3]>,
}

/// `sum_p F_p / sum_p E_p W_p` for pixel `i`, channel `c`: [`weight_scale`] of
/// [`pixel_profiles`], without building the profiles.
pub(crate) fn pixel_amplitude(
    i: usize,
    c: usize,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
) -> f64 {
    let (mut flux, mut ew) = (0.0, 0.0);
    for (geo, sweep) in geometries.iter().zip(sweeps) {
        let Some(&g) = geo.get(i) else { continue };
        for (f, e) in sweep.fluxes(i, c, &g) {
            flux += f;
            ew += e;
        }
    }
    if ew > 0.0 { flux / ew } else { 0.0 }
}

/// `sum_p F_p / sum_p E_p W_p` for pixel `i`, channel `c`.
fn weight_scale(profiles: &[Profile], ew: &[f64]) -> f64 {
    let flux: f64 = profiles.iter().map(Profile::flux).sum();
    let den: f64 = ew.iter().sum();
    if den > 0.0 { flux / den } else { 0.0 }
}

/// Relative layer shape of one pixel-channel fit (weights sum to 1).
#[derive(Debug, Clone)]
struct Shape {
    layers: Vec<SplatLayer>,
    iterations: usize,
}

fn fit_layered_shape(
    profiles: &[Profile],
    spacing: f64,
    opts: &FitOptions,
    warm: Option<&LayeredParams>,
) -> Result<(Shape, LayeredParams), EmError> {
    let fit = em_layered::fit_layered(profiles, DepthSpacing::Fixed(spacing), &opts.em, warm)?;
    let layers = fit
        .layers
        .iter()
        .map(|l| SplatLayer {
            index: l.depth_index as u16,
            weight: l.weight as f32,
            sigma_mm: l.sigma as f32,
            depth_mm: (l.depth_index as f64 * spacing) as f32,
        })
        .collect();
    let params = LayeredParams {
        layers: fit.layers,
        depth_spacing: spacing,
    };
    Ok((
        Shape {
            layers,
            iterations: fit.trace.iterations(),
        },
        params,
    ))
}

fn fit_free_shape(profiles: &[Profile], opts: &FitOptions) -> Result<Shape, EmError> {
    let mut per_rank: Vec<(f64, f64, f64, f64, usize)> = Vec::new(); // w, sigma, sum mu c, sum c^2, n
    let mut iterations = 0;
    let mut fitted = 0usize;
    for p in profiles {
        let fit = match em_free::fit_free(p, &opts.em, None) {
            Ok(f) => f,
            Err(EmError::NoSignal) => continue,
            Err(e) => return Err(e),
        };
        fitted += 1;
        iterations += fit.trace.iterations();
        for (
            r,
            Component {
                weight,
                mean,
                sigma,
            },
        ) in fit.components.iter().enumerate()
        {
            if per_rank.len() <= r {
                per_rank.push((0.0, 0.0, 0.0, 0.0, 0));
            }
            let e = &mut per_rank[r];
            e.0 += weight;
            e.1 += sigma;
            e.2 += mean * p.shift_per_depth;
            e.3 += p.shift_per_depth * p.shift_per_depth;
            e.4 += 1;
        }
    }
    if fitted == 0 {
        return Err(EmError::NoSignal);
    }
    let total: f64 = per_rank.iter().map(|e| e.0).sum();
    let layers = per_rank
        .iter()
        .enumerate()
        .map(|(r, e)| SplatLayer {
            index: r as u16,
            weight: (e.0 / total) as f32,
            sigma_mm: (e.1 / e.4 as f64) as f32,
            depth_mm: if e.3 > 1e-9 {
                (e.2 / e.3).max(0.0) as f32
            } else {
                0.0
            },
        })
        .collect();
    Ok(Shape { layers, iterations })
}

/// Runs the fit stage over the surface.
pub fn fit_model(
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    opts: &FitOptions,
) -> Result<FitResult, FitError> {
    if geometries.len() != sweeps.len() {
        return Err(FitError::ProjectorCount {
            geometries: geometries.len(),
            sweeps: sweeps.len(),
        });
    }
    let (w, h) = (surface.width, surface.height);
    let lit_by_any = |i: usize| surface.mask[i] && geometries.iter().any(|g| g.get(i).is_some());
    let lit: Vec<usize> = (0..w * h).filter(|&i| lit_by_any(i)).collect();
    if lit.is_empty() {
        return Err(FitError::NothingToFit);
    }
    let depth = match opts.variant {
        EmVariant::Layered => layer_depth::estimate_spacing(&lit, geometries, sweeps, opts)?,
        EmVariant::Free => SpacingEstimate::fixed(opts.depth_spacing.unwrap_or(0.0)),
    };
    let spacing = depth.spacing_mm;
    let block = opts.block.max(1);
    let (bw, bh) = (w.div_ceil(block), h.div_ceil(block));
    // Fit tile centres (or the first lit pixel of the tile), rows of tiles in parallel with a
    // warm start from the left neighbour.
    let tile_rows: Vec<Result<Vec<[Option<Shape>; 3]>, FitError>> = (0..bh)
        .into_par_iter()
        .map(|by| {
            let mut warm: [Option<LayeredParams>; 3] = Default::default();
            let mut row = Vec::with_capacity(bw);
            for bx in 0..bw {
                let centre = tile_pixel(bx, by, block, w, h, &lit_by_any);
                let shapes = match centre {
                    Some(i) => fit_pixel_shapes(i, geometries, sweeps, spacing, opts, &mut warm)?,
                    None => Default::default(),
                };
                row.push(shapes);
            }
            Ok(row)
        })
        .collect();
    let mut tiles = Vec::with_capacity(bw * bh);
    for row in tile_rows {
        tiles.extend(row?);
    }
    let stats = fit_stats(&tiles, depth)?;
    let scales = pixel_amplitudes(surface, geometries, sweeps);
    // Lit pixels as flags: the model's rows are made twice per channel (`LayerModel::from_fn`),
    // and asking every projector's geometry each time was seconds at full size.
    let mut lit_mask = vec![false; w * h];
    for &i in &lit {
        lit_mask[i] = true;
    }
    let tile_shape = |i: usize, c: usize| {
        let (x, y) = (i % w, i / w);
        tiles[(y / block) * bw + x / block][c].as_ref()
    };
    // Iterators, not a vector per row (millions of small allocations).
    let scales_ref = &scales;
    let model = LayerModel::from_fn(w, h, |i, c| {
        let shape = if lit_mask[i] { tile_shape(i, c) } else { None };
        shape.into_iter().flat_map(move |shape| {
            let scale = scales_ref[i][c];
            shape.layers.iter().map(move |l| SplatLayer {
                weight: l.weight * scale,
                ..*l
            })
        })
    });
    Ok(FitResult {
        model,
        stats,
        amplitudes: scales,
    })
}

/// The shapes of pixel `i` in every channel (`None` where its profiles have no light), with the
/// layered fit warm-started from and updating `warm` (per channel).
fn fit_pixel_shapes(
    i: usize,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    spacing: f64,
    opts: &FitOptions,
    warm: &mut [Option<LayeredParams>; 3],
) -> Result<[Option<Shape>; 3], FitError> {
    let mut shapes: [Option<Shape>; 3] = Default::default();
    for c in 0..3 {
        let (profiles, _) = pixel_profiles(i, c, geometries, sweeps);
        let result = match opts.variant {
            EmVariant::Layered => fit_layered_shape(&profiles, spacing, opts, warm[c].as_ref())
                .map(|(s, p)| {
                    warm[c] = Some(p);
                    s
                }),
            EmVariant::Free => fit_free_shape(&profiles, opts),
        };
        match result {
            Ok(s) => shapes[c] = Some(s),
            Err(EmError::NoSignal) => {}
            Err(source) => return Err(FitError::Em { pixel: i, source }),
        }
    }
    Ok(shapes)
}

/// Counts and means of the tile fits; no fit at all is [`FitError::NothingToFit`].
fn fit_stats(tiles: &[[Option<Shape>; 3]], depth: SpacingEstimate) -> Result<FitStats, FitError> {
    let mut stats = FitStats {
        depth_spacing_mm: depth.spacing_mm,
        depth,
        ..FitStats::default()
    };
    let (mut layer_sum, mut iter_sum) = (0usize, 0usize);
    for shapes in tiles {
        for s in shapes {
            match s {
                Some(s) => {
                    stats.fits += 1;
                    layer_sum += s.layers.len();
                    iter_sum += s.iterations;
                }
                None => stats.skipped += 1,
            }
        }
    }
    if stats.fits == 0 {
        return Err(FitError::NothingToFit);
    }
    stats.mean_layers = layer_sum as f64 / stats.fits as f64;
    stats.mean_iterations = iter_sum as f64 / stats.fits as f64;
    Ok(stats)
}

/// Every pixel's own amplitude per channel (its profiles' flux over `sum E W`; 0 where no
/// training projector lights it), pixels in parallel.
pub fn pixel_amplitudes(
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
) -> Vec<[f32; 3]> {
    (0..surface.len())
        .into_par_iter()
        .map(|i| {
            if !surface.mask[i] || geometries.iter().all(|g| g.get(i).is_none()) {
                return [0.0; 3];
            }
            std::array::from_fn(|c| pixel_amplitude(i, c, geometries, sweeps) as f32)
        })
        .collect()
}

/// The pixel fitted for tile `(bx, by)`: its centre if lit, else the first lit pixel of the tile.
pub fn tile_pixel(
    bx: usize,
    by: usize,
    block: usize,
    w: usize,
    h: usize,
    lit: &impl Fn(usize) -> bool,
) -> Option<usize> {
    let (x0, y0) = (bx * block, by * block);
    let (x1, y1) = ((x0 + block).min(w), (y0 + block).min(h));
    let centre = ((y0 + y1) / 2) * w + (x0 + x1) / 2;
    if lit(centre) {
        return Some(centre);
    }
    (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| y * w + x))
        .find(|&i| lit(i))
}

/// The dipole baseline over the surface: one isotropic dipole per pixel and channel, fitted to the
/// same profiles (see [`super::dipole`]). With `block > 1` the reduced extinction (the profile's
/// shape) is fitted at one pixel per `block x block` tile, as [`fit_model`] does, and every pixel
/// of the tile keeps its own reflectance, `amplitudes` ([`FitResult::amplitudes`] or
/// [`pixel_amplitudes`]). Pixels without light get no layers.
pub fn fit_dipole_model(
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    eta: f64,
    block: usize,
    amplitudes: &[[f32; 3]],
) -> Result<LayerModel, FitError> {
    if geometries.len() != sweeps.len() {
        return Err(FitError::ProjectorCount {
            geometries: geometries.len(),
            sweeps: sweeps.len(),
        });
    }
    if amplitudes.len() != surface.len() {
        return Err(FitError::AmplitudeCount {
            got: amplitudes.len(),
            want: surface.len(),
        });
    }
    let table = super::dipole::DipoleTable::new(eta);
    let (w, h) = (surface.width, surface.height);
    let block = block.max(1);
    let (bw, bh) = (w.div_ceil(block), h.div_ceil(block));
    let lit = |i: usize| surface.mask[i] && geometries.iter().any(|g| g.get(i).is_some());
    // Extinction per tile and channel, fitted at the tile's pixel: rows of tiles in parallel,
    // each tile's search starting from its left neighbour's optimum (the first of a row searches
    // the whole range).
    let extinctions: Vec<[Option<f64>; 3]> = (0..bh)
        .into_par_iter()
        .flat_map_iter(|by| {
            let mut hint: [Option<f64>; 3] = [None; 3];
            let table = &table;
            let lit = &lit;
            (0..bw).map(move |bx| {
                let mut out = [None; 3];
                let Some(i) = tile_pixel(bx, by, block, w, h, lit) else {
                    return out;
                };
                for (c, o) in out.iter_mut().enumerate() {
                    let (profiles, ew) = pixel_profiles(i, c, geometries, sweeps);
                    if profiles.is_empty() {
                        continue;
                    }
                    *o = table
                        .fit(&profiles, weight_scale(&profiles, &ew), hint[c])
                        .map(|f| f.extinction);
                    if o.is_some() {
                        hint[c] = *o;
                    }
                }
                out
            })
        })
        .collect();
    // Every lit pixel: its own amplitude with its tile's extinction, built straight into the
    // model (no per-pixel vectors: ~4 million pixel-channels at full size).
    let tile = |i: usize| (i / w / block) * bw + (i % w) / block;
    // Every pixel of a tile scales the table row's shape at the tile's extinction.
    let table = &table;
    Ok(LayerModel::from_shapes(
        w,
        h,
        |i, c| {
            let reflectance = f64::from(amplitudes[i][c]);
            lit(i)
                .then(|| extinctions[tile(i)][c])
                .flatten()
                .and_then(|ext| table.shape_row(reflectance, ext))
                .map_or(RowSource::Empty, |row| RowSource::Shape {
                    key: (tile(i), c, row),
                    scale: reflectance,
                })
        },
        |(t, c, row)| {
            extinctions[t][c]
                .into_iter()
                .flat_map(move |ext| table.shape_layers(row, ext))
        },
    ))
}

//! Subsurface (global) light: the flux entering the skin at every surface sample, spread by the
//! Monte Carlo exit response of the local material at the local angle of incidence, summed at
//! every exit point. The skin is treated as locally planar: the offset between entry and exit is
//! measured in the entry point's tangent plane, oriented by the light direction, exactly as the
//! response was tabulated (x forward, away from the light).
//!
//! The sum over all pairs of surface samples is evaluated in radial bands (a smooth partition of
//! unity of the entry-exit distance r): band 0 (r < 2 rho_0) pixel by pixel, band j >= 1
//! (rho_{j-1} < r < 2 rho_j, rho_j = 2^j rho_0) between cells of 2^j x 2^j pixels whose flux
//! is summed, and whose result is interpolated back to pixels. A band only ever sees cells at
//! least 1.5 cells apart, where the (low-passed) response is smooth over a cell, so the error
//! is second order in cell size over distance; energy is conserved exactly by construction (the
//! bands sum to the full response). This is the hierarchical evaluation of Jensen & Buhler 2002
//! ("A rapid hierarchical rendering technique for translucent materials") on the camera grid.
//!
//! Conventions
//! - Response grids: exitance per unit incident power, 1/mm^2, per channel, on square cells
//!   centred on the entry point; x forward (away from the light), y to the side.
//! - Flux: power entering at a pixel (irradiance x area), per frame; exitance: power per mm^2
//!   leaving at a pixel, per channel and frame. Layout `flux[pixel * frames + f]`,
//!   `exitance[(pixel * 3 + c) * frames + f]`.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d};

/// The exit response of one material at one incidence angle, on a square grid centred on the entry
/// point (odd number of cells, cell `(cells - 1) / 2` holds the entry point).
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseGrid {
    pub cell_mm: f64,
    pub cells: usize,
    /// Row-major `values[iy * cells + ix]`, 1/mm^2 per incident power, R, G, B.
    pub values: Vec<[f32; 3]>,
}

impl ResponseGrid {
    fn centre_index(&self) -> f64 {
        (self.cells as f64 - 1.0) / 2.0
    }

    /// Half-width of the grid, mm.
    pub fn half_extent_mm(&self) -> f64 {
        0.5 * self.cells as f64 * self.cell_mm
    }

    /// Diffuse reflectance inside the grid, per channel.
    pub fn total(&self) -> [f64; 3] {
        let mut t = [0.0; 3];
        for v in &self.values {
            for c in 0..3 {
                t[c] += v[c] as f64;
            }
        }
        t.map(|s| s * self.cell_mm * self.cell_mm)
    }
}

/// Responses of every basis material at every tabulated incidence angle.
#[derive(Debug, Clone)]
pub struct ResponseSet {
    /// Ascending incidence angles, degrees.
    pub angles_deg: Vec<f64>,
    /// `grids[material][angle]`.
    pub grids: Vec<Vec<ResponseGrid>>,
}

/// Smooth step from 1 (t <= 1) to 0 (t >= 2).
fn window_step(t: f64) -> f64 {
    if t <= 1.0 {
        1.0
    } else if t >= 2.0 {
        0.0
    } else {
        let u = t - 1.0;
        1.0 - u * u * (3.0 - 2.0 * u)
    }
}

/// One radial band: `W(r) = step(r / rho_outer) - step(r / rho_inner)`.
#[derive(Debug, Clone, Copy)]
struct Band {
    /// `None` for the innermost band.
    rho_inner: Option<f64>,
    /// `None` for the outermost band.
    rho_outer: Option<f64>,
}

impl Band {
    fn weight(&self, r: f64) -> f64 {
        let outer = self.rho_outer.map_or(1.0, |rho| window_step(r / rho));
        let inner = self.rho_inner.map_or(0.0, |rho| window_step(r / rho));
        outer - inner
    }

    fn r_min(&self) -> f64 {
        self.rho_inner.unwrap_or(0.0)
    }

    fn r_max(&self) -> f64 {
        self.rho_outer.map_or(f64::INFINITY, |rho| 2.0 * rho)
    }
}

/// A response restricted to one band and filtered to one cell size, for bilinear lookup.
#[derive(Debug, Clone)]
struct BandTable {
    spacing: f64,
    /// Cells per side = 2 * half + 1, centred on 0.
    half: usize,
    values: Vec<[f32; 3]>,
}

impl BandTable {
    /// The band-windowed, low-passed `grid` on the table layout `spacing` (mm) x `half`.
    fn build(
        grid: &ResponseGrid,
        band: &Band,
        cell_size_mm: f64,
        spacing: f64,
        half: usize,
    ) -> Self {
        let side = 2 * half + 1;
        // Bin the windowed MC grid into the table samples (keeps the integral).
        let mut boxed = vec![[0.0f64; 3]; side * side];
        let centre = grid.centre_index();
        for iy in 0..grid.cells {
            let y = (iy as f64 - centre) * grid.cell_mm;
            for ix in 0..grid.cells {
                let x = (ix as f64 - centre) * grid.cell_mm;
                let w = band.weight((x * x + y * y).sqrt());
                if w == 0.0 {
                    continue;
                }
                let bx = (x / spacing).round() as isize + half as isize;
                let by = (y / spacing).round() as isize + half as isize;
                if bx < 0 || by < 0 || bx as usize >= side || by as usize >= side {
                    continue;
                }
                let v = grid.values[iy * grid.cells + ix];
                let cell = &mut boxed[by as usize * side + bx as usize];
                let area_ratio = (grid.cell_mm / spacing).powi(2);
                for c in 0..3 {
                    cell[c] += w * v[c] as f64 * area_ratio;
                }
            }
        }
        gaussian_filter(
            &mut boxed,
            side,
            FILTER_SIGMA_CELLS * cell_size_mm / spacing,
        );
        Self {
            spacing,
            half,
            values: boxed.into_iter().map(|v| v.map(|x| x as f32)).collect(),
        }
    }

    /// Bilinear value and gradient (d/dx, d/dy) at (x, y), mm; zero outside the table. The
    /// reference for [`PackedTables::lookup`].
    #[cfg(test)]
    fn lookup(&self, x: f32, y: f32) -> [[f32; 3]; 3] {
        let inv = 1.0 / self.spacing as f32;
        let fx = x * inv + self.half as f32;
        let fy = y * inv + self.half as f32;
        let side = 2 * self.half + 1;
        if fx < 0.0 || fy < 0.0 || fx >= (side - 1) as f32 || fy >= (side - 1) as f32 {
            return [[0.0; 3]; 3];
        }
        let (ix, iy) = (fx as usize, fy as usize);
        let (tx, ty) = (fx - ix as f32, fy - iy as f32);
        let i = iy * side + ix;
        let (a, b, c, d) = (
            self.values[i],
            self.values[i + 1],
            self.values[i + side],
            self.values[i + side + 1],
        );
        let mut out = [[0.0; 3]; 3];
        for k in 0..3 {
            let top = a[k] + (b[k] - a[k]) * tx;
            let bottom = c[k] + (d[k] - c[k]) * tx;
            out[0][k] = top + (bottom - top) * ty;
            out[1][k] = ((b[k] - a[k]) * (1.0 - ty) + (d[k] - c[k]) * ty) * inv;
            out[2][k] = (bottom - top) * inv;
        }
        out
    }
}

/// Every (material, angle) table of one level interleaved texel by texel, so that one pair of
/// cells costs one index computation and four contiguous texel reads whatever the material mix.
/// Each table's texel is padded to four lanes (R, G, B, 0): a tap then mixes one 4-wide vector
/// per corner (one SIMD multiply-add) instead of three scalar ones.
#[derive(Debug, Clone)]
struct PackedTables {
    spacing: f32,
    half: usize,
    side: usize,
    /// Tables per texel: materials x angles, ordered `[material][angle]`.
    stride: usize,
    values: Vec<[f32; 4]>,
}

/// One (material, angle) table of a cell's mix: its index in a texel, and weight.
#[derive(Debug, Clone, Copy, Default)]
struct Tap {
    offset: u32,
    weight: f32,
}

/// At most two angles for each of the four basis materials.
const MAX_TAPS: usize = 8;

/// The tables a cell of these material weights and angle interpolation mixes, with their
/// weights (materials below 1e-4 are skipped), for tables packed with `angles` angles.
fn mix_taps(
    materials: &[f32; 4],
    angle_index: u16,
    angle_t: f32,
    angles: usize,
) -> ([Tap; MAX_TAPS], u8) {
    let mut taps = [Tap::default(); MAX_TAPS];
    let mut count = 0;
    let a0 = angle_index as usize;
    for (m, &wm) in materials.iter().enumerate() {
        if wm <= 1e-4 {
            continue;
        }
        let (w_lo, w_hi) = (wm * (1.0 - angle_t), wm * angle_t);
        let offset = |a: usize| (m * angles + a) as u32;
        taps[count] = Tap {
            offset: offset(a0),
            weight: w_lo,
        };
        count += 1;
        if w_hi > 0.0 && a0 + 1 < angles {
            taps[count] = Tap {
                offset: offset(a0 + 1),
                weight: w_hi,
            };
            count += 1;
        }
    }
    (taps, count as u8)
}

impl PackedTables {
    /// The tables of every material and angle of `grids[material][angle]` for one band and cell
    /// size, on one common layout reaching `response_reach_mm` (the largest response extent).
    fn build(
        grids: &[Vec<ResponseGrid>],
        angles: usize,
        band: &Band,
        cell_size_mm: f64,
        response_reach_mm: f64,
    ) -> Self {
        // Resample finely enough for bilinear lookups of the low-passed table to be accurate
        // (MC cells finer than this are summed, coarser ones land on one sample each).
        let spacing = TABLE_SPACING_CELLS * cell_size_mm;
        let reach = band.r_max().min(response_reach_mm) + FILTER_REACH_CELLS * cell_size_mm;
        let half = (reach / spacing).ceil() as usize;
        let side = 2 * half + 1;
        let stride = grids.len() * angles;
        let mut values = vec![[0.0f32; 4]; side * side * stride];
        for (m, per_angle) in grids.iter().enumerate() {
            for (a, grid) in per_angle.iter().take(angles).enumerate() {
                let table = BandTable::build(grid, band, cell_size_mm, spacing, half);
                debug_assert!(table.half == half && table.spacing == spacing);
                let offset = m * angles + a;
                for (i, v) in table.values.iter().enumerate() {
                    values[i * stride + offset] = [v[0], v[1], v[2], 0.0];
                }
            }
        }
        Self {
            spacing: spacing as f32,
            half,
            side,
            stride,
            values,
        }
    }

    /// The weighted mix of the tables `taps` at (x, y), mm, bilinearly interpolated, with its
    /// gradient (d/dx, d/dy) when `GRADIENT`; `None` outside the tables (where they are zero).
    #[inline]
    fn lookup<const GRADIENT: bool>(&self, x: f32, y: f32, taps: &[Tap]) -> Option<[[f32; 3]; 3]> {
        let inv = 1.0 / self.spacing;
        let fx = x * inv + self.half as f32;
        let fy = y * inv + self.half as f32;
        let last = (self.side - 1) as f32;
        if !(fx >= 0.0 && fy >= 0.0 && fx < last && fy < last) {
            return None;
        }
        let (ix, iy) = (fx as usize, fy as usize);
        let (tx, ty) = (fx - ix as f32, fy - iy as f32);
        let base = (iy * self.side + ix) * self.stride;
        let corners = [
            base,
            base + self.stride,
            base + self.side * self.stride,
            base + (self.side + 1) * self.stride,
        ];
        let mut mix = [[0.0f32; 4]; 4];
        for (m, &corner) in mix.iter_mut().zip(&corners) {
            for tap in taps {
                let texel = self.values[corner + tap.offset as usize];
                for c in 0..4 {
                    m[c] += tap.weight * texel[c];
                }
            }
        }
        let [a, b, c, d] = mix;
        let mut out = [[0.0f32; 3]; 3];
        for k in 0..3 {
            let top = a[k] + (b[k] - a[k]) * tx;
            let bottom = c[k] + (d[k] - c[k]) * tx;
            out[0][k] = top + (bottom - top) * ty;
            if GRADIENT {
                out[1][k] = ((b[k] - a[k]) * (1.0 - ty) + (d[k] - c[k]) * ty) * inv;
                out[2][k] = (bottom - top) * inv;
            }
        }
        Some(out)
    }
}

/// The tables are low-passed with an isotropic Gaussian of this many cells (standard deviation)
/// before they are sampled at cell spacing. Pixel offsets are looked up in each entry point's
/// light-oriented frame, i.e. on a lattice rotated against the tables; an isotropic filter whose
/// spectrum is ~1e-3 at the lattice frequency keeps the lattice sum equal to the integral (energy
/// conservation) at any rotation, even for the sharply peaked responses of skin. It stands for
/// the pixel's integration over its footprint (a box of 1 cell has sigma 0.29 cells).
const FILTER_SIGMA_CELLS: f64 = 0.6;
/// Table sample spacing, in cells (a quarter of the filter's sigma).
const TABLE_SPACING_CELLS: f64 = 0.15;
/// How far the filtered tables reach beyond the band, in cells.
const FILTER_REACH_CELLS: f64 = 2.0;

/// Separable convolution with a normalised Gaussian of `sigma` samples (truncated at 3.5 sigma),
/// zero outside; the identity below a quarter sample.
fn gaussian_filter(data: &mut [[f64; 3]], side: usize, sigma: f64) {
    if sigma < 0.25 {
        return;
    }
    let kernel = GaussianKernel::new(sigma, 3.5, Normalisation::Outputs);
    if let Err(e) = blur_2d(data, side, side, &kernel, Border::Zero) {
        unreachable!("the table is side x side: {e}");
    }
}

/// Per-pixel data of the entry side, for one projector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EntrySample {
    /// Area-weighted surface point of the pixel, mm.
    pub point: Point3<f64>,
    /// Outward unit normal.
    pub normal: Vector3<f64>,
    /// Unit vector from the point to the light.
    pub to_light: Vector3<f64>,
    /// Surface area seen by the pixel, mm^2.
    pub area_mm2: f64,
    /// Basis material weights (sum 1).
    pub materials: [f32; 4],
}

/// A cell of one level: aggregated entry geometry.
#[derive(Debug, Clone, Copy)]
struct Cell {
    point: [f32; 3],
    forward: [f32; 3],
    side: [f32; 3],
    /// The (material, angle) tables this cell's response mixes: its material weights times the
    /// interpolation weights of the two tabulated angles around its incidence angle.
    taps: [Tap; MAX_TAPS],
    tap_count: u8,
}

impl Cell {
    fn taps(&self) -> &[Tap] {
        &self.taps[..self.tap_count as usize]
    }
}

/// One level of the kernel: the band it covers and its filtered tables.
struct KernelLevel {
    /// Cell size in pixels (`2^level`).
    scale: usize,
    /// Nominal cell size, mm (the scale of the tables' filter).
    cell_mm: f64,
    band: Band,
    /// Every material's and angle's table for this band.
    tables: PackedTables,
    /// Cells to search around an output cell.
    search_radius: isize,
}

/// The banded, filtered responses for one camera view; shared by every projector.
pub struct SubsurfaceKernel {
    angles_deg: Vec<f64>,
    levels: Vec<KernelLevel>,
}

/// Innermost band radius in pixel footprints.
const INNER_BAND_PIXELS: f64 = 4.0;

impl SubsurfaceKernel {
    /// Bands and tables for a view whose pixels cover `pixel_mm` on average and at least
    /// `min_pixel_mm`, at most `max_dim` pixels across.
    pub fn new(responses: &ResponseSet, pixel_mm: f64, min_pixel_mm: f64, max_dim: usize) -> Self {
        let reach = responses
            .grids
            .iter()
            .flatten()
            .map(|g| g.half_extent_mm() * std::f64::consts::SQRT_2)
            .fold(0.0, f64::max);
        let rho0 = INNER_BAND_PIXELS * pixel_mm;
        // Levels until the last band starts past the responses, or cells would exceed the image.
        let mut count = 1;
        while rho0 * f64::powi(2.0, count as i32 - 1) < reach && (1usize << count) < max_dim {
            count += 1;
        }
        let rho = |k: usize| rho0 * f64::powi(2.0, k as i32);
        let levels = (0..count)
            .into_par_iter()
            .map(|j| {
                let band = Band {
                    rho_inner: (j > 0).then(|| rho(j - 1)),
                    rho_outer: (j + 1 < count).then(|| rho(j)),
                };
                let scale = 1usize << j;
                let cell_mm = scale as f64 * pixel_mm;
                let tables = PackedTables::build(
                    &responses.grids,
                    responses.angles_deg.len(),
                    &band,
                    cell_mm,
                    reach,
                );
                let r_max = band.r_max().min(reach) + FILTER_REACH_CELLS * cell_mm;
                let search_radius = (r_max / (scale as f64 * min_pixel_mm)).ceil() as isize + 1;
                KernelLevel {
                    scale,
                    cell_mm,
                    band,
                    tables,
                    search_radius,
                }
            })
            .collect();
        Self {
            angles_deg: responses.angles_deg.clone(),
            levels,
        }
    }
}

/// The cells of one level for one projector's entry geometry.
struct LevelCells {
    width: usize,
    height: usize,
    cells: Vec<Option<Cell>>,
}

/// The subsurface transport of one projector's light on one camera view.
pub struct SubsurfaceOperator<'k> {
    kernel: &'k SubsurfaceKernel,
    width: usize,
    height: usize,
    /// Entry point of every pixel (for the flux moments of the cells).
    points: Vec<Option<[f32; 3]>>,
    levels: Vec<LevelCells>,
}

impl<'k> SubsurfaceOperator<'k> {
    /// Aggregates the entry samples of a `width x height` view (row-major, `None` off the skin)
    /// for every level of `kernel`.
    pub fn new(
        kernel: &'k SubsurfaceKernel,
        width: usize,
        height: usize,
        entries: &[Option<EntrySample>],
    ) -> Self {
        let levels = kernel
            .levels
            .iter()
            .map(|level| {
                let (w, h) = (width.div_ceil(level.scale), height.div_ceil(level.scale));
                LevelCells {
                    width: w,
                    height: h,
                    cells: aggregate(
                        width,
                        height,
                        entries,
                        level.scale,
                        w,
                        h,
                        &kernel.angles_deg,
                    ),
                }
            })
            .collect();
        let points = entries
            .iter()
            .map(|e| e.map(|e| [e.point.x as f32, e.point.y as f32, e.point.z as f32]))
            .collect();
        Self {
            kernel,
            width,
            height,
            points,
            levels,
        }
    }

    /// Exitance at every pixel for `frames` flux images (`flux[pixel * frames + f]`); returns
    /// `exitance[(pixel * 3 + c) * frames + f]`.
    pub fn apply(&self, flux: &[f32], frames: usize) -> Vec<f32> {
        let mut out = vec![0.0f32; self.width * self.height * 3 * frames];
        for (level, cells) in self.kernel.levels.iter().zip(&self.levels) {
            if level.scale == 1 {
                let result = level.evaluate(cells, flux, None, frames);
                out.par_iter_mut()
                    .zip(result.par_iter())
                    .for_each(|(o, r)| *o += r);
            } else {
                let (sum, mf, ms) = self.cell_moments(level.scale, cells, flux, frames);
                let result = level.evaluate(cells, &sum, Some((&mf, &ms)), frames);
                level.interpolate_into(cells, &result, frames, self.width, self.height, &mut out);
            }
        }
        out
    }

    /// Per cell and frame: total flux and its first moments about the cell point along the
    /// cell's forward and side axes.
    fn cell_moments(
        &self,
        scale: usize,
        grid: &LevelCells,
        flux: &[f32],
        frames: usize,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let n = grid.width * grid.height * frames;
        let (mut sum, mut mf, mut ms) = (vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]);
        sum.par_chunks_mut(frames)
            .zip(mf.par_chunks_mut(frames))
            .zip(ms.par_chunks_mut(frames))
            .enumerate()
            .for_each(|(ci, ((s, a), b))| {
                let Some(cell) = &grid.cells[ci] else { return };
                let (cx, cy) = (ci % grid.width, ci / grid.width);
                for y in cy * scale..((cy + 1) * scale).min(self.height) {
                    for x in cx * scale..((cx + 1) * scale).min(self.width) {
                        let i = y * self.width + x;
                        let Some(p) = self.points[i] else { continue };
                        let d = [
                            p[0] - cell.point[0],
                            p[1] - cell.point[1],
                            p[2] - cell.point[2],
                        ];
                        let along = |v: [f32; 3]| v[0] * d[0] + v[1] * d[1] + v[2] * d[2];
                        let (df, ds) = (along(cell.forward), along(cell.side));
                        let src = &flux[i * frames..(i + 1) * frames];
                        for f in 0..frames {
                            s[f] += src[f];
                            a[f] += src[f] * df;
                            b[f] += src[f] * ds;
                        }
                    }
                }
            });
        (sum, mf, ms)
    }
}

/// Adds `sum over pairs of K * flux(source)` (minus the first-moment correction
/// `grad K . m(source)` when `moments` are given) to `acc` = `[c * frames + f]`.
fn sum_pairs(
    pairs: &[Pair],
    flux: &[f32],
    moments: Option<(&[f32], &[f32])>,
    frames: usize,
    acc: &mut [f32],
) {
    let mut f0 = 0;
    while f0 + FRAME_BLOCK <= frames {
        sum_block::<FRAME_BLOCK>(pairs, flux, moments, frames, f0, acc);
        f0 += FRAME_BLOCK;
    }
    for f in f0..frames {
        sum_block::<1>(pairs, flux, moments, frames, f, acc);
    }
}

/// [`sum_pairs`] for frames `f0..f0 + B`.
#[inline(always)]
fn sum_block<const B: usize>(
    pairs: &[Pair],
    flux: &[f32],
    moments: Option<(&[f32], &[f32])>,
    frames: usize,
    f0: usize,
    acc: &mut [f32],
) {
    let mut sum = [[0.0f32; B]; 3];
    match moments {
        None => {
            for p in pairs {
                let at = p.source as usize * frames + f0;
                let phi = &flux[at..at + B];
                for (sum_c, k_c) in sum.iter_mut().zip(p.k) {
                    for j in 0..B {
                        sum_c[j] += k_c * phi[j];
                    }
                }
            }
        }
        Some((along_forward, along_side)) => {
            for p in pairs {
                let at = p.source as usize * frames + f0;
                let (phi, mf, ms) = (
                    &flux[at..at + B],
                    &along_forward[at..at + B],
                    &along_side[at..at + B],
                );
                // A source displaced by m/phi from the cell point sees the offset d - m/phi:
                // first-order correction -grad K . m.
                for (c, sum_c) in sum.iter_mut().enumerate() {
                    let (k, gx, gy) = (p.k[c], p.gx[c], p.gy[c]);
                    for j in 0..B {
                        sum_c[j] += k * phi[j] - (gx * mf[j] + gy * ms[j]);
                    }
                }
            }
        }
    }
    for (c, channel) in sum.iter().enumerate() {
        let at = c * frames + f0;
        for (a, v) in acc[at..at + B].iter_mut().zip(channel) {
            *a += v;
        }
    }
}

/// Area-weighted aggregation of the entry samples into cells of `scale x scale` pixels.
fn aggregate(
    width: usize,
    height: usize,
    entries: &[Option<EntrySample>],
    scale: usize,
    w: usize,
    h: usize,
    angles: &[f64],
) -> Vec<Option<Cell>> {
    (0..w * h)
        .into_par_iter()
        .map(|ci| {
            let (cx, cy) = (ci % w, ci / w);
            let mut area = 0.0;
            let mut p = Vector3::zeros();
            let mut n = Vector3::zeros();
            let mut l = Vector3::zeros();
            let mut m = [0.0f64; 4];
            for y in cy * scale..((cy + 1) * scale).min(height) {
                for x in cx * scale..((cx + 1) * scale).min(width) {
                    if let Some(e) = &entries[y * width + x] {
                        area += e.area_mm2;
                        p += e.point.coords * e.area_mm2;
                        n += e.normal * e.area_mm2;
                        l += e.to_light * e.area_mm2;
                        for (mk, ek) in m.iter_mut().zip(e.materials) {
                            *mk += ek as f64 * e.area_mm2;
                        }
                    }
                }
            }
            if area <= 0.0 {
                return None;
            }
            let n = n.normalize();
            let l = l.normalize();
            let cos_i = n.dot(&l).clamp(0.0, 1.0);
            let (forward, side) = tangent_frame(&n, &l);
            let angle = cos_i.acos().to_degrees();
            let (angle_index, angle_t) = angle_interpolation(angles, angle);
            let (taps, tap_count) = mix_taps(
                &m.map(|x| (x / area) as f32),
                angle_index,
                angle_t,
                angles.len(),
            );
            let f32v = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
            Some(Cell {
                point: f32v(p / area),
                forward: f32v(forward),
                side: f32v(side),
                taps,
                tap_count,
            })
        })
        .collect()
}

/// Forward (tangential, away from the light) and side unit vectors at a surface point.
pub fn tangent_frame(
    normal: &Vector3<f64>,
    to_light: &Vector3<f64>,
) -> (Vector3<f64>, Vector3<f64>) {
    let tangential = -(to_light - normal * normal.dot(to_light));
    let forward = if tangential.norm() > 1e-9 {
        tangential.normalize()
    } else {
        // Normal incidence: the response is radially symmetric, any tangent will do.
        let helper = if normal.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        (helper - normal * normal.dot(&helper)).normalize()
    };
    // MC frame: z into the medium (-normal), y = z x x.
    let side = (-normal).cross(&forward);
    (forward, side)
}

/// Lower index into `angles` and weight towards the next, clamped at both ends.
fn angle_interpolation(angles: &[f64], angle: f64) -> (u16, f32) {
    if angles.len() < 2 || angle <= angles[0] {
        return (0, 0.0);
    }
    for i in 0..angles.len() - 1 {
        if angle <= angles[i + 1] {
            let t = (angle - angles[i]) / (angles[i + 1] - angles[i]);
            return (i as u16, t as f32);
        }
    }
    ((angles.len() - 2) as u16, 1.0)
}

/// One source cell's contribution to an output cell: the band response at their offset and,
/// for aggregated cells, its derivatives along the source's forward and side axes.
#[derive(Debug, Clone, Copy)]
struct Pair {
    source: u32,
    k: [f32; 3],
    gx: [f32; 3],
    gy: [f32; 3],
}

/// Frames are summed in blocks of this many: the block's accumulators stay in registers while
/// every source of an output cell is visited, instead of a read-modify-write of every frame's
/// accumulator per pair.
const FRAME_BLOCK: usize = 8;

impl KernelLevel {
    /// Exitance at each cell of this level from the band's pairs: `[(cell * 3 + c) * frames + f]`.
    /// `moments` holds, per cell and frame, the first moments of the flux about the cell's point
    /// along its forward and side axes (`None` at the pixel level, where cells are points).
    /// The band response of each pair is looked up once and reused for every frame.
    fn evaluate(
        &self,
        grid: &LevelCells,
        flux: &[f32],
        moments: Option<(&[f32], &[f32])>,
        frames: usize,
    ) -> Vec<f32> {
        let (w, h) = (grid.width, grid.height);
        let lit: Vec<bool> = (0..w * h)
            .map(|i| {
                grid.cells[i].is_some()
                    && flux[i * frames..(i + 1) * frames].iter().any(|&v| v > 0.0)
            })
            .collect();
        let mut out = vec![0.0f32; w * h * 3 * frames];
        out.par_chunks_mut(w * 3 * frames)
            .enumerate()
            .for_each_init(Vec::new, |pairs, (oy, row)| {
                for ox in 0..w {
                    let Some(o) = &grid.cells[oy * w + ox] else {
                        continue;
                    };
                    pairs.clear();
                    self.gather_pairs(grid, &lit, o, [ox, oy], moments.is_some(), pairs);
                    let acc = &mut row[ox * 3 * frames..(ox + 1) * 3 * frames];
                    sum_pairs(pairs, flux, moments, frames, acc);
                }
            });
        out
    }

    /// The lit source cells within this band's reach of output cell `o` (at `[ox, oy]`) and
    /// their band responses (with derivatives when `gradient`).
    fn gather_pairs(
        &self,
        grid: &LevelCells,
        lit: &[bool],
        o: &Cell,
        [ox, oy]: [usize; 2],
        gradient: bool,
        pairs: &mut Vec<Pair>,
    ) {
        let (w, h) = (grid.width as isize, grid.height as isize);
        // The tables are filtered, so they reach a little beyond the band.
        let reach = FILTER_REACH_CELLS * self.cell_mm;
        let r_min = (self.band.r_min() - reach).max(0.0) as f32;
        let r_max = (self.band.r_max() + reach) as f32;
        let rad = self.search_radius;
        let (ox, oy) = (ox as isize, oy as isize);
        for sy in (oy - rad).max(0)..(oy + rad + 1).min(h) {
            for sx in (ox - rad).max(0)..(ox + rad + 1).min(w) {
                let si = (sy * w + sx) as usize;
                if !lit[si] {
                    continue;
                }
                let Some(s) = &grid.cells[si] else { continue };
                let d = [
                    o.point[0] - s.point[0],
                    o.point[1] - s.point[1],
                    o.point[2] - s.point[2],
                ];
                let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if r >= r_max || r < r_min {
                    continue;
                }
                let response = if gradient {
                    self.kernel::<true>(s, d, r)
                } else {
                    self.kernel::<false>(s, d, r)
                };
                let Some([k, gx, gy]) = response else {
                    continue;
                };
                if k == [0.0; 3] && gx == [0.0; 3] && gy == [0.0; 3] {
                    continue;
                }
                pairs.push(Pair {
                    source: si as u32,
                    k,
                    gx,
                    gy,
                });
            }
        }
    }

    /// Band response from source cell `s` at offset `d` (world mm, |d| = r), and (when
    /// `GRADIENT`) its derivatives with respect to the offset along the cell's forward and side
    /// axes; `None` beyond the tables.
    #[inline]
    fn kernel<const GRADIENT: bool>(&self, s: &Cell, d: [f32; 3], r: f32) -> Option<[[f32; 3]; 3]> {
        let dot = |a: [f32; 3]| a[0] * d[0] + a[1] * d[1] + a[2] * d[2];
        let (mut x, mut y) = (dot(s.forward), dot(s.side));
        // Keep the 3-D distance: project the offset onto the tangent plane, then rescale.
        let t = (x * x + y * y).sqrt();
        if t > 1e-6 {
            x *= r / t;
            y *= r / t;
        }
        self.tables.lookup::<GRADIENT>(x, y, s.taps())
    }

    /// Adds the bilinear interpolation of this level's cell values to full-resolution pixels,
    /// interpolating only between cells that hold skin.
    fn interpolate_into(
        &self,
        grid: &LevelCells,
        values: &[f32],
        frames: usize,
        width: usize,
        height: usize,
        out: &mut [f32],
    ) {
        let s = self.scale as f32;
        out.par_chunks_mut(width * 3 * frames)
            .enumerate()
            .take(height)
            .for_each(|(y, row)| {
                let gy = (y as f32 + 0.5) / s - 0.5;
                let y0 = gy.floor();
                let ty = gy - y0;
                for x in 0..width {
                    let gx = (x as f32 + 0.5) / s - 0.5;
                    let x0 = gx.floor();
                    let tx = gx - x0;
                    let mut taps = [(0usize, 0.0f32); 4];
                    let mut total = 0.0;
                    let mut count = 0;
                    for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
                        for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                            let cx = (x0 as isize + dx).clamp(0, grid.width as isize - 1) as usize;
                            let cy = (y0 as isize + dy).clamp(0, grid.height as isize - 1) as usize;
                            let ci = cy * grid.width + cx;
                            let w = wx * wy;
                            if w > 0.0 && grid.cells[ci].is_some() {
                                taps[count] = (ci, w);
                                count += 1;
                                total += w;
                            }
                        }
                    }
                    if total <= 0.0 {
                        continue;
                    }
                    let dst = &mut row[x * 3 * frames..(x + 1) * 3 * frames];
                    for &(ci, w) in &taps[..count] {
                        let src = &values[ci * 3 * frames..(ci + 1) * 3 * frames];
                        let w = w / total;
                        for (d, v) in dst.iter_mut().zip(src) {
                            *d += w * v;
                        }
                    }
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A forward-shifted, anisotropic Gaussian response: per-channel widths, known total.
    fn synthetic_response(cell_mm: f64, cells: usize, total: [f64; 3]) -> ResponseGrid {
        let centre = (cells as f64 - 1.0) / 2.0;
        let sigma = [1.5, 0.8, 0.4];
        let shift = 0.3;
        let values = (0..cells * cells)
            .map(|i| {
                let x = (i % cells) as f64 - centre;
                let y = (i / cells) as f64 - centre;
                let (x, y) = (x * cell_mm, y * cell_mm);
                let mut v = [0.0f32; 3];
                for c in 0..3 {
                    let s2 = sigma[c] * sigma[c];
                    let g = (-((x - shift).powi(2) + y * y) / (2.0 * s2)).exp()
                        / (2.0 * std::f64::consts::PI * s2);
                    v[c] = (total[c] * g) as f32;
                }
                v
            })
            .collect();
        ResponseGrid {
            cell_mm,
            cells,
            values,
        }
    }

    fn plane_entries(
        w: usize,
        h: usize,
        pixel_mm: f64,
        light: Vector3<f64>,
    ) -> Vec<Option<EntrySample>> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                Some(EntrySample {
                    point: Point3::new(x * pixel_mm, y * pixel_mm, 0.0),
                    normal: -Vector3::z(),
                    to_light: light,
                    area_mm2: pixel_mm * pixel_mm,
                    materials: [1.0, 0.0, 0.0, 0.0],
                })
            })
            .collect()
    }

    fn response_set(grid: ResponseGrid) -> ResponseSet {
        ResponseSet {
            angles_deg: vec![0.0],
            grids: vec![
                vec![grid.clone()],
                vec![grid.clone()],
                vec![grid.clone()],
                vec![grid],
            ],
        }
    }

    /// The packed, interleaved tables give the same mix as looking every (material, angle)
    /// table up on its own and weighting the results (the evaluation before packing).
    #[test]
    fn packed_lookup_equals_the_weighted_per_table_lookups() {
        let angles = [0.0, 40.0, 80.0];
        let grids: Vec<Vec<ResponseGrid>> = (0..4)
            .map(|m| {
                angles
                    .iter()
                    .map(|&a| {
                        let t = 0.1 * (m + 1) as f64 + a / 400.0;
                        synthetic_response(0.2, 41, [t, 0.5 * t, 0.25 * t])
                    })
                    .collect()
            })
            .collect();
        let band = Band {
            rho_inner: Some(0.5),
            rho_outer: Some(1.0),
        };
        let (cell_mm, reach) = (0.4, 0.5 * 41.0 * 0.2 * std::f64::consts::SQRT_2);
        let packed = PackedTables::build(&grids, angles.len(), &band, cell_mm, reach);
        let spacing = TABLE_SPACING_CELLS * cell_mm;
        let reference: Vec<Vec<BandTable>> = grids
            .iter()
            .map(|per_angle| {
                per_angle
                    .iter()
                    .map(|g| BandTable::build(g, &band, cell_mm, spacing, packed.half))
                    .collect()
            })
            .collect();
        let materials = [0.55, 0.3, 0.0, 0.15];
        let (angle_index, angle_t) = (1u16, 0.3f32);
        let (taps, count) = mix_taps(&materials, angle_index, angle_t, angles.len());
        assert_eq!(count, 6, "three materials x two angles");
        for i in 0..200 {
            let (x, y) = (-3.0 + 0.031 * i as f32, 2.5 * (0.37 * i as f32).sin());
            let mut expected = [[0.0f32; 3]; 3];
            for (m, &wm) in materials.iter().enumerate() {
                if wm <= 1e-4 {
                    continue;
                }
                for (a, wa) in [(1, 1.0 - angle_t), (2, angle_t)] {
                    let v = reference[m][a].lookup(x, y);
                    for (e, v) in expected.iter_mut().zip(v) {
                        for c in 0..3 {
                            e[c] += wm * wa * v[c];
                        }
                    }
                }
            }
            let got = packed
                .lookup::<true>(x, y, &taps[..count as usize])
                .unwrap_or([[0.0; 3]; 3]);
            // Only float rounding may differ (the mix is summed in another order; gradients
            // are differences scaled by 1 / spacing).
            let scale = expected
                .iter()
                .flatten()
                .fold(1e-6f32, |m, v| m.max(v.abs()));
            for (g, e) in got.iter().zip(&expected) {
                for c in 0..3 {
                    assert!(
                        (g[c] - e[c]).abs() <= 1e-5 * scale,
                        "({x}, {y}): packed {got:?}, per table {expected:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn bands_partition_the_response() {
        let rho0 = 0.75;
        let count = 5;
        for i in 0..200 {
            let r = i as f64 * 0.1;
            let total: f64 = (0..count)
                .map(|j| {
                    Band {
                        rho_inner: (j > 0).then(|| rho0 * f64::powi(2.0, j - 1)),
                        rho_outer: (j + 1 < count).then(|| rho0 * f64::powi(2.0, j)),
                    }
                    .weight(r)
                })
                .sum();
            assert!((total - 1.0).abs() < 1e-12, "r {r}: {total}");
        }
    }

    #[test]
    fn uniform_light_with_pixels_wider_than_the_response_keeps_the_total() {
        let (w, h, pixel_mm) = (40, 40, 1.0);
        let mut grid = synthetic_response(0.333, 61, [0.6, 0.4, 0.2]);
        // Blue: half the energy in the central cell (much sharper than a pixel), like skin.
        let centre = 30 * 61 + 30;
        let cell_area = 0.333 * 0.333;
        for v in grid.values.iter_mut() {
            v[2] *= 0.5;
        }
        grid.values[centre][2] += (0.1 / cell_area) as f32;
        let totals = grid.total();
        let kernel = SubsurfaceKernel::new(&response_set(grid), pixel_mm, pixel_mm, w.max(h));
        // Light from a diagonal: the pixel lattice is rotated 45 degrees against the tables.
        let light = Vector3::new(-0.4, -0.4, -0.82).normalize();
        let entries = plane_entries(w, h, pixel_mm, light);
        let op = SubsurfaceOperator::new(&kernel, w, h, &entries);
        let flux = vec![(pixel_mm * pixel_mm) as f32; w * h];
        let out = op.apply(&flux, 1);
        let centre = (h / 2) * w + w / 2;
        for c in 0..3 {
            let m = out[centre * 3 + c] as f64;
            assert!(
                (m / totals[c] - 1.0).abs() < 0.01,
                "channel {c}: {m} vs {}",
                totals[c]
            );
        }
    }

    #[test]
    fn uniform_light_on_a_plane_gives_the_response_total() {
        // Far from the edges, uniform entry flux E per area gives exitance E * total.
        let (w, h, pixel_mm) = (96, 96, 0.25);
        let grid = synthetic_response(0.05, 301, [0.6, 0.4, 0.2]);
        let totals = grid.total();
        let kernel = SubsurfaceKernel::new(&response_set(grid), pixel_mm, pixel_mm, w.max(h));
        let entries = plane_entries(w, h, pixel_mm, -Vector3::z());
        let op = SubsurfaceOperator::new(&kernel, w, h, &entries);
        let flux = vec![(pixel_mm * pixel_mm) as f32; w * h];
        let out = op.apply(&flux, 1);
        let centre = (h / 2) * w + w / 2;
        for c in 0..3 {
            let m = out[centre * 3 + c] as f64;
            assert!(
                (m / totals[c] - 1.0).abs() < 0.01,
                "channel {c}: {m} vs {}",
                totals[c]
            );
        }
    }

    #[test]
    fn a_lit_line_gives_the_brute_force_profile() {
        // One lit column: the exitance profile across it matches the direct pairwise sum of the
        // (unfiltered) response, including its forward shift.
        let (w, h, pixel_mm) = (128, 64, 0.25);
        let grid = synthetic_response(0.05, 301, [0.6, 0.4, 0.2]);
        // Light from -x: forward is +x.
        let light = Vector3::new(-0.5, 0.0, -(0.75f64).sqrt());
        let entries = plane_entries(w, h, pixel_mm, light);
        let kernel =
            SubsurfaceKernel::new(&response_set(grid.clone()), pixel_mm, pixel_mm, w.max(h));
        let op = SubsurfaceOperator::new(&kernel, w, h, &entries);
        let lit_x = 50;
        let flux: Vec<f32> = (0..w * h)
            .map(|i| {
                if i % w == lit_x {
                    (pixel_mm * pixel_mm) as f32
                } else {
                    0.0
                }
            })
            .collect();
        let out = op.apply(&flux, 1);
        let row = h / 2;
        // Brute force: sum over the lit column of the response sampled with 5x5 sub-cells.
        let centre = grid.centre_index();
        let sample = |x: f64, y: f64, c: usize| -> f64 {
            let fx = x / grid.cell_mm + centre;
            let fy = y / grid.cell_mm + centre;
            if fx < 0.0
                || fy < 0.0
                || fx >= grid.cells as f64 - 1.0
                || fy >= grid.cells as f64 - 1.0
            {
                return 0.0;
            }
            let (ix, iy) = (fx.round() as usize, fy.round() as usize);
            grid.values[iy * grid.cells + ix][c] as f64
        };
        let dxs = [-12i32, -6, -3, -1, 0, 1, 2, 4, 8, 16, 30];
        let mut results = Vec::new();
        for dx in dxs {
            let ox = (lit_x as i32 + dx) as usize;
            for c in 0..3 {
                // Direct sum over the lit column, each pair weighted by the pixel footprint
                // model (isotropic Gaussian of FILTER_SIGMA_CELLS pixels, 9x9 quadrature).
                let sigma = FILTER_SIGMA_CELLS;
                let taps: Vec<(f64, f64)> = (-4..=4)
                    .map(|k| {
                        let o = k as f64 * sigma * 0.75;
                        (o, (-0.5 * (o / sigma).powi(2)).exp())
                    })
                    .collect();
                let norm: f64 = taps.iter().map(|t| t.1).sum::<f64>().powi(2);
                let mut brute = 0.0;
                for sy in 0..h {
                    for &(ox_, wx) in &taps {
                        for &(oy_, wy) in &taps {
                            let x = (dx as f64 + ox_) * pixel_mm;
                            let y = (row as f64 - sy as f64 + oy_) * pixel_mm;
                            brute += sample(x, y, c) * (pixel_mm * pixel_mm) * wx * wy / norm;
                        }
                    }
                }
                let got = out[(row * w + ox) * 3 + c] as f64;
                results.push((dx, c, got, brute));
            }
        }
        // Within 1 % of the peak at the line, within 3 % of the peak everywhere (the band
        // transitions are where cell aggregation errs most).
        for c in 0..3 {
            let peak = results
                .iter()
                .filter(|r| r.1 == c)
                .map(|r| r.3)
                .fold(0.0, f64::max);
            for &(dx, _, got, brute) in results.iter().filter(|r| r.1 == c) {
                let tolerance = if dx.abs() <= 1 { 0.01 } else { 0.03 } * peak;
                assert!(
                    (got - brute).abs() < tolerance,
                    "dx {dx} channel {c}: hierarchical {got}, brute force {brute}, peak {peak}"
                );
            }
        }
    }
}

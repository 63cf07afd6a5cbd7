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
//! is second order in cell size over distance; energy is conserved by construction (the bands
//! sum to the full response), up to the filtered tables' ends `FILTER_REACH_CELLS` beyond their
//! band (below 5e-5 of a response per band: `the_filtered_bands_end_within_the_reach`). This is
//! the hierarchical evaluation of Jensen & Buhler 2002 ("A rapid hierarchical rendering technique
//! for translucent materials") on the camera grid.
//!
//! Conventions
//! - Response grids: exitance per unit incident power, 1/mm^2, per channel, on square cells
//!   centred on the entry point; x forward (away from the light), y to the side.
//! - Flux: power entering at a pixel (irradiance x area), per frame; exitance: power per mm^2
//!   leaving at a pixel, per channel and frame. Layout `flux[pixel * frames + f]`,
//!   `exitance[(pixel * 3 + c) * frames + f]`.

use mlsss_core::resources::zeros_written;
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

mod tables;
#[cfg(test)]
mod tests;

use tables::*;

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

/// A cell of one level: its aggregated response (its geometry is in [`CellAxes`]).
#[derive(Debug, Clone, Copy)]
struct Cell {
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

/// A cell's aggregated geometry: its point and tangent frame (forward, away from the light, and
/// side), world mm.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CellFrame {
    point: [f32; 3],
    forward: [f32; 3],
    side: [f32; 3],
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

/// Innermost band radius `rho_0` in pixel footprints, the kernel's quality knob: band 0 (up to
/// `2 rho_0`) is summed pixel by pixel, and band `j` sees cells at least `rho_0 / 2` cells
/// apart. Most of the work is the pairs within `2 rho_0` of a cell (about `(2 rho_0)^2`).
/// Measured on the quick head scan (seed 1, skin II, 10k photons; truth global images of every
/// projector against `rho_0` = 8 px): 4 px errs 0.06-0.31 % relative RMS, 3 px 0.13-0.59 %,
/// for 11.4 against 8.6 CPU-s of the whole scan; the Monte Carlo noise of the shipped 10k
/// photons against 40k is 0.79-0.94 % on the same images. Next to a lit line of a sharply
/// peaked synthetic response (`a_lit_line_gives_the_brute_force_profile`), the worst pixel errs
/// 0.9 % (at the line) and 3.0 % (band transitions) of the peak at 4 px, 2.4 % and 4.0 % at 3 px.
pub const INNER_BAND_PIXELS: f64 = 4.0;

/// The smallest [`INNER_BAND_PIXELS`] the bands allow: with `rho_0` = 3 px an aggregated band's
/// cells are still 1.5 cells apart, where the response is smooth over a cell.
pub const MIN_INNER_BAND_PIXELS: f64 = 3.0;

impl SubsurfaceKernel {
    /// Bands and tables for a view whose pixels cover `pixel_mm` on average and at least
    /// `min_pixel_mm`, at most `max_dim` pixels across, with the innermost band `inner_band_px`
    /// pixels wide ([`INNER_BAND_PIXELS`]; values below [`MIN_INNER_BAND_PIXELS`], or not a
    /// number, are raised to it).
    pub fn new(
        responses: &ResponseSet,
        pixel_mm: f64,
        min_pixel_mm: f64,
        max_dim: usize,
        inner_band_px: f64,
    ) -> Self {
        let reach = responses
            .grids
            .iter()
            .flatten()
            .map(|g| g.half_extent_mm() * std::f64::consts::SQRT_2)
            .fold(0.0, f64::max);
        let rho0 = inner_band_px.max(MIN_INNER_BAND_PIXELS) * pixel_mm;
        // Levels until the last band starts past the responses, or cells would exceed the image.
        let mut count = 1;
        while rho0 * f64::powi(2.0, count as i32 - 1) < reach && (1usize << count) < max_dim {
            count += 1;
        }
        let levels = (0..count)
            .into_par_iter()
            .map(|j| {
                let band = Band::of_level(j, count, rho0);
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
    /// The cells' geometry by coordinate, apart from their responses: the search around an
    /// output cell reads every candidate's point and axes, the response (~70 bytes) of the few
    /// within reach only. Held here alone (the cells held a copy, 36 bytes a cell, until the
    /// full-size scan's peak rose 0.1-0.3 GB with it).
    axes: CellAxes,
}

impl LevelCells {
    fn new(aggregated: Vec<Option<(CellFrame, Cell)>>, width: usize, height: usize) -> Self {
        let axes = CellAxes::new(&aggregated);
        let mut cells: Vec<Option<Cell>> = aggregated
            .into_iter()
            .map(|c| c.map(|(_, cell)| cell))
            .collect();
        // The collect may reuse the aggregate's larger allocation: give the rest back.
        cells.shrink_to_fit();
        Self {
            width,
            height,
            cells,
            axes,
        }
    }
}

/// Every cell's point, forward and side axes as one array per coordinate (zero where there is
/// no cell, and for [`TILE_CELLS`] cells past the last): the distance and tangent offset of the
/// pairs of a tile's row at one source offset are then computed side by side, one vector lane
/// per pair, on [`TILE_CELLS`] consecutive cells from any cell (see
/// [`KernelLevel::tile_candidates`]).
struct CellAxes {
    point: [Vec<f32>; 3],
    forward: [Vec<f32>; 3],
    side: [Vec<f32>; 3],
}

impl CellAxes {
    fn new(cells: &[Option<(CellFrame, Cell)>]) -> Self {
        let coordinate = |of: fn(&CellFrame) -> [f32; 3], axis: usize| -> Vec<f32> {
            padded(
                cells
                    .iter()
                    .map(|c| c.as_ref().map_or(0.0, |(frame, _)| of(frame)[axis])),
            )
        };
        let vector =
            |of: fn(&CellFrame) -> [f32; 3]| std::array::from_fn(|axis| coordinate(of, axis));
        Self {
            point: vector(|f| f.point),
            forward: vector(|f| f.forward),
            side: vector(|f| f.side),
        }
    }

    /// Cell `ci`'s frame (zeros where there is no cell).
    fn frame(&self, ci: usize) -> CellFrame {
        let at = |v: &[Vec<f32>; 3]| [v[0][ci], v[1][ci], v[2][ci]];
        CellFrame {
            point: at(&self.point),
            forward: at(&self.forward),
            side: at(&self.side),
        }
    }
}

/// `values` followed by [`TILE_CELLS`] defaults: any cell starts a full run of lanes.
fn padded<T: Default + Clone>(values: impl Iterator<Item = T>) -> Vec<T> {
    let mut out: Vec<T> = values.collect();
    out.resize(out.len() + TILE_CELLS, T::default());
    out
}

/// The [`TILE_CELLS`] values of `values` from `start` (a padded array, see [`padded`]).
#[inline(always)]
fn lanes<T>(values: &[T], start: usize) -> &[T; TILE_CELLS] {
    match values[start..start + TILE_CELLS].try_into() {
        Ok(lanes) => lanes,
        Err(_) => unreachable!("the slice has TILE_CELLS values"),
    }
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
            .map(|level| aggregate(width, height, entries, level, &kernel.angles_deg))
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
        self.apply_with(flux, frames, RowIsa::detect())
    }

    /// [`Self::apply`] with the rows compiled for `isa`.
    fn apply_with(&self, flux: &[f32], frames: usize, isa: RowIsa) -> Vec<f32> {
        let mut out = zeros_written(self.width * self.height * 3 * frames);
        for (level, cells) in self.kernel.levels.iter().zip(&self.levels) {
            if level.scale == 1 {
                // Pixel cells are the output pixels: summed in place (no second full-size
                // buffer, 12 bytes per pixel and frame less at the batch's peak).
                level.evaluate_into(cells, flux, None, frames, isa, &mut out);
            } else {
                let (sum, mf, ms) = self.cell_moments(level.scale, cells, flux, frames);
                let mut result = zeros_written(cells.width * cells.height * 3 * frames);
                level.evaluate_into(cells, &sum, Some((&mf, &ms)), frames, isa, &mut result);
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
        let (mut sum, mut mf, mut ms) = (zeros_written(n), zeros_written(n), zeros_written(n));
        sum.par_chunks_mut(frames)
            .zip(mf.par_chunks_mut(frames))
            .zip(ms.par_chunks_mut(frames))
            .enumerate()
            .for_each(|(ci, ((s, a), b))| {
                if grid.cells[ci].is_none() {
                    return;
                }
                let cell = grid.axes.frame(ci);
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
/// `grad K . m(source)` when `moments` are given) to `acc` = `[c * frames + f]`, in blocks of
/// frames (see [`FRAME_BLOCK`]): of `WIDE` at the pixel level, where pairs carry no gradient.
#[inline(always)]
fn sum_pairs<const WIDE: usize>(
    pairs: &CellPairs,
    flux: &[f32],
    moments: Option<(&[f32], &[f32])>,
    frames: usize,
    acc: &mut [f32],
) {
    // With the moments, blocks of 16 were summed one frame at a time (not vectorised).
    match moments {
        None => sum_in_blocks::<WIDE>(pairs, flux, None, frames, acc),
        Some(_) => sum_in_blocks::<FRAME_BLOCK>(pairs, flux, moments, frames, acc),
    }
}

/// [`sum_pairs`] in blocks of `B` frames, then [`FRAME_BLOCK`], then one by one: each block is
/// one pass over the pairs, and each frame's sum runs over the pairs in the same order whatever
/// its block.
#[inline(always)]
fn sum_in_blocks<const B: usize>(
    pairs: &CellPairs,
    flux: &[f32],
    moments: Option<(&[f32], &[f32])>,
    frames: usize,
    acc: &mut [f32],
) {
    let mut f0 = 0;
    while f0 + B <= frames {
        sum_block::<B>(pairs, flux, moments, frames, f0, acc);
        f0 += B;
    }
    if B > FRAME_BLOCK && f0 + FRAME_BLOCK <= frames {
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
    pairs: &CellPairs,
    flux: &[f32],
    moments: Option<(&[f32], &[f32])>,
    frames: usize,
    f0: usize,
    acc: &mut [f32],
) {
    let mut sum = [[0.0f32; B]; 3];
    match moments {
        None => {
            for p in &pairs.pairs {
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
            for (p, g) in pairs.pairs.iter().zip(&pairs.gradients) {
                let at = p.source as usize * frames + f0;
                let (phi, mf, ms) = (
                    &flux[at..at + B],
                    &along_forward[at..at + B],
                    &along_side[at..at + B],
                );
                // A source displaced by m/phi from the cell point sees the offset d - m/phi:
                // first-order correction -grad K . m.
                for (c, sum_c) in sum.iter_mut().enumerate() {
                    let (k, gx, gy) = (p.k[c], g.gx[c], g.gy[c]);
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

/// Area-weighted aggregation of the entry samples of a `width x height` view into the cells of
/// `level` (`scale x scale` pixels), their taps into its tables of `angles`.
fn aggregate(
    width: usize,
    height: usize,
    entries: &[Option<EntrySample>],
    level: &KernelLevel,
    angles: &[f64],
) -> LevelCells {
    let scale = level.scale;
    let (w, h) = (width.div_ceil(scale), height.div_ceil(scale));
    let cells = (0..w * h)
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
                level.tables.plane,
            );
            let f32v = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
            let frame = CellFrame {
                point: f32v(p / area),
                forward: f32v(forward),
                side: f32v(side),
            };
            Some((frame, Cell { taps, tap_count }))
        })
        .collect();
    LevelCells::new(cells, w, h)
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

/// Half-width of the search window's row `dy` cells from the output cell: the window is the
/// disc of cells that can hold a source within reach, not the whole square of radius `rad`.
/// `rad - 1` cells bound the reach (see [`SubsurfaceKernel::new`]) and two cell points `d`
/// cells apart along an axis are at least `|d| - 1` cells apart on it: a cell whose
/// `(|dx| - 1, |dy| - 1)` lies outside the radius `rad - 1` is out of reach (the distance test
/// would reject it), so the disc finds the same pairs in the same order as the square.
#[inline(always)]
fn disc_half_width(rad: isize, dy: isize) -> isize {
    let ey = (dy.abs() - 1).max(0);
    let r = (rad - 1).max(0);
    let room = r * r - ey * ey;
    if room < 0 {
        return -1;
    }
    ((room as f64).sqrt().floor() as isize + 1).min(rad)
}

/// One source cell's contribution to an output cell: the band response at their offset.
#[derive(Debug, Clone, Copy)]
struct Pair {
    source: u32,
    k: [f32; 3],
}

/// The derivatives of a pair's band response along the source's forward and side axes (for
/// aggregated cells).
#[derive(Debug, Clone, Copy)]
struct Gradient {
    gx: [f32; 3],
    gy: [f32; 3],
}

/// The pairs of one output cell, with their gradients at aggregated levels (none at the pixel
/// level). Apart, not in one 40-byte pair: at the pixel level, where most pairs are, a tile's
/// lists (~300 pairs a cell, 32 cells) take 16 bytes a pair of the core's cache instead of 40,
/// leaving more of it to the tables' texels: the quick head scan (one thread each, side by
/// side) took 45.9 CPU-s against 46.6-47.3, the same exitance bit for bit.
#[derive(Default)]
struct CellPairs {
    pairs: Vec<Pair>,
    gradients: Vec<Gradient>,
}

/// A source cell within reach of one output cell of a tile, for one source offset: the first
/// pass of [`KernelLevel::gather_tile`] finds them, the second looks their responses up.
///
/// Gathering pair by pair, each pair was one long chain of dependent operations (distance,
/// square root, projection, a second square root and a division, the table index, the texel
/// loads, the mix over the taps, the bilinear weights) of some 300 instructions, too long
/// for the core to overlap the next pair's: the gather ran at ~125 cycles a pair whether its
/// tables were in the L1 cache or not, and fewer instructions in the mix changed nothing.
/// Split in two passes, the independent pairs of a tile sit side by side in each.
#[derive(Debug, Clone, Copy, Default)]
struct Candidate {
    /// The output cell's place in the tile.
    slot: u8,
    source: u32,
    /// The offset in the source's tangent frame (see [`tangent_offset`]), mm.
    x: f32,
    y: f32,
}

/// The offset `d` (world mm, |d| = r) from source cell `s` in its forward and side axes, where
/// its band tables are looked up: the reference of [`KernelLevel::tile_candidates`], which
/// computes it for a tile's pairs side by side.
#[cfg(test)]
fn tangent_offset(s: &CellFrame, d: [f32; 3], r: f32) -> (f32, f32) {
    let dot = |a: [f32; 3]| a[0] * d[0] + a[1] * d[1] + a[2] * d[2];
    let (mut x, mut y) = (dot(s.forward), dot(s.side));
    // Keep the 3-D distance: project the offset onto the tangent plane, then rescale.
    let t = (x * x + y * y).sqrt();
    if t > 1e-6 {
        x *= r / t;
        y *= r / t;
    }
    (x, y)
}

/// What every output row of one level's evaluation reads.
struct RowInputs<'a> {
    grid: &'a LevelCells,
    /// Per cell: on the skin and lit in some frame ([`padded`]).
    lit: &'a [bool],
    /// Per cell: on the skin ([`padded`]).
    on_skin: &'a [bool],
    flux: &'a [f32],
    moments: Option<(&'a [f32], &'a [f32])>,
    frames: usize,
}

/// The instruction set the rows of [`KernelLevel::evaluate_into`] are compiled for: the same
/// code in every case (no fused multiply-add), so the same results bit for bit; wider vectors
/// only. AVX-512 is about 3 % faster than AVX2 over a quick scan on an AVX-512 CPU (the table
/// lookups of the pair gathering dominate, not the sums).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum RowIsa {
    Baseline,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl RowIsa {
    /// The widest this CPU runs.
    fn detect() -> Self {
        Self::available().last().copied().unwrap_or(Self::Baseline)
    }

    /// Every one this CPU runs, narrowest first.
    fn available() -> Vec<Self> {
        #[allow(unused_mut)]
        let mut isas = vec![Self::Baseline];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                isas.push(Self::Avx2);
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                isas.push(Self::Avx512);
            }
        }
        isas
    }
}

/// Output cells whose pairs are gathered together, offset by offset (see
/// [`KernelLevel::gather_tile`]): a tile's pair lists (a few hundred 40-byte pairs per cell)
/// stay in the core's cache while they are summed. 32, not 16: each texel read at one source
/// offset serves twice the output cells; the quick scan (seed 1, single-threaded, side by side
/// with 16) took 15.6-15.9 CPU-s against 16.4-16.5, the same frames. At most 32:
/// [`KernelLevel::tile_candidates`] keeps a tile's lanes in a `u32` mask.
const TILE_CELLS: usize = 32;
const _: () = assert!(TILE_CELLS <= 32);

/// Scratch of one worker: the pair list of every output cell of a tile.
#[derive(Default)]
struct TilePairs(Vec<CellPairs>);

/// Frames are summed in blocks of this many: the block's accumulators stay in registers while
/// every source of an output cell is visited, instead of a read-modify-write of every frame's
/// accumulator per pair.
const FRAME_BLOCK: usize = 8;
/// The block of AVX-512, whose registers hold 16 frames: 40 frames take three passes over the
/// pairs instead of five.
const WIDE_FRAME_BLOCK: usize = 16;

impl KernelLevel {
    /// Adds the exitance at each cell of this level from the band's pairs to `out`
    /// (`[(cell * 3 + c) * frames + f]`).
    /// `moments` holds, per cell and frame, the first moments of the flux about the cell's point
    /// along its forward and side axes (`None` at the pixel level, where cells are points).
    /// The band response of each pair is looked up once and reused for every frame.
    fn evaluate_into(
        &self,
        grid: &LevelCells,
        flux: &[f32],
        moments: Option<(&[f32], &[f32])>,
        frames: usize,
        isa: RowIsa,
        out: &mut [f32],
    ) {
        let (w, h) = (grid.width, grid.height);
        let lit: Vec<bool> = (0..w * h)
            .map(|i| {
                grid.cells[i].is_some()
                    && flux[i * frames..(i + 1) * frames].iter().any(|&v| v > 0.0)
            })
            .collect();
        let lit = padded(lit.into_iter());
        let on_skin = padded(grid.cells.iter().map(Option::is_some));
        let rows = RowInputs {
            grid,
            lit: &lit,
            on_skin: &on_skin,
            flux,
            moments,
            frames,
        };
        out.par_chunks_mut(w * 3 * frames)
            .enumerate()
            .for_each_init(TilePairs::default, |pairs, (oy, row)| match isa {
                RowIsa::Baseline => self.evaluate_row::<FRAME_BLOCK>(&rows, oy, row, pairs),
                // SAFETY: `RowIsa::available` detected AVX2 on this CPU.
                #[cfg(target_arch = "x86_64")]
                RowIsa::Avx2 => unsafe { self.evaluate_row_avx2(&rows, oy, row, pairs) },
                // SAFETY: `RowIsa::available` detected AVX-512F on this CPU.
                #[cfg(target_arch = "x86_64")]
                RowIsa::Avx512 => unsafe { self.evaluate_row_avx512(&rows, oy, row, pairs) },
            });
    }

    /// Output row `oy` of [`Self::evaluate_into`] (`row` = its cells' accumulators; `pairs`
    /// is scratch), [`TILE_CELLS`] output cells at a time.
    #[inline(always)]
    fn evaluate_row<const BLOCK: usize>(
        &self,
        rows: &RowInputs,
        oy: usize,
        row: &mut [f32],
        pairs: &mut TilePairs,
    ) {
        let (grid, frames) = (rows.grid, rows.frames);
        let w = grid.width;
        for first in (0..w).step_by(TILE_CELLS) {
            let tile = first..(first + TILE_CELLS).min(w);
            self.gather_tile(rows, oy, tile.clone(), pairs);
            for (ox, cell_pairs) in tile.zip(&pairs.0) {
                if grid.cells[oy * w + ox].is_none() {
                    continue;
                }
                let acc = &mut row[ox * 3 * frames..(ox + 1) * 3 * frames];
                sum_pairs::<BLOCK>(cell_pairs, rows.flux, rows.moments, frames, acc);
            }
        }
    }

    /// [`Self::evaluate_row`] compiled for AVX2: the same operations in the same order (no
    /// fused multiply-add), so the same results bit for bit, on wider vectors.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn evaluate_row_avx2(
        &self,
        rows: &RowInputs,
        oy: usize,
        row: &mut [f32],
        pairs: &mut TilePairs,
    ) {
        self.evaluate_row::<FRAME_BLOCK>(rows, oy, row, pairs);
    }

    /// [`Self::evaluate_row`] compiled for AVX-512: the same operations in the same order (no
    /// fused multiply-add), so the same results bit for bit, on 16-lane vectors.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn evaluate_row_avx512(
        &self,
        rows: &RowInputs,
        oy: usize,
        row: &mut [f32],
        pairs: &mut TilePairs,
    ) {
        self.evaluate_row::<WIDE_FRAME_BLOCK>(rows, oy, row, pairs);
    }

    /// For every output cell of row `oy`, columns `tile`: the lit source cells within this
    /// band's reach and their band responses (with derivatives at aggregated levels), into
    /// `pairs` (one list per cell of the tile, in raster order of the sources).
    ///
    /// The tile's cells are visited offset by offset: for one source offset, neighbouring output
    /// cells look up nearly the same texels of the tables (a source one cell further away sits
    /// one cell further along), so the texels they read are still in cache. Visited cell by
    /// cell, each lookup of a cell's few hundred pairs missed the cache (the tables are several
    /// MB). Each cell's list holds the same pairs in the same order either way.
    #[inline(always)]
    fn gather_tile(
        &self,
        rows: &RowInputs,
        oy: usize,
        tile: std::ops::Range<usize>,
        pairs: &mut TilePairs,
    ) {
        let grid = rows.grid;
        let gradient = rows.moments.is_some();
        let (w, h) = (grid.width as isize, grid.height as isize);
        // The tables are filtered, so they reach a little beyond the band.
        let reach = FILTER_REACH_CELLS * self.cell_mm;
        let r_min = (self.band.r_min() - reach).max(0.0) as f32;
        let r_max = (self.band.r_max() + reach) as f32;
        let rad = self.search_radius;
        let oy = oy as isize;
        pairs.0.resize_with(tile.len(), CellPairs::default);
        pairs.0.truncate(tile.len());
        for list in &mut pairs.0 {
            list.pairs.clear();
            list.gradients.clear();
        }
        let mut found = [Candidate::default(); TILE_CELLS];
        for sy in (oy - rad).max(0)..(oy + rad + 1).min(h) {
            let half = disc_half_width(rad, sy - oy);
            for dx in -half..=half {
                // Two passes over the tile: the geometry of every candidate first, then the
                // lookups of those within reach (see [`Candidate`]).
                // The tile's cells whose source, `dx` columns away, is inside the grid.
                let first = (tile.start as isize).max(-dx);
                let end = (tile.end as isize).min(w - dx);
                if first >= end {
                    continue;
                }
                let outputs = (oy * w + first) as usize..(oy * w + end) as usize;
                let count = self.tile_candidates(
                    rows,
                    outputs,
                    (sy * w + first + dx) as usize,
                    (first as usize - tile.start) as u8,
                    [r_min, r_max],
                    &mut found,
                );
                for c in &found[..count] {
                    let Some(s) = &grid.cells[c.source as usize] else {
                        continue;
                    };
                    let response = if gradient {
                        self.tables.lookup::<true>(c.x, c.y, s.taps())
                    } else {
                        self.tables.lookup::<false>(c.x, c.y, s.taps())
                    };
                    let Some([k, gx, gy]) = response else {
                        continue;
                    };
                    if k == [0.0; 3] && gx == [0.0; 3] && gy == [0.0; 3] {
                        continue;
                    }
                    let Some(list) = pairs.0.get_mut(c.slot as usize) else {
                        continue;
                    };
                    list.pairs.push(Pair {
                        source: c.source,
                        k,
                    });
                    if gradient {
                        list.gradients.push(Gradient { gx, gy });
                    }
                }
            }
        }
    }

    /// The candidates of [`Self::gather_tile`] for the output cells `outputs` (consecutive cells
    /// of one row, the first in slot `first_slot` of the tile) and their sources, as many cells
    /// on from `sources_start`: those on the skin, lit, at a distance in `[r_min, r_max)`, with
    /// their tangent offsets (as [`tangent_offset`] computes them), into `found` in slot order;
    /// returns how many.
    ///
    /// The geometry of every pair is computed, within reach or not, without a branch (`&`, not
    /// `&&`; the ratio divided before the test that selects it): the same operations on each
    /// pair's coordinates, which the compiler then runs one pair per vector lane, 16 on AVX-512
    /// (the same results bit for bit as one pair at a time; no fused multiply-add). Pair by
    /// pair, with branches, this pass was a quarter of the gather's time.
    #[inline(always)]
    fn tile_candidates(
        &self,
        rows: &RowInputs,
        outputs: std::ops::Range<usize>,
        sources_start: usize,
        first_slot: u8,
        [r_min, r_max]: [f32; 2],
        found: &mut [Candidate; TILE_CELLS],
    ) -> usize {
        let n = outputs.len().min(TILE_CELLS);
        let (o0, s0) = (outputs.start, sources_start);
        let axes = &rows.grid.axes;
        let o = axes.point.each_ref().map(|v| lanes(v, o0));
        let p = axes.point.each_ref().map(|v| lanes(v, s0));
        let forward = axes.forward.each_ref().map(|v| lanes(v, s0));
        let side = axes.side.each_ref().map(|v| lanes(v, s0));
        let (lit, on_skin) = (lanes(rows.lit, s0), lanes(rows.on_skin, o0));
        let (mut xs, mut ys) = ([0.0f32; TILE_CELLS], [0.0f32; TILE_CELLS]);
        let mut keep = 0u32;
        for j in 0..TILE_CELLS {
            let d = [o[0][j] - p[0][j], o[1][j] - p[1][j], o[2][j] - p[2][j]];
            let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let within = !((r >= r_max) | (r < r_min));
            let dot =
                |a: &[&[f32; TILE_CELLS]; 3]| a[0][j] * d[0] + a[1][j] * d[1] + a[2][j] * d[2];
            let (x, y) = (dot(&forward), dot(&side));
            // As in [`tangent_offset`]: keep the 3-D distance (x * 1 is x, bit for bit).
            let t = (x * x + y * y).sqrt();
            let ratio = r / t;
            let scale = if t > 1e-6 { ratio } else { 1.0 };
            xs[j] = x * scale;
            ys[j] = y * scale;
            keep |= u32::from((j < n) & within & on_skin[j] & lit[j]) << j;
        }
        let mut count = 0;
        while keep != 0 {
            let j = keep.trailing_zeros() as usize;
            keep &= keep - 1;
            found[count] = Candidate {
                slot: first_slot + j as u8,
                source: (s0 + j) as u32,
                x: xs[j],
                y: ys[j],
            };
            count += 1;
        }
        count
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

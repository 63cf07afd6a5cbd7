//! The response tables of the hierarchical evaluation: each material's and angle's exit response
//! restricted to one radial band, low-passed to the band's cell size and packed texel by texel
//! for the kernel's lookups.

use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d};

use super::ResponseGrid;

/// Smooth step from 1 (t <= 1) to 0 (t >= 2).
pub(super) fn window_step(t: f64) -> f64 {
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
pub(super) struct Band {
    /// `None` for the innermost band.
    pub(super) rho_inner: Option<f64>,
    /// `None` for the outermost band.
    pub(super) rho_outer: Option<f64>,
}

impl Band {
    /// Band `level` of a kernel of `count` levels whose innermost radius is `rho0`: it spans
    /// `rho_{level-1}..2 rho_level` with `rho_j = 2^j rho0`, the first without an inner edge and
    /// the last without an outer one.
    pub(super) fn of_level(level: usize, count: usize, rho0: f64) -> Self {
        let rho = |j: usize| rho0 * f64::powi(2.0, j as i32);
        Self {
            rho_inner: (level > 0).then(|| rho(level - 1)),
            rho_outer: (level + 1 < count).then(|| rho(level)),
        }
    }

    pub(super) fn weight(&self, r: f64) -> f64 {
        let outer = self.rho_outer.map_or(1.0, |rho| window_step(r / rho));
        let inner = self.rho_inner.map_or(0.0, |rho| window_step(r / rho));
        outer - inner
    }

    pub(super) fn r_min(&self) -> f64 {
        self.rho_inner.unwrap_or(0.0)
    }

    pub(super) fn r_max(&self) -> f64 {
        self.rho_outer.map_or(f64::INFINITY, |rho| 2.0 * rho)
    }
}

/// A response restricted to one band and filtered to one cell size, for bilinear lookup.
#[derive(Debug, Clone)]
pub(super) struct BandTable {
    pub(super) spacing: f64,
    /// Cells per side = 2 * half + 1, centred on 0.
    pub(super) half: usize,
    pub(super) values: Vec<[f32; 3]>,
}

impl BandTable {
    /// The band-windowed, low-passed `grid` on the table layout `spacing` (mm) x `half`.
    pub(super) fn build(
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
    pub(super) fn lookup(&self, x: f32, y: f32) -> [[f32; 3]; 3] {
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

/// Every (material, angle) table of one level, angle by angle, and within an angle the four
/// materials of a texel side by side (`[angle][texel][material]`, R, G, B each): a cell mixes
/// two neighbouring angles of up to all four materials, i.e. two runs of 48 bytes per corner.
///
/// The lookups are bound by those reads from the cache. Angle by angle, a region of the face
/// lit at similar incidence keeps only its two angles' tables in the cache, not every angle's:
/// interleaved texel by texel (`[texel][angle][material]`, padded to four lanes), the quick head
/// scan (seed 1, one thread each, side by side, cores swapped) took 49.2-51.5 CPU-s against
/// 45.0-45.2 angle by angle, the same exitance bit for bit. The fourth (padding) lane made no
/// difference either way (the mix compiled to two-plus-one lanes), so it went. Each tap holds
/// its table's offset in `values` ([`Tap::offset`]): with the angle and material split out of a
/// table index at every lookup instead, the `plane` subject, lit at one angle everywhere (no
/// cache to win, only the extra arithmetic), took 24.1-24.3 CPU-s against 21.0-22.3 before the
/// change, and 22.1-22.5 with the offsets.
#[derive(Debug, Clone)]
pub(super) struct PackedTables {
    pub(super) spacing: f32,
    pub(super) half: usize,
    pub(super) side: usize,
    /// Values per angle: `side * side` texels of [`MATERIALS`] tables.
    pub(super) plane: usize,
    /// `[angle][texel][material]`.
    pub(super) values: Vec<[f32; 3]>,
}

/// One (material, angle) table of a cell's mix, and its weight.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Tap {
    /// Where the table's first texel is in [`PackedTables::values`]: `angle * plane + material`
    /// (computed once per cell, not per lookup: the lookups are most of the gather's work).
    pub(super) offset: u32,
    pub(super) weight: f32,
}

/// Basis materials a cell mixes.
pub(super) const MATERIALS: usize = 4;
/// At most two angles for each of the four basis materials.
pub(super) const MAX_TAPS: usize = 2 * MATERIALS;

/// The tables a cell of these material weights and angle interpolation mixes, with their
/// weights (materials below 1e-4 are skipped), for tables packed with `angles` angles of
/// `plane` values each ([`PackedTables::plane`]).
pub(super) fn mix_taps(
    materials: &[f32; MATERIALS],
    angle_index: u16,
    angle_t: f32,
    angles: usize,
    plane: usize,
) -> ([Tap; MAX_TAPS], u8) {
    let mut taps = [Tap::default(); MAX_TAPS];
    let mut count = 0;
    let a0 = angle_index as usize;
    for (m, &wm) in materials.iter().enumerate() {
        if wm <= 1e-4 {
            continue;
        }
        let (w_lo, w_hi) = (wm * (1.0 - angle_t), wm * angle_t);
        let offset = |a: usize| (a * plane + m) as u32;
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
    pub(super) fn build(
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
        debug_assert!(grids.len() <= MATERIALS);
        let plane = side * side * MATERIALS;
        let mut values = vec![[0.0f32; 3]; plane * angles];
        for (m, per_angle) in grids.iter().enumerate() {
            for (a, grid) in per_angle.iter().take(angles).enumerate() {
                let table = BandTable::build(grid, band, cell_size_mm, spacing, half);
                debug_assert!(table.half == half && table.spacing == spacing);
                for (i, v) in table.values.iter().enumerate() {
                    values[a * plane + i * MATERIALS + m] = *v;
                }
            }
        }
        Self {
            spacing: spacing as f32,
            half,
            side,
            plane,
            values,
        }
    }

    /// The weighted mix of the tables `taps` at (x, y), mm, bilinearly interpolated, with its
    /// gradient (d/dx, d/dy) when `GRADIENT`; `None` outside the tables (where they are zero).
    #[inline(always)]
    pub(super) fn lookup<const GRADIENT: bool>(
        &self,
        x: f32,
        y: f32,
        taps: &[Tap],
    ) -> Option<[[f32; 3]; 3]> {
        let inv = 1.0 / self.spacing;
        let fx = x * inv + self.half as f32;
        let fy = y * inv + self.half as f32;
        let last = (self.side - 1) as f32;
        if !(fx >= 0.0 && fy >= 0.0 && fx < last && fy < last) {
            return None;
        }
        let (ix, iy) = (fx as usize, fy as usize);
        let (tx, ty) = (fx - ix as f32, fy - iy as f32);
        let base = (iy * self.side + ix) * MATERIALS;
        let corners = [
            base,
            base + MATERIALS,
            base + self.side * MATERIALS,
            base + (self.side + 1) * MATERIALS,
        ];
        let mut mix = [[0.0f32; 3]; 4];
        for (m, &corner) in mix.iter_mut().zip(&corners) {
            for tap in taps {
                let texel = self.values[corner + tap.offset as usize];
                for c in 0..3 {
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
pub(super) const FILTER_SIGMA_CELLS: f64 = 0.6;
/// Table sample spacing, in cells (a quarter of the filter's sigma). Coarser tables are read
/// faster (the lookups are bound by the cache; 0.3 cells took the quick head scan's CPU time
/// down a third), but their bilinear lookups miss the sharp peaks of skin: at 0.3 cells a
/// response with half its energy in one Monte Carlo cell gained 2.2 % of its total and the
/// quick head scan's global light moved 0.5 % RMS (skin II) to 1.1 % (skin VI, +0.7 % of its
/// total) against tables of 0.075 cells; at 0.2 a lit line's profile erred by 1.1 % of its peak.
/// At 0.15 the subsurface tests hold within 1 % and the head scan moves 0.14-0.25 % RMS.
pub(super) const TABLE_SPACING_CELLS: f64 = 0.15;
/// How far the filtered tables reach beyond the band, in cells: 2.1 filter sigmas, where the
/// band's window, vanishing quadratically at its edges, has spread almost nothing. Every pair of
/// cells within this reach is looked up, so it sets how many pairs a level holds: against 2 cells
/// (3.3 sigmas), 1.5 cells took the quick head scan's CPU time down 9-15 % and 1.25 cells a
/// further 2-7 % (seed 1, one thread each, side by side, cores swapped), with the global light
/// unchanged against tables of 0.075 cells and 3 cells' reach (relative RMS 0.14 % on skin II seed
/// 1, 0.25 % on skin VI seed 7, the same to two digits as with 2 cells; against 2 cells it moved
/// 0.1 % of the frames' pixel values by a code, 0.45 codes RMS in 16 bits). At 1 cell it moved
/// 3.7 % of them (2.98 codes RMS, a third of what 0.15-cell tables differ from 0.075-cell ones).
pub(super) const FILTER_REACH_CELLS: f64 = 1.25;

/// Separable convolution with a normalised Gaussian of `sigma` samples (truncated at 3.5 sigma),
/// zero outside; the identity below a quarter sample.
pub(super) fn gaussian_filter(data: &mut [[f64; 3]], side: usize, sigma: f64) {
    if sigma < 0.25 {
        return;
    }
    let kernel = GaussianKernel::new(sigma, 3.5, Normalisation::Outputs);
    if let Err(e) = blur_2d(data, side, side, &kernel, Border::Zero) {
        unreachable!("the table is side x side: {e}");
    }
}

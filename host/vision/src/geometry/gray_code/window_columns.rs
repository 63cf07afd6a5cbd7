//! The repair's window statistics from column sums (step 3): the windows of neighbouring pixels
//! of a row share all their columns but one, so each column's sums are taken once and a window
//! adds up its columns'.
//!
//! Why: the repair reads a 9 x 9 window around every pixel waiting for it (529 000 windows on
//! the real procam capture_0, both axes and all rounds), and gathering each window's valid
//! codes and summing them were a third of the decode's CPU time (perf: `gather_valid` 20 %,
//! `of_samples` 13 %). Here a window costs the sums of its 9 columns (each read once per row)
//! and, when the first plane may be final, one pass over the window to test its inliers; the
//! samples are gathered only for the windows that need the general robust fit. The sums are
//! exact integers, so the statistics equal [`WindowSums::of_samples`]'s and the prediction is
//! bit for bit the gathered one (test; the decodes of the 5 real captures and of a full-size
//! simulated one are byte-identical). Measured (`decode_breakdown`, alternated with the
//! gathering build): the repair of capture_0 114-123 -> 96-107 ms (best wall of 15, 3 pairs);
//! a full-size simulated capture's 4 projectors 0.29-0.30 -> 0.24-0.25 s, its decode 0.70-0.72
//! -> 0.63-0.64 s (mean of 3, 2 pairs). The consistency check read the same way was no faster
//! (its gather is not where its time goes) and still gathers ([`WindowSums::of_samples`]).

use super::axis::Grid;
use super::plane::Sample;
use super::window_fit::WindowSums;
use super::{DecodeParams, PixelStatus};
use rayon::prelude::*;

/// The column sums of the windows of one row's pixels, over one version of the codes (borrowed,
/// so the sums cannot outlive them). Column `x` of every array is the sum over the valid codes
/// of column `x`, rows `y - radius ..= y + radius` inside the image, offsets `dy` from row `y`:
/// `count` of them, those `above` (`dy < 0`) and `below` (`dy > 0`), the sums `sy` of `dy`,
/// `syy` of `dy^2`, `sv` of the codes and `syv` of `dy * code`, their `min` and `max`
/// (`i32::MAX`, `i32::MIN` without any). All fit `i32` exactly: a column holds at most
/// `4 MAX_WINDOW_RADIUS + 1` codes below `2^16`, and `sum |dy| * 65535 < 2^31`.
#[derive(Debug, Default)]
pub(super) struct ColumnBuffer {
    count: Vec<i32>,
    above: Vec<i32>,
    below: Vec<i32>,
    sy: Vec<i32>,
    syy: Vec<i32>,
    sv: Vec<i32>,
    syv: Vec<i32>,
    min: Vec<i32>,
    max: Vec<i32>,
}

impl ColumnBuffer {
    /// Makes every array `width` columns long (their values are set by [`sum_columns`]).
    fn fit_width(&mut self, width: usize) {
        for v in [
            &mut self.count,
            &mut self.above,
            &mut self.below,
            &mut self.sy,
            &mut self.syy,
            &mut self.sv,
            &mut self.syv,
            &mut self.min,
            &mut self.max,
        ] {
            v.resize(width, 0);
        }
    }
}

/// The codes of `pairs` as one `i32` each: the code where valid, -1 elsewhere (valid codes are
/// never negative). Why: the column sums read whole rows of it as plain integers; split out of
/// the pairs on the fly, the status bytes were gathered one by one.
pub(super) fn signed_codes(pairs: &[(i32, PixelStatus)], out: &mut Vec<i32>) {
    out.clear();
    out.par_extend(
        pairs
            .par_iter()
            .map(|&(code, status)| if status.is_valid() { code } else { -1 }),
    );
}

/// The windows of `radius` around some pixels of row `y` (see [`ColumnBuffer`]).
#[derive(Debug)]
pub(super) struct RowColumns<'a> {
    grid: Grid,
    codes: &'a [(i32, PixelStatus)],
    /// The same codes, [`signed_codes`].
    signed: &'a [i32],
    y: usize,
    radius: usize,
    columns: &'a ColumnBuffer,
}

impl<'a> RowColumns<'a> {
    /// The column sums of the windows of `radius` around the pixels `centres` (ascending) of
    /// row `y`, over `codes` and the same codes `signed` ([`signed_codes`]); `buffer` is reused.
    pub(super) fn new(
        grid: Grid,
        y: usize,
        radius: usize,
        (codes, signed): (&'a [(i32, PixelStatus)], &'a [i32]),
        buffer: &'a mut ColumnBuffer,
        centres: &[usize],
    ) -> Self {
        buffer.fit_width(grid.width);
        debug_assert!(centres.windows(2).all(|w| w[0] < w[1]), "centres ascending");
        // The columns of the windows, as runs of adjacent columns.
        let mut run: Option<(usize, usize)> = None;
        for &x in centres {
            let ((x0, x1), _) = grid.window_bounds(x, y, radius);
            run = match run {
                Some((start, end)) if x0 <= end + 1 => Some((start, end.max(x1))),
                Some(done) => {
                    sum_columns(grid, y, radius, signed, buffer, done);
                    Some((x0, x1))
                }
                None => Some((x0, x1)),
            };
        }
        if let Some(last) = run {
            sum_columns(grid, y, radius, signed, buffer, last);
        }
        Self {
            grid,
            codes,
            signed,
            y,
            radius,
            columns: buffer,
        }
    }

    /// Half-size of the windows.
    pub(super) fn radius(&self) -> usize {
        self.radius
    }

    /// [`Grid::gather_valid`] of the window around pixel `x` of the row.
    pub(super) fn gather_valid(&self, x: usize, samples: &mut Vec<Sample>) {
        let i = self.y * self.grid.width + x;
        self.grid.gather_valid(i, self.radius, self.codes, samples);
    }

    /// [`WindowSums::of_samples`] of the window around pixel `x` of the row, one of the centres
    /// the sums were taken for, which must have no code (the repair's pixels: the centre is not
    /// excluded from the columns).
    pub(super) fn window(&self, x: usize) -> WindowSums {
        debug_assert!(self.signed[self.y * self.grid.width + x] < 0);
        let ((x0, x1), (y0, y1)) = self.grid.window_bounds(x, self.y, self.radius);
        let c = self.columns;
        let (mut count, [mut left, mut right, mut above, mut below]) = (0i32, [0i32; 4]);
        let [mut sx, mut sxx, mut sy, mut syy, mut sxy] = [0i64; 5];
        let [mut sv, mut sxv, mut syv] = [0i64; 3];
        let (mut min, mut max) = (i32::MAX, i32::MIN);
        for column in x0..=x1 {
            let dx = column as i64 - x as i64;
            let n = c.count[column];
            count += n;
            left += n * i32::from(dx < 0);
            right += n * i32::from(dx > 0);
            above += c.above[column];
            below += c.below[column];
            sx += dx * i64::from(n);
            sxx += dx * dx * i64::from(n);
            sy += i64::from(c.sy[column]);
            syy += i64::from(c.syy[column]);
            sxy += dx * i64::from(c.sy[column]);
            sv += i64::from(c.sv[column]);
            sxv += dx * i64::from(c.sv[column]);
            syv += i64::from(c.syv[column]);
            min = min.min(c.min[column]);
            max = max.max(c.max[column]);
        }
        WindowSums {
            count: count as usize,
            size: (x1 - x0 + 1) * (y1 - y0 + 1) - 1,
            min,
            max,
            sums: [sx, sy, sv, sxx, syy, sxy, sxv, syv],
            sides: [left > 0, right > 0, above > 0, below > 0],
        }
    }

    /// [`WindowSums::first_fit_if_final`] of the window around pixel `x` of the row (which has no
    /// code), `sums` being its [`RowColumns::window`], testing the inliers on the window itself
    /// instead of gathered samples.
    pub(super) fn first_fit_if_final(
        &self,
        x: usize,
        sums: &WindowSums,
        params: &DecodeParams,
    ) -> Option<f64> {
        let plane = sums.first_plane_if_narrow(params)?;
        let ((x0, x1), (y0, y1)) = self.grid.window_bounds(x, self.y, self.radius);
        let mut all_inliers = true;
        for row in y0..=y1 {
            let dy = row as i32 - self.y as i32;
            let start = row * self.grid.width;
            for (column, &code) in (x0..).zip(&self.signed[start + x0..=start + x1]) {
                let dx = column as i32 - x as i32;
                // Non-short-circuit: no branch per pixel.
                all_inliers &= (code < 0) | plane.is_inlier(dx, dy, code);
            }
        }
        all_inliers.then_some(plane.a)
    }
}

/// Fills columns `x0..=x1` of `buffer`'s sums for the windows of row `y` (see [`ColumnBuffer`]):
/// the band's rows one after the other, each added to every column of the run at once (loops
/// over plain `i32` columns, which the compiler vectorises with AVX2's 32-bit multiplies; the
/// baseline x86-64 build left them scalar, and they were a tenth of the decode).
fn sum_columns(
    grid: Grid,
    y: usize,
    radius: usize,
    signed: &[i32],
    buffer: &mut ColumnBuffer,
    run: (usize, usize),
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, the one feature `sum_columns_avx2` is compiled for.
        return unsafe { sum_columns_avx2(grid, y, radius, signed, buffer, run) };
    }
    sum_columns_portable(grid, y, radius, signed, buffer, run)
}

/// [`sum_columns_portable`] compiled with AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn sum_columns_avx2(
    grid: Grid,
    y: usize,
    radius: usize,
    signed: &[i32],
    buffer: &mut ColumnBuffer,
    run: (usize, usize),
) {
    sum_columns_portable(grid, y, radius, signed, buffer, run)
}

/// The body of [`sum_columns`] (inlined into each instruction-set variant).
#[inline(always)]
fn sum_columns_portable(
    grid: Grid,
    y: usize,
    radius: usize,
    signed: &[i32],
    buffer: &mut ColumnBuffer,
    (x0, x1): (usize, usize),
) {
    let run = x0..x1 + 1;
    let ColumnBuffer {
        count,
        above,
        below,
        sy,
        syy,
        sv,
        syv,
        min,
        max,
    } = buffer;
    let (count, above, below) = (
        &mut count[run.clone()],
        &mut above[run.clone()],
        &mut below[run.clone()],
    );
    let (sy, syy, sv, syv) = (
        &mut sy[run.clone()],
        &mut syy[run.clone()],
        &mut sv[run.clone()],
        &mut syv[run.clone()],
    );
    let (min, max) = (&mut min[run.clone()], &mut max[run.clone()]);
    for column in [
        &mut *count,
        &mut *above,
        &mut *below,
        &mut *sy,
        &mut *syy,
        &mut *sv,
        &mut *syv,
    ] {
        column.fill(0);
    }
    min.fill(i32::MAX);
    max.fill(i32::MIN);
    let (_, (y0, y1)) = grid.window_bounds(x0, y, radius);
    for row in y0..=y1 {
        let start = row * grid.width;
        let codes = &signed[start + run.start..start + run.end];
        let dy = row as i32 - y as i32;
        let (is_above, is_below) = (i32::from(dy < 0), i32::from(dy > 0));
        for k in 0..codes.len() {
            // All ones for a valid code (not negative), else 0.
            let c = codes[k];
            let mask = !(c >> 31);
            let v = mask & 1;
            count[k] += v;
            above[k] += v * is_above;
            below[k] += v * is_below;
            sy[k] += mask & dy;
            syy[k] += mask & (dy * dy);
            sv[k] += mask & c;
            syv[k] += mask & (c * dy);
            min[k] = min[k].min(mask & c | !mask & i32::MAX);
            max[k] = max[k].max(mask & c | !mask & i32::MIN);
        }
    }
}

//! Steps 3 and 4 of the algorithm for one axis: integer codes, repair of unreliable bits against
//! the neighbours' plane, the outlier check and the sub-pixel fit.

use std::time::Instant;

use rayon::prelude::*;

use super::bits::PixelBits;
use super::lit_test::Lighting;
use super::plane::{FitScratch, Sample, jump_limit, robust_plane_at_centre};
use super::window_columns::{ColumnBuffer, RowColumns, signed_codes};
use super::window_fit::WindowSums;
use super::{AxisDecode, DecodeParams, DecodePhases, PixelStatus};
use mlsss_core::capture::patterns::gray_decode;

#[derive(Debug, Clone, Copy)]
pub(super) struct Grid {
    pub(super) width: usize,
    pub(super) height: usize,
}

impl Grid {
    pub(super) fn len(&self) -> usize {
        self.width * self.height
    }

    /// The first and last column, and the first and last row, of the window of `radius` around
    /// column `x`, row `y`, clipped to the image.
    #[inline(always)]
    pub(super) fn window_bounds(
        &self,
        x: usize,
        y: usize,
        radius: usize,
    ) -> ((usize, usize), (usize, usize)) {
        (
            (x.saturating_sub(radius), (x + radius).min(self.width - 1)),
            (y.saturating_sub(radius), (y + radius).min(self.height - 1)),
        )
    }

    /// Replaces `samples` with `(dx, dy, code)` of the valid pixels in the window of `radius`
    /// around `i`, excluding `i`, rows top to bottom and each row left to right. Branch-free:
    /// every pixel of the window is written and the count advances only for the valid ones
    /// (whether a neighbour is valid is as good as random at a blurred region's edge, and the
    /// mispredicted branch of a `push` per valid pixel made this a tenth of the decode).
    pub(super) fn gather_valid(
        &self,
        i: usize,
        radius: usize,
        codes: &[(i32, PixelStatus)],
        samples: &mut Vec<Sample>,
    ) {
        let (x, y) = (i % self.width, i / self.width);
        let ((x0, x1), (y0, y1)) = self.window_bounds(x, y, radius);
        samples.clear();
        samples.resize(
            (x1 - x0 + 1) * (y1 - y0 + 1),
            Sample {
                dx: 0,
                dy: 0,
                code: 0,
            },
        );
        let mut kept = 0;
        for row in y0..=y1 {
            let dy = row as i32 - y as i32;
            let start = row * self.width;
            for (col, &(code, status)) in (x0..).zip(&codes[start + x0..=start + x1]) {
                samples[kept] = Sample {
                    dx: col as i32 - x as i32,
                    dy,
                    code,
                };
                kept += usize::from(status.is_valid() && (col, row) != (x, y));
            }
        }
        samples.truncate(kept);
    }

    /// True when some pixel within `radius` of `i` (itself included) is set in `mask`.
    fn any_within(&self, i: usize, radius: usize, mask: &[bool]) -> bool {
        let (x, y) = (i % self.width, i / self.width);
        let ((x0, x1), (y0, y1)) = self.window_bounds(x, y, radius);
        (y0..=y1).any(|row| {
            mask[row * self.width + x0..=row * self.width + x1]
                .iter()
                .any(|&m| m)
        })
    }
}

/// Reusable buffers of one worker: the window's samples and the plane fits.
#[derive(Debug, Default)]
struct Scratch {
    samples: Vec<Sample>,
    with_self: Vec<Sample>,
    columns: ColumnBuffer,
    /// The pixels of a row due for repair (their columns).
    due_columns: Vec<usize>,
    fit: FitScratch,
}

/// Integer codes of one axis: direct decode, repair of low bits, consistency and sub-pixel fit.
pub(super) fn decode_axis(
    grid: Grid,
    bits: &[PixelBits],
    nbits: u32,
    size: u32,
    params: &DecodeParams,
    phases: &mut DecodePhases,
) -> AxisDecode {
    let start = Instant::now();
    // Pass 1: pixels whose bits are all reliable.
    let first: Vec<(i32, PixelStatus)> = bits
        .par_iter()
        .map(|b| initial_code(b, nbits, size, params))
        .collect();
    let decoded = Instant::now();
    phases.bits_s += (decoded - start).as_secs_f64();
    // Pass 2: repair from the neighbours, growing into regions where most pixels need it: each
    // round uses the codes decoded or repaired by the previous one.
    let repaired = repair_rounds(grid, bits, nbits, first, size, params);
    let repair_end = Instant::now();
    phases.repair_s += (repair_end - decoded).as_secs_f64();
    // Pass 3: consistency with the neighbours, and sub-pixel coordinate.
    // Unzipped in parallel straight into the three outputs (a serial split of 1.3 M pixels was
    // a visible share of an axis, and a vector of tuples split afterwards was one more fresh
    // 16 MB buffer).
    let smooth = smooth_window_sums(grid, &repaired, params.window_radius as usize);
    let (code, (coord, status)): (Vec<i32>, (Vec<f32>, Vec<PixelStatus>)) = (0..grid.len())
        .into_par_iter()
        .map_init(Scratch::default, |scratch, i| {
            let (code, coord, status) =
                check_and_refine(grid, i, &repaired, smooth[i], params, scratch);
            (code, (coord, status))
        })
        .unzip();
    phases.check_s += repair_end.elapsed().as_secs_f64();
    AxisDecode {
        code,
        coord,
        status,
    }
}

/// Rounds of neighbour repair (each can reach `2 * window_radius` further into a blurred region).
const REPAIR_ROUNDS: usize = 3;

/// Pass 2: [`REPAIR_ROUNDS`] rounds of [`repair`] over the pixels still waiting for it. A pixel's
/// repair depends only on the codes within the repair window, so from the second round on only
/// pixels with a code changed in their window by the previous round are tried again: the others
/// would give the same answer.
fn repair_rounds(
    grid: Grid,
    bits: &[PixelBits],
    nbits: u32,
    first: Vec<(i32, PixelStatus)>,
    size: u32,
    params: &DecodeParams,
) -> Vec<(i32, PixelStatus)> {
    let radius = repair_radius(params);
    let mut codes = first;
    // Two code buffers and two change masks, swapped after each round. Why: a fresh 10 MB
    // vector per round (and a mask per round) came from the system as new zeroed pages, and
    // their page faults were a visible share of the repair.
    let mut next = codes.clone();
    let mut changed = vec![false; grid.len()];
    let mut now_changed = vec![false; grid.len()];
    let mut signed = Vec::new();
    for round in 0..REPAIR_ROUNDS {
        let (previous, changed_before) = (&codes, &changed);
        signed_codes(previous, &mut signed);
        let signed = &signed;
        let due = |i: usize| {
            previous[i].1 == PixelStatus::RepairFailed
                && (round == 0 || grid.any_within(i, radius, changed_before))
        };
        // Row by row: the windows of a row's pixels share their columns ([`RowColumns`]).
        let any_change = next
            .par_chunks_mut(grid.width)
            .zip(now_changed.par_chunks_mut(grid.width))
            .enumerate()
            .map_init(Scratch::default, |scratch, (y, (out_row, now_row))| {
                let row = y * grid.width..(y + 1) * grid.width;
                out_row.copy_from_slice(&previous[row.clone()]);
                let Scratch {
                    samples,
                    columns,
                    due_columns,
                    fit,
                    ..
                } = scratch;
                due_columns.clear();
                due_columns.extend((0..grid.width).filter(|&x| due(row.start + x)));
                let windows =
                    RowColumns::new(grid, y, radius, (previous, signed), columns, due_columns);
                // Only the due pixels can change.
                now_row.fill(false);
                let mut row_changed = false;
                for &x in due_columns.iter() {
                    let predicted = neighbour_prediction(&windows, x, params, samples, fit);
                    out_row[x] = repair(&bits[row.start + x], nbits, size, params, predicted);
                    now_row[x] = out_row[x] != previous[row.start + x];
                    row_changed |= now_row[x];
                }
                row_changed
            })
            .reduce(|| false, |a, b| a | b);
        std::mem::swap(&mut codes, &mut next);
        if !any_change {
            break;
        }
        std::mem::swap(&mut changed, &mut now_changed);
    }
    codes
}

/// Half-size of the repair window: wider than for the checks, as in blurred regions the
/// reliable pixels are sparse.
fn repair_radius(params: &DecodeParams) -> usize {
    2 * params.window_radius as usize
}

/// Pass 1 for one pixel. Pixels that need repair are marked `RepairFailed` until pass 2 succeeds.
fn initial_code(b: &PixelBits, nbits: u32, size: u32, params: &DecodeParams) -> (i32, PixelStatus) {
    match b.lighting {
        Lighting::Unlit => return (-1, PixelStatus::Unlit),
        Lighting::Dim => return (-1, PixelStatus::Dim),
        Lighting::Lit => {}
    }
    let unreliable = !b.reliable & bit_mask(nbits);
    if unreliable == 0 {
        return in_range(gray_decode(u32::from(b.gray)), size, PixelStatus::Decoded);
    }
    if unreliable.count_ones() > params.max_repaired_bits {
        return (-1, PixelStatus::UnreliableBits);
    }
    (-1, PixelStatus::RepairFailed)
}

fn in_range(code: u32, size: u32, status: PixelStatus) -> (i32, PixelStatus) {
    if code < size {
        (code as i32, status)
    } else {
        (-1, PixelStatus::OutOfRange)
    }
}

fn bit_mask(bits: u32) -> u16 {
    if bits >= 16 {
        u16::MAX
    } else {
        (1u16 << bits) - 1
    }
}

/// Pass 2 for one pixel: the candidate code closest to the neighbours' plane value `predicted`,
/// if close enough.
fn repair(
    b: &PixelBits,
    nbits: u32,
    size: u32,
    params: &DecodeParams,
    predicted: Option<f64>,
) -> (i32, PixelStatus) {
    let Some(predicted) = predicted else {
        return (-1, PixelStatus::RepairFailed);
    };
    let unreliable = !b.reliable & bit_mask(nbits);
    let fixed = b.gray & !unreliable;
    // Enumerate every setting of the unreliable bits (at most 2^max_repaired_bits).
    let mut best: Option<(f64, u32)> = None;
    let mut subset: u16 = 0;
    loop {
        let code = gray_decode(u32::from(fixed | subset));
        let distance = (code as f64 - predicted).abs();
        if code < size && best.is_none_or(|(d, _)| distance < d) {
            best = Some((distance, code));
        }
        // Next subset of `unreliable` (standard subset enumeration).
        subset = subset.wrapping_sub(unreliable) & unreliable;
        if subset == 0 {
            break;
        }
    }
    match best {
        Some((d, code)) if d <= params.repair_tolerance_px as f64 => {
            (code as i32, PixelStatus::Repaired)
        }
        _ => (-1, PixelStatus::RepairFailed),
    }
}

/// Marks an invalid code in [`smooth_window_sums`]'s scan: far below every code, so a window
/// holding one has a range beyond any smoothness limit and a negative minimum.
const NO_CODE: i32 = -(1 << 20);

/// For every pixel, the sum of the codes of its `(2 radius + 1)^2` window (itself included)
/// when that window lies inside the image, every pixel of it is valid and its codes span at
/// most `2 radius + 2`; else -1. Such a pixel (when valid) passes
/// [`WindowStats::is_full_and_smooth`] with the sum of its neighbours' codes `sum - code`: its
/// neighbours are the window less itself, and their range is within the window's. Why: the
/// check read every decoded pixel's window to find this out, a tenth of the decode (perf); as
/// separable sums, minima and maxima over the image (rows, then columns, each a contiguous
/// loop the compiler vectorises) it is a few operations per pixel. The other pixels are
/// examined as before. Sums wrap (`wrapping_add`): a window holding [`NO_CODE`] is rejected by
/// its minimum whatever its sum, and a valid window's sum is at most
/// `129^2 * 65535 < 2^31` (codes are 16-bit, the radius at most [`super::MAX_WINDOW_RADIUS`]).
fn smooth_window_sums(grid: Grid, codes: &[(i32, PixelStatus)], radius: usize) -> Vec<i32> {
    let Grid { width, height } = grid;
    let side = 2 * radius + 1;
    let mut out = vec![-1i32; grid.len()];
    if width < side || height < side {
        return out;
    }
    // Row pass: sum, minimum and maximum over `side` pixels ending at each x (windows wholly
    // inside the row only).
    let inner = width - side + 1;
    let mut row_sum = vec![0i32; inner * height];
    let mut row_min = vec![0i32; inner * height];
    let mut row_max = vec![0i32; inner * height];
    row_sum
        .par_chunks_mut(inner)
        .zip(row_min.par_chunks_mut(inner))
        .zip(row_max.par_chunks_mut(inner))
        .enumerate()
        .for_each(|(y, ((sum, min), max))| {
            let row = &codes[y * width..(y + 1) * width];
            let masked: Vec<i32> = row
                .iter()
                .map(|&(c, s)| if s.is_valid() { c } else { NO_CODE })
                .collect();
            sum.copy_from_slice(&masked[..inner]);
            min.copy_from_slice(&masked[..inner]);
            max.copy_from_slice(&masked[..inner]);
            for k in 1..side {
                let shifted = &masked[k..k + inner];
                fold_window((sum, min, max), (shifted, shifted, shifted));
            }
        });
    // Column pass over `side` rows centred on y, written at the window's centre pixel.
    let limit = 2 * radius as i32 + 2;
    out.par_chunks_mut(width)
        .enumerate()
        .skip(radius)
        .take(height - side + 1)
        .for_each(|(y, out_row)| {
            let first = (y - radius) * inner;
            let mut sum = row_sum[first..first + inner].to_vec();
            let mut min = row_min[first..first + inner].to_vec();
            let mut max = row_max[first..first + inner].to_vec();
            for k in 1..side {
                let at = first + k * inner..first + (k + 1) * inner;
                fold_window(
                    (&mut sum, &mut min, &mut max),
                    (&row_sum[at.clone()], &row_min[at.clone()], &row_max[at]),
                );
            }
            for (o, ((&s, &lo), &hi)) in out_row[radius..radius + inner]
                .iter_mut()
                .zip(sum.iter().zip(&min).zip(&max))
            {
                *o = if lo >= 0 && hi - lo <= limit { s } else { -1 };
            }
        });
    out
}

/// One step of [`smooth_window_sums`]'s row and column passes: the running window sums,
/// minima and maxima take in one more column (or row) of `add`'s sums, minima and maxima.
fn fold_window(
    (sum, min, max): (&mut [i32], &mut [i32], &mut [i32]),
    (add_sum, add_min, add_max): (&[i32], &[i32], &[i32]),
) {
    for (((s, lo), hi), ((&a, &a_lo), &a_hi)) in sum
        .iter_mut()
        .zip(min.iter_mut())
        .zip(max.iter_mut())
        .zip(add_sum.iter().zip(add_min).zip(add_max))
    {
        *s = s.wrapping_add(a);
        *lo = (*lo).min(a_lo);
        *hi = (*hi).max(a_hi);
    }
}

/// Pass 3 for one pixel: flag codes that disagree with the neighbours, fit the sub-pixel value.
/// `smooth_sum` is the pixel's [`smooth_window_sums`] value. Other windows are gathered once;
/// their statistics and, where the robust fits end at their first plane, the fits' values come
/// from [`WindowSums`].
fn check_and_refine(
    grid: Grid,
    i: usize,
    codes: &[(i32, PixelStatus)],
    smooth_sum: i32,
    params: &DecodeParams,
    scratch: &mut Scratch,
) -> (i32, f32, PixelStatus) {
    let (code, status) = codes[i];
    if !status.is_valid() {
        return (-1, f32::NAN, status);
    }
    let radius = params.window_radius as usize;
    if smooth_sum >= 0 {
        // The full window's statistics without reading it: every neighbour valid, the range
        // within the smooth limit.
        let full = (2 * radius + 1).pow(2) - 1;
        return check_against_mean(code, status, f64::from(smooth_sum - code), full, params);
    }
    let Scratch {
        samples,
        with_self,
        fit,
        ..
    } = scratch;
    grid.gather_valid(i, radius, codes, samples);
    let sums = WindowSums::of_samples(grid, i, radius, samples);
    let stats = WindowStats::of_sums(&sums);
    if stats.is_full_and_smooth(radius) {
        return check_against_mean(code, status, stats.sum, stats.count, params);
    }
    if stats.count < params.min_neighbours as usize {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    }
    let predicted = sums
        .first_fit_if_final(samples, params, None)
        .or_else(|| robust_plane_at_centre(samples, params, fit));
    let Some(predicted) = predicted else {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    };
    if (code as f64 - predicted).abs() > params.outlier_px as f64 {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    }
    // The fit with the pixel itself, restricted to the same inliers, gives the sub-pixel value.
    let with_self_fit = sums
        .first_fit_if_final(samples, params, Some(code))
        .or_else(|| {
            with_self.clear();
            with_self.extend(
                samples
                    .iter()
                    .copied()
                    .filter(|s| f64::from(s.code.abs_diff(code)) <= jump_limit(params)),
            );
            with_self.push(Sample { dx: 0, dy: 0, code });
            robust_plane_at_centre(with_self, params, fit)
        });
    // The code says which projector pixel is seen: keep the refined value inside it.
    let refined = with_self_fit
        .map(|p| p.clamp(code as f64 - 0.5, code as f64 + 0.5))
        .unwrap_or(code as f64);
    (code, refined as f32, status)
}

/// The check of a pixel whose window is complete and smooth: over a complete symmetric window
/// the least-squares plane's value at the centre is the mean, so no fit is needed.
/// `neighbour_sum` is the sum of the `count` neighbours' codes.
fn check_against_mean(
    code: i32,
    status: PixelStatus,
    neighbour_sum: f64,
    count: usize,
    params: &DecodeParams,
) -> (i32, f32, PixelStatus) {
    let predicted = neighbour_sum / count as f64;
    if (code as f64 - predicted).abs() > params.outlier_px as f64 {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    }
    let refined = ((neighbour_sum + code as f64) / (count + 1) as f64)
        .clamp(code as f64 - 0.5, code as f64 + 0.5);
    (code, refined as f32, status)
}

/// The neighbours' plane value at pixel `x` of `windows`' row (valid neighbours within its
/// radius; the pixel has no code), if there are enough of them. The statistics and, where the
/// robust fit ends at its first plane, its value come from the window's column sums
/// ([`RowColumns`]); `samples` are gathered only for the general fit.
fn neighbour_prediction(
    windows: &RowColumns,
    x: usize,
    params: &DecodeParams,
    samples: &mut Vec<Sample>,
    fit: &mut FitScratch,
) -> Option<f64> {
    let sums = windows.window(x);
    let stats = WindowStats::of_sums(&sums);
    if stats.is_full_and_smooth(windows.radius()) {
        return Some(stats.sum / stats.count as f64);
    }
    if stats.count < params.min_neighbours as usize {
        return None;
    }
    // Interpolate, never extrapolate: a plane through integer codes on one side only (image
    // border, shadow edge) is biased by the staircase of the codes.
    if !sums.surrounded() {
        return None;
    }
    windows.first_fit_if_final(x, &sums, params).or_else(|| {
        windows.gather_valid(x, samples);
        robust_plane_at_centre(samples, params, fit)
    })
}

/// Count, sum and range of the valid codes around a pixel (itself excluded), without allocating.
#[derive(Debug, Clone, Copy)]
struct WindowStats {
    count: usize,
    sum: f64,
    min: i32,
    max: i32,
    /// Pixels of the window inside the image (excluding the centre).
    size: usize,
}

impl WindowStats {
    /// The statistics of a window's sums ([`WindowSums::of_samples`]).
    fn of_sums(sums: &WindowSums) -> Self {
        Self {
            count: sums.count,
            sum: sums.code_sum(),
            min: sums.min,
            max: sums.max,
            size: sums.size,
        }
    }

    /// The statistics read straight from the window: the reference of [`WindowStats::of_sums`]
    /// (tests).
    #[cfg(test)]
    fn new(grid: Grid, i: usize, radius: usize, codes: &[(i32, PixelStatus)]) -> Self {
        let (x, y) = (i % grid.width, i / grid.width);
        let ((x0, x1), (y0, y1)) = grid.window_bounds(x, y, radius);
        let (mut count, mut sum, mut min, mut max) = (0usize, 0i64, i32::MAX, i32::MIN);
        for row in y0..=y1 {
            let start = row * grid.width;
            for (j, &(code, status)) in (start + x0..).zip(&codes[start + x0..=start + x1]) {
                let valid = status.is_valid() && j != i;
                count += usize::from(valid);
                sum += if valid { i64::from(code) } else { 0 };
                min = if valid { min.min(code) } else { min };
                max = if valid { max.max(code) } else { max };
            }
        }
        Self {
            count,
            sum: sum as f64,
            min,
            max,
            size: (x1 - x0 + 1) * (y1 - y0 + 1) - 1,
        }
    }

    /// [`WindowStats::new`] from the window's valid samples ([`Grid::gather_valid`] of the same
    /// window).
    #[cfg(test)]
    fn of_samples(grid: Grid, i: usize, radius: usize, samples: &[Sample]) -> Self {
        let (x, y) = (i % grid.width, i / grid.width);
        let ((x0, x1), (y0, y1)) = grid.window_bounds(x, y, radius);
        let (mut sum, mut min, mut max) = (0i64, i32::MAX, i32::MIN);
        for sample in samples {
            sum += i64::from(sample.code);
            min = min.min(sample.code);
            max = max.max(sample.code);
        }
        Self {
            count: samples.len(),
            sum: sum as f64,
            min,
            max,
            size: (x1 - x0 + 1) * (y1 - y0 + 1) - 1,
        }
    }

    /// Every pixel of the full square window is decoded and the codes span no more than a surface
    /// with a gradient of about one projector pixel per camera pixel would.
    fn is_full_and_smooth(&self, radius: usize) -> bool {
        let full = (2 * radius + 1).pow(2) - 1;
        self.size == full && self.count == full && self.max - self.min <= 2 * radius as i32 + 2
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    /// The check as it was: every window read for its statistics, then the full robust fits.
    fn check_and_refine_reference(
        grid: Grid,
        i: usize,
        codes: &[(i32, PixelStatus)],
        params: &DecodeParams,
    ) -> (i32, f32, PixelStatus) {
        let (code, status) = codes[i];
        if !status.is_valid() {
            return (-1, f32::NAN, status);
        }
        let radius = params.window_radius as usize;
        let stats = WindowStats::new(grid, i, radius, codes);
        if stats.is_full_and_smooth(radius) {
            let predicted = stats.sum / stats.count as f64;
            if (code as f64 - predicted).abs() > params.outlier_px as f64 {
                return (-1, f32::NAN, PixelStatus::Inconsistent);
            }
            let refined = ((stats.sum + code as f64) / (stats.count + 1) as f64)
                .clamp(code as f64 - 0.5, code as f64 + 0.5);
            return (code, refined as f32, status);
        }
        let mut fit = FitScratch::default();
        let mut samples = Vec::new();
        grid.gather_valid(i, radius, codes, &mut samples);
        if samples.len() < params.min_neighbours as usize {
            return (-1, f32::NAN, PixelStatus::Inconsistent);
        }
        let Some(predicted) = robust_plane_at_centre(&samples, params, &mut fit) else {
            return (-1, f32::NAN, PixelStatus::Inconsistent);
        };
        if (code as f64 - predicted).abs() > params.outlier_px as f64 {
            return (-1, f32::NAN, PixelStatus::Inconsistent);
        }
        let mut with_self: Vec<Sample> = samples
            .iter()
            .copied()
            .filter(|s| f64::from(s.code.abs_diff(code)) <= jump_limit(params))
            .collect();
        with_self.push(Sample { dx: 0, dy: 0, code });
        let refined = robust_plane_at_centre(&with_self, params, &mut fit)
            .map(|p| p.clamp(code as f64 - 0.5, code as f64 + 0.5))
            .unwrap_or(code as f64);
        (code, refined as f32, status)
    }

    /// The prediction as it was: every window's samples gathered, then the full robust fit.
    fn neighbour_prediction_reference(
        grid: Grid,
        i: usize,
        radius: usize,
        codes: &[(i32, PixelStatus)],
        params: &DecodeParams,
    ) -> Option<f64> {
        let mut samples = Vec::new();
        grid.gather_valid(i, radius, codes, &mut samples);
        let stats = WindowStats::of_samples(grid, i, radius, &samples);
        if stats.is_full_and_smooth(radius) {
            return Some(stats.sum / stats.count as f64);
        }
        if stats.count < params.min_neighbours as usize {
            return None;
        }
        let has = |side: fn(i32, i32) -> bool| samples.iter().any(|s| side(s.dx, s.dy));
        let surrounded = has(|dx, _| dx < 0)
            && has(|dx, _| dx > 0)
            && has(|_, dy| dy < 0)
            && has(|_, dy| dy > 0);
        if !surrounded {
            return None;
        }
        robust_plane_at_centre(&samples, params, &mut FitScratch::default())
    }

    /// Codes of a tilted plane (gentle to steeper than the jump limit) from `seed`, with
    /// adversarial neighbours for the window fits: holes of every invalid status, codes off by
    /// one to three (around the 1.5 inlier bound), wild outliers, a second surface past a
    /// depth edge, and codes near the top of the 16-bit range.
    fn adversarial_codes(seed: u64, grid: Grid) -> Vec<(i32, PixelStatus)> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let base = if rng.gen_bool(0.2) {
            65_000.0
        } else {
            rng.gen_range(10.0..3000.0)
        };
        let (gx, gy) = (rng.gen_range(-3.5..3.5), rng.gen_range(-3.5..3.5));
        let edge = rng.gen_range(0.0..grid.width as f64 * 1.5);
        let (holes, off, wild) = (
            rng.gen_range(0.0..0.6),
            rng.gen_range(0.0..0.3),
            rng.gen_range(0.0..0.05),
        );
        (0..grid.len())
            .map(|i| {
                let (x, y) = ((i % grid.width) as f64, (i / grid.width) as f64);
                let mut code = (base + gx * x + gy * y).round() as i32;
                if x > edge {
                    code += 40;
                }
                if rng.gen_bool(off) {
                    code += rng.gen_range(-3..=3);
                }
                if rng.gen_bool(wild) {
                    code += rng.gen_range(-5000..5000);
                }
                let code = code.clamp(0, 65_535);
                if rng.gen_bool(holes) {
                    let status = [
                        PixelStatus::Unlit,
                        PixelStatus::RepairFailed,
                        PixelStatus::Inconsistent,
                        PixelStatus::Dim,
                    ][rng.gen_range(0..4)];
                    (-1, status)
                } else if rng.gen_bool(0.1) {
                    (code, PixelStatus::Repaired)
                } else {
                    (code, PixelStatus::Decoded)
                }
            })
            .collect()
    }

    /// The straightforward pass 2: every round tries every pixel still waiting for repair.
    fn repair_rounds_every_pixel(
        grid: Grid,
        bits: &[PixelBits],
        nbits: u32,
        first: Vec<(i32, PixelStatus)>,
        size: u32,
        params: &DecodeParams,
    ) -> Vec<(i32, PixelStatus)> {
        let mut codes = first;
        let radius = repair_radius(params);
        for _ in 0..REPAIR_ROUNDS {
            let previous = codes;
            codes = (0..grid.len())
                .map(|i| match previous[i].1 {
                    PixelStatus::RepairFailed => {
                        let predicted =
                            neighbour_prediction_reference(grid, i, radius, &previous, params);
                        repair(&bits[i], nbits, size, params, predicted)
                    }
                    _ => previous[i],
                })
                .collect();
        }
        codes
    }

    /// Bits of a tilted ramp of codes with `unreliable_share` of the pixels missing up to three
    /// low bits (some of them wrong), a few pixels unlit, from `seed`.
    fn ramp_bits(seed: u64, grid: Grid, nbits: u32, unreliable_share: f64) -> Vec<PixelBits> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let slope = rng.gen_range(0.3..1.8);
        let tilt = rng.gen_range(-0.5..0.5);
        (0..grid.len())
            .map(|i| {
                let (x, y) = ((i % grid.width) as f64, (i / grid.width) as f64);
                let code = (3.0 + slope * x + tilt * y).round().max(0.0) as u32;
                let mut b = PixelBits {
                    gray: (code ^ (code >> 1)) as u16,
                    reliable: bit_mask(nbits),
                    lighting: Lighting::Lit,
                };
                if rng.gen_bool(0.03) {
                    b.lighting = Lighting::Unlit;
                } else if rng.gen_bool(unreliable_share) {
                    let lost = rng.gen_range(1..=3);
                    b.reliable &= !((1u16 << lost) - 1);
                    b.gray ^= rng.gen_range(0..1u16 << lost);
                }
                b
            })
            .collect()
    }

    /// The adversarial codes send windows down both ways of the fast fit: ended at the first
    /// plane, and handed to the general fit (outliers, edges, steep windows), with and without
    /// the centre; so the comparison with the gathered fits covers both.
    #[test]
    fn adversarial_windows_take_both_paths_of_the_first_plane_fit() {
        let grid = Grid {
            width: 40,
            height: 30,
        };
        let params = DecodeParams::default();
        let radius = params.window_radius as usize;
        let mut taken = [[0usize; 2]; 2];
        let mut samples = Vec::new();
        for seed in 0..20 {
            let codes = adversarial_codes(seed, grid);
            for (i, &(code, status)) in codes.iter().enumerate() {
                grid.gather_valid(i, radius, &codes, &mut samples);
                let sums = WindowSums::of_samples(grid, i, radius, &samples);
                if sums.count == 0 || !status.is_valid() {
                    continue;
                }
                for (k, centre) in [None, Some(code)].into_iter().enumerate() {
                    let fast = sums.first_fit_if_final(&samples, &params, centre);
                    taken[k][usize::from(fast.is_some())] += 1;
                }
            }
        }
        for counts in taken {
            assert!(counts.iter().all(|&c| c > 100), "{taken:?}");
        }
    }

    /// The same for the repair's windows read through their column sums (pixels without a
    /// code, the repair's radius), on adversarial codes and on ramps with holes (where the
    /// 9 x 9 windows are clean enough to end at their first plane): both ways are taken.
    #[test]
    fn adversarial_repair_windows_take_both_paths_of_the_column_fit() {
        let grid = Grid {
            width: 40,
            height: 30,
        };
        let params = DecodeParams::default();
        let radius = repair_radius(&params);
        let mut taken = [0usize; 2];
        let mut buffer = ColumnBuffer::default();
        for seed in 0..20 {
            let ramp: Vec<(i32, PixelStatus)> = ramp_bits(seed, grid, 9, 0.4)
                .iter()
                .map(|b| initial_code(b, 9, 512, &params))
                .collect();
            for codes in [adversarial_codes(seed, grid), ramp] {
                let mut signed = Vec::new();
                signed_codes(&codes, &mut signed);
                for y in 0..grid.height {
                    let centres: Vec<usize> = (0..grid.width)
                        .filter(|&x| !codes[y * grid.width + x].1.is_valid())
                        .collect();
                    let windows =
                        RowColumns::new(grid, y, radius, (&codes, &signed), &mut buffer, &centres);
                    for &x in &centres {
                        let sums = windows.window(x);
                        if sums.count > 0 {
                            taken[usize::from(
                                windows.first_fit_if_final(x, &sums, &params).is_some(),
                            )] += 1;
                        }
                    }
                }
            }
        }
        assert!(taken.iter().all(|&c| c > 100), "{taken:?}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// The statistics taken from the gathered samples equal those read from the window,
        /// at the borders too, around valid and invalid centres.
        #[test]
        fn window_statistics_from_samples_equal_the_window_scan(
            seed in 0u64..1_000_000,
            width in 1usize..20,
            height in 1usize..20,
            radius in 1usize..5,
        ) {
            let grid = Grid { width, height };
            let bits = ramp_bits(seed, grid, 7, 0.5);
            let params = DecodeParams::default();
            let codes: Vec<(i32, PixelStatus)> =
                bits.iter().map(|b| initial_code(b, 7, 128, &params)).collect();
            let mut samples = Vec::new();
            for i in 0..grid.len() {
                grid.gather_valid(i, radius, &codes, &mut samples);
                let (a, b) = (WindowStats::new(grid, i, radius, &codes), WindowStats::of_samples(grid, i, radius, &samples));
                prop_assert_eq!((a.count, a.sum.to_bits(), a.min, a.max, a.size), (b.count, b.sum.to_bits(), b.min, b.max, b.size));
            }
        }

        /// The separable window scan marks exactly the pixels whose whole window (itself
        /// included) is inside the image, valid and within the smooth range, with that window's
        /// sum; and the check with it returns the check that reads every window, bit for bit.
        #[test]
        fn separable_smooth_windows_equal_the_window_scan(
            seed in 0u64..1_000_000,
            width in 1usize..24,
            height in 1usize..20,
            unreliable_share in 0.0f64..0.5,
            window_radius in 1u32..4,
        ) {
            let grid = Grid { width, height };
            let radius = window_radius as usize;
            let params = DecodeParams { window_radius, min_neighbours: 3, ..DecodeParams::default() };
            let bits = ramp_bits(seed, grid, 9, unreliable_share);
            let codes: Vec<(i32, PixelStatus)> =
                bits.iter().map(|b| initial_code(b, 9, 512, &params)).collect();
            let smooth = smooth_window_sums(grid, &codes, radius);
            for (i, &smooth_sum) in smooth.iter().enumerate() {
                let (x, y) = (i % width, i / width);
                let inside = x >= radius && y >= radius && x + radius < width && y + radius < height;
                let mut window = Vec::new();
                if inside {
                    for ny in y - radius..=y + radius {
                        for nx in x - radius..=x + radius {
                            window.push(codes[ny * width + nx]);
                        }
                    }
                }
                let all_valid = window.iter().all(|c| c.1.is_valid());
                let (lo, hi) = window.iter().fold((i32::MAX, i32::MIN), |(lo, hi), c| (lo.min(c.0), hi.max(c.0)));
                let expected = if inside && all_valid && hi - lo <= 2 * radius as i32 + 2 {
                    window.iter().map(|c| c.0).sum::<i32>()
                } else {
                    -1
                };
                prop_assert_eq!(smooth_sum, expected);
                let mut scratch = Scratch::default();
                let (c, f, st) = check_and_refine(grid, i, &codes, smooth_sum, &params, &mut scratch);
                let (rc, rf, rst) = check_and_refine_reference(grid, i, &codes, &params);
                prop_assert_eq!((c, f.to_bits(), st), (rc, rf.to_bits(), rst));
            }
        }

        /// The branch-free gather returns the valid neighbours of the plain scan, in its order.
        #[test]
        fn gather_equals_the_plain_scan(
            seed in 0u64..1_000_000,
            width in 1usize..20,
            height in 1usize..20,
            radius in 1usize..6,
        ) {
            let grid = Grid { width, height };
            let bits = ramp_bits(seed, grid, 7, 0.5);
            let params = DecodeParams::default();
            let codes: Vec<(i32, PixelStatus)> =
                bits.iter().map(|b| initial_code(b, 7, 128, &params)).collect();
            let mut samples = Vec::new();
            for i in 0..grid.len() {
                let (x, y) = ((i % width) as i32, (i / width) as i32);
                let mut plain = Vec::new();
                for ny in (y - radius as i32).max(0)..(y + radius as i32 + 1).min(height as i32) {
                    for nx in (x - radius as i32).max(0)..(x + radius as i32 + 1).min(width as i32) {
                        let (code, status) = codes[ny as usize * width + nx as usize];
                        if status.is_valid() && (nx, ny) != (x, y) {
                            plain.push(Sample { dx: nx - x, dy: ny - y, code });
                        }
                    }
                }
                grid.gather_valid(i, radius, &codes, &mut samples);
                prop_assert_eq!(&samples, &plain);
            }
        }

        /// The one-read window sums and the first-plane fast path give exactly the gathered
        /// samples' statistics, prediction and check (bit for bit), on adversarial codes
        /// (holes, off-by-few codes, outliers, depth edges, steep slopes), at the borders.
        #[test]
        fn window_sums_fast_path_equals_the_gathered_fits(
            seed in 0u64..1_000_000,
            width in 1usize..26,
            height in 1usize..22,
            window_radius in 1u32..5,
            min_neighbours in 0u32..9,
        ) {
            let grid = Grid { width, height };
            let params = DecodeParams { window_radius, min_neighbours, ..DecodeParams::default() };
            let codes = adversarial_codes(seed, grid);
            let mut scratch = Scratch::default();
            let mut samples = Vec::new();
            for radius in [window_radius as usize, repair_radius(&params)] {
                for i in 0..grid.len() {
                    grid.gather_valid(i, radius, &codes, &mut samples);
                    let sums = WindowSums::of_samples(grid, i, radius, &samples);
                    let (a, b) = (WindowStats::of_sums(&sums), WindowStats::new(grid, i, radius, &codes));
                    prop_assert_eq!((a.count, a.sum.to_bits(), a.min, a.max, a.size), (b.count, b.sum.to_bits(), b.min, b.max, b.size));
                    let has = |side: fn(i32, i32) -> bool| samples.iter().any(|s| side(s.dx, s.dy));
                    prop_assert_eq!(sums.surrounded(), has(|dx, _| dx < 0) && has(|dx, _| dx > 0) && has(|_, dy| dy < 0) && has(|_, dy| dy > 0));
                }
                // The repair's column sums and prediction, for the pixels without a code: all
                // of a row's at once (columns shared), and each alone.
                let mut buffer = ColumnBuffer::default();
                let mut signed = Vec::new();
                signed_codes(&codes, &mut signed);
                for y in 0..height {
                    let centres: Vec<usize> = (0..width).filter(|&x| !codes[y * width + x].1.is_valid()).collect();
                    for &x in &centres {
                        let i = y * width + x;
                        grid.gather_valid(i, radius, &codes, &mut samples);
                        let plain_sums = WindowSums::of_samples(grid, i, radius, &samples);
                        let plain = neighbour_prediction_reference(grid, i, radius, &codes, &params);
                        for row_centres in [&centres[..], &[x][..]] {
                            let windows = RowColumns::new(grid, y, radius, (&codes, &signed), &mut buffer, row_centres);
                            prop_assert_eq!(windows.window(x), plain_sums);
                            let fast = neighbour_prediction(&windows, x, &params, &mut scratch.samples, &mut scratch.fit);
                            prop_assert_eq!(fast.map(f64::to_bits), plain.map(f64::to_bits));
                        }
                    }
                }
            }
            let smooth = smooth_window_sums(grid, &codes, window_radius as usize);
            for (i, &smooth_sum) in smooth.iter().enumerate() {
                let (c, f, st) = check_and_refine(grid, i, &codes, smooth_sum, &params, &mut scratch);
                let (rc, rf, rst) = check_and_refine_reference(grid, i, &codes, &params);
                prop_assert_eq!((c, f.to_bits(), st), (rc, rf.to_bits(), rst));
            }
        }

        /// Retrying only the pixels whose window changed gives exactly the codes of retrying
        /// every waiting pixel every round.
        #[test]
        fn frontier_repair_equals_repairing_every_pixel_every_round(
            seed in 0u64..1_000_000,
            width in 6usize..30,
            height in 6usize..24,
            unreliable_share in 0.1f64..0.9,
            window_radius in 1u32..3,
        ) {
            let grid = Grid { width, height };
            let nbits = 7;
            let size = 128;
            let params = DecodeParams { window_radius, min_neighbours: 3, ..DecodeParams::default() };
            let bits = ramp_bits(seed, grid, nbits, unreliable_share);
            let first: Vec<(i32, PixelStatus)> =
                bits.iter().map(|b| initial_code(b, nbits, size, &params)).collect();
            let fast = repair_rounds(grid, &bits, nbits, first.clone(), size, &params);
            let plain = repair_rounds_every_pixel(grid, &bits, nbits, first, size, &params);
            prop_assert_eq!(fast, plain);
        }
    }
}

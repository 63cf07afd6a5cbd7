//! The one Gaussian blur: a sampled, truncated kernel and separable 1-D and 2-D passes with an
//! explicit border policy.
//!
//! Every output is a weighted sum accumulated from zero in kernel order (offset `-radius` first),
//! so a caller gets the same numbers whatever the element type; taps that fall outside the data
//! under [`Border::Zero`] add nothing. A 2-D blur runs along rows first, then along columns; the
//! column pass sums whole rows (contiguous, vectorisable) without transposing.
//!
//! Normalisation is the kernel's: [`Normalisation::Weights`] divides the weights by their sum
//! when the kernel is built, [`Normalisation::Outputs`] keeps the raw weights and divides each
//! output of a pass by their sum. The two agree to rounding; each caller keeps the one its
//! numbers were produced with.

use std::ops::{Add, Div, Mul};

/// What a kernel tap reads beyond the ends of the data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Border {
    /// Zero: what leaves the data is lost (and nothing comes in).
    Zero,
    /// The nearest element (edge replication).
    Clamp,
    /// Periodic data: the index wraps around.
    Wrap,
}

impl Border {
    /// The element index that offset position `i` reads from data of length `n` (> 0), or
    /// `None` for a zero tap.
    #[inline]
    fn index(self, i: isize, n: usize) -> Option<usize> {
        let n = n as isize;
        match self {
            Border::Zero => (0..n).contains(&i).then_some(i as usize),
            Border::Clamp => Some(i.clamp(0, n - 1) as usize),
            Border::Wrap => Some(i.rem_euclid(n) as usize),
        }
    }
}

/// Where a kernel's weights are normalised to unit sum.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Normalisation {
    /// The weights are divided by their sum when the kernel is built.
    Weights,
    /// The weights stay raw; each output of a pass is divided by the sum of all of them (also
    /// at a border where some taps fell outside: no renormalisation).
    Outputs,
}

/// Errors of the blur passes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BlurError {
    /// The image buffer does not hold `width * height` elements.
    #[error("image buffer holds {len} elements, not {width} x {height}")]
    Shape {
        len: usize,
        width: usize,
        height: usize,
    },
}

/// A floating-point type kernels are built and applied in (`f32` or `f64`).
///
/// The weight of offset `k` is `exp(-k^2 / (2 sigma^2))` evaluated in the type itself, with the
/// expression its callers' numbers were produced with: `exp(-0.5 (k / sigma)^2)` in `f64`,
/// `exp(-(k k) / (2 sigma sigma))` in `f32`.
pub trait KernelFloat:
    Copy + PartialOrd + Add<Output = Self> + Mul<Output = Self> + Div<Output = Self>
{
    /// Zero.
    const ZERO: Self;
    /// One.
    const ONE: Self;
    /// `ceil(truncate * sigma)`, at least 1, in taps.
    fn radius(sigma: Self, truncate: Self) -> usize;
    /// The unnormalised weight of integer offset `k`.
    fn weight(k: isize, sigma: Self) -> Self;
}

impl KernelFloat for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    fn radius(sigma: Self, truncate: Self) -> usize {
        (truncate * sigma).ceil().max(1.0) as usize
    }
    fn weight(k: isize, sigma: Self) -> Self {
        (-0.5 * (k as f64 / sigma).powi(2)).exp()
    }
}

impl KernelFloat for f32 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    fn radius(sigma: Self, truncate: Self) -> usize {
        (truncate * sigma).ceil().max(1.0) as usize
    }
    fn weight(k: isize, sigma: Self) -> Self {
        (-((k * k) as f32) / (2.0 * sigma * sigma)).exp()
    }
}

/// An element that can be blurred with weights of type `W`: a number, or a tuple of channels
/// blurred independently.
pub trait Sample<W>: Copy {
    /// The empty sum.
    const ZERO: Self;
    /// `self + w * v`.
    fn add_weighted(self, w: W, v: Self) -> Self;
    /// `self / d`.
    fn divide(self, d: W) -> Self;
}

impl Sample<f32> for f32 {
    const ZERO: Self = 0.0;
    #[inline(always)]
    fn add_weighted(self, w: f32, v: Self) -> Self {
        self + w * v
    }
    #[inline(always)]
    fn divide(self, d: f32) -> Self {
        self / d
    }
}

impl Sample<f64> for f64 {
    const ZERO: Self = 0.0;
    #[inline(always)]
    fn add_weighted(self, w: f64, v: Self) -> Self {
        self + w * v
    }
    #[inline(always)]
    fn divide(self, d: f64) -> Self {
        self / d
    }
}

impl<const N: usize> Sample<f64> for [f64; N] {
    const ZERO: Self = [0.0; N];
    #[inline(always)]
    fn add_weighted(mut self, w: f64, v: Self) -> Self {
        for (a, v) in self.iter_mut().zip(v) {
            *a += w * v;
        }
        self
    }
    #[inline(always)]
    fn divide(self, d: f64) -> Self {
        self.map(|a| a / d)
    }
}

/// A sampled Gaussian truncated at `radius` taps each side: weights of offsets
/// `-radius..=radius`.
#[derive(Debug, Clone, PartialEq)]
pub struct GaussianKernel<W> {
    weights: Vec<W>,
    /// The sum outputs are divided by ([`Normalisation::Outputs`]), if any.
    divisor: Option<W>,
}

impl<W: KernelFloat> GaussianKernel<W> {
    /// The Gaussian of standard deviation `sigma` (in taps), truncated at
    /// `ceil(truncate * sigma)` taps (at least 1). A `sigma` that is not positive gives the
    /// identity (a single unit tap).
    pub fn new(sigma: W, truncate: W, normalisation: Normalisation) -> Self {
        if sigma.partial_cmp(&W::ZERO) != Some(std::cmp::Ordering::Greater) {
            return Self::identity();
        }
        let r = W::radius(sigma, truncate) as isize;
        let raw: Vec<W> = (-r..=r).map(|k| W::weight(k, sigma)).collect();
        let sum = raw.iter().fold(W::ZERO, |a, &w| a + w);
        match normalisation {
            Normalisation::Weights => Self {
                weights: raw.iter().map(|&w| w / sum).collect(),
                divisor: None,
            },
            Normalisation::Outputs => Self {
                weights: raw,
                divisor: Some(sum),
            },
        }
    }

    /// The single unit tap.
    pub fn identity() -> Self {
        Self {
            weights: vec![W::ONE],
            divisor: None,
        }
    }

    /// Taps each side of the centre.
    pub fn radius(&self) -> usize {
        self.weights.len() / 2
    }

    /// The weights of offsets `-radius..=radius` (unnormalised under
    /// [`Normalisation::Outputs`]).
    pub fn weights(&self) -> &[W] {
        &self.weights
    }

    /// `(offset, weight)` of every tap, offset `-radius` first.
    pub fn taps(&self) -> impl Iterator<Item = (isize, W)> + '_ {
        let r = self.radius() as isize;
        self.weights
            .iter()
            .enumerate()
            .map(move |(i, &w)| (i as isize - r, w))
    }

    /// Whether blurring with this kernel leaves the data unchanged (a single tap).
    pub fn is_identity(&self) -> bool {
        self.weights.len() == 1
    }

    /// The output of a pass from its accumulated weighted sum.
    #[inline(always)]
    fn finish<S: Sample<W>>(&self, acc: S) -> S {
        match self.divisor {
            Some(d) => acc.divide(d),
            None => acc,
        }
    }
}

impl GaussianKernel<f64> {
    /// The kernel with its weights (and divisor) rounded to `f32`.
    pub fn to_f32(&self) -> GaussianKernel<f32> {
        GaussianKernel {
            weights: self.weights.iter().map(|&w| w as f32).collect(),
            divisor: self.divisor.map(|d| d as f32),
        }
    }
}

/// `line` = `data` with `r` border elements each side under `border`.
fn pad<S: Copy>(line: &mut [S], data: &[S], r: usize, border: Border, zero: S) {
    for (i, l) in line.iter_mut().enumerate() {
        *l = match border.index(i as isize - r as isize, data.len()) {
            Some(j) => data[j],
            None => zero,
        };
    }
}

/// Outputs a [`convolve_padded`] pass accumulates side by side (a block stays in L1).
const CONVOLVE_BLOCK: usize = 512;

/// One pass along `line` (already padded by the kernel radius) into `out`.
///
/// Tap by tap over a block of outputs, not output by output over the taps: each output still
/// sums its taps from zero in kernel order (the same numbers), but neighbouring outputs
/// accumulate in parallel lanes instead of one dependent chain of adds per output (about 10x
/// faster on a full-size row).
#[inline]
fn convolve_padded<W: KernelFloat, S: Sample<W>>(
    out: &mut [S],
    line: &[S],
    kernel: &GaussianKernel<W>,
) {
    for (b, block) in out.chunks_mut(CONVOLVE_BLOCK).enumerate() {
        let start = b * CONVOLVE_BLOCK;
        block.fill(S::ZERO);
        for (j, &w) in kernel.weights.iter().enumerate() {
            let taps = &line[start + j..start + j + block.len()];
            for (o, &v) in block.iter_mut().zip(taps) {
                *o = o.add_weighted(w, v);
            }
        }
        if kernel.divisor.is_some() {
            block.iter_mut().for_each(|o| *o = kernel.finish(*o));
        }
    }
}

/// `data` convolved with `kernel` under `border`.
pub fn blur_1d<W: KernelFloat, S: Sample<W>>(
    data: &[S],
    kernel: &GaussianKernel<W>,
    border: Border,
) -> Vec<S> {
    if kernel.is_identity() || data.is_empty() {
        return data.to_vec();
    }
    let r = kernel.radius();
    let mut line = vec![S::ZERO; data.len() + 2 * r];
    pad(&mut line, data, r, border, S::ZERO);
    let mut out = vec![S::ZERO; data.len()];
    convolve_padded(&mut out, &line, kernel);
    out
}

/// In-place separable blur of a row-major `width` x `height` image: rows, then columns, both
/// with `kernel` under `border`. On the calling thread (callers that already run in parallel,
/// such as the renderer's bins, keep it so); see [`blur_2d_mapped`] for a field blurred on every
/// core.
pub fn blur_2d<W: KernelFloat, S: Sample<W>>(
    image: &mut [S],
    width: usize,
    height: usize,
    kernel: &GaussianKernel<W>,
    border: Border,
) -> Result<(), BlurError> {
    if !needs_blur(image, width, height, kernel)? {
        return Ok(());
    }
    let r = kernel.radius();
    let mut line = vec![S::ZERO; width + 2 * r];
    for row in image.chunks_exact_mut(width) {
        blur_row(row, &mut line, kernel, border);
    }
    let src = image.to_vec();
    for (y, out) in image.chunks_exact_mut(width).enumerate() {
        let row = |yy: usize| &src[yy * width..(yy + 1) * width];
        blur_column_row(out, y, row, height, kernel, border);
    }
    Ok(())
}

/// The image whose pixel `i` (row-major, `width` x `height`) is `source(i)`, blurred as
/// [`blur_2d`] blurs it (the same numbers), each output pixel handed to `map(i, blurred)`; the
/// results in pixel order. The image itself is never held: bands of 64 rows (`BAND_ROWS`) are
/// blurred on rayon's threads, each from its own rows and the rows its kernel reaches around
/// them (`source` is asked for those again by the next band). For a full-size field blurred on
/// an otherwise idle pool (the point normals' moments, the normal fusion's sums), not from
/// inside a parallel loop. Why: a full-size field and the copy its column pass read from were
/// fresh memory for the kernel to fault in (the point normals' 113 MB of moments twice over:
/// ~0.2 CPU-s of page clearing at full size, perf), where a band's buffers are reused.
pub fn blur_2d_mapped<W, S, T>(
    width: usize,
    height: usize,
    kernel: &GaussianKernel<W>,
    border: Border,
    source: impl Fn(usize) -> S + Sync,
    map: impl Fn(usize, S) -> T + Sync,
) -> Vec<T>
where
    W: KernelFloat + Sync,
    S: Sample<W> + Send + Sync,
    T: Send,
{
    blur_2d_mapped_in_bands(width, height, kernel, border, source, map, BAND_ROWS)
}

/// Rows per band of [`blur_2d_mapped`]: a band reads its kernel's radius of rows on either side
/// again (5 rows each side at the point normals' 1.5 px, 74 rows held: 8 MB of moments at full
/// width).
const BAND_ROWS: usize = 64;

/// [`blur_2d_mapped`] in bands of `band_rows` rows (the result does not depend on it; tests take
/// small bands).
fn blur_2d_mapped_in_bands<W, S, T>(
    width: usize,
    height: usize,
    kernel: &GaussianKernel<W>,
    border: Border,
    source: impl Fn(usize) -> S + Sync,
    map: impl Fn(usize, S) -> T + Sync,
    band_rows: usize,
) -> Vec<T>
where
    W: KernelFloat + Sync,
    S: Sample<W> + Send + Sync,
    T: Send,
{
    use rayon::prelude::*;
    // A size beyond memory fails to allocate below, never wraps to a smaller image.
    let n = width.saturating_mul(height);
    if kernel.is_identity() || n == 0 {
        // `blur_2d` leaves such an image as it is.
        return (0..n).into_par_iter().map(|i| map(i, source(i))).collect();
    }
    let mut out = Vec::with_capacity(n);
    out.spare_capacity_mut()[..n]
        .par_chunks_mut(band_rows.max(1) * width)
        .enumerate()
        .for_each_init(
            || BandRows::new(width, height),
            |band, (b, outputs)| {
                let first = b * band_rows.max(1);
                let rows = first..first + outputs.len() / width;
                band.fill(rows.clone(), kernel, border, &source);
                for (y, row) in rows.zip(outputs.chunks_exact_mut(width)) {
                    let column = band.column_row(y, kernel, border);
                    for (x, (o, &v)) in row.iter_mut().zip(column).enumerate() {
                        o.write(map(y * width + x, v));
                    }
                }
            },
        );
    // SAFETY: the chunks cover the first `n` elements of the spare capacity, and every element
    // of every chunk was written above (a chunk is whole rows: `outputs.len() / width` rows of
    // `width` pixels each).
    unsafe { out.set_len(n) };
    out
}

/// The rows one band of [`blur_2d_mapped`] reads, row-blurred, and its scratch lines.
struct BandRows<S> {
    width: usize,
    height: usize,
    /// The rows held, `width` samples each, in the order of `slot`.
    rows: Vec<S>,
    /// Per image row: its place in `rows`, if held.
    slot: Vec<Option<usize>>,
    /// The row pass's padded line.
    line: Vec<S>,
    /// One output row of the column pass.
    column: Vec<S>,
}

impl<S: Copy> BandRows<S> {
    fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            rows: Vec::new(),
            slot: vec![None; height],
            line: Vec::new(),
            column: Vec::new(),
        }
    }

    /// Holds the rows the column pass of the output rows `band` reads (under `border`), each
    /// from `source` and blurred along itself, as [`blur_2d`]'s row pass blurs it.
    fn fill<W: KernelFloat>(
        &mut self,
        band: std::ops::Range<usize>,
        kernel: &GaussianKernel<W>,
        border: Border,
        source: &impl Fn(usize) -> S,
    ) where
        S: Sample<W>,
    {
        let (w, h, r) = (self.width, self.height, kernel.radius());
        self.slot.fill(None);
        self.rows.clear();
        let reach = band.start as isize - r as isize..(band.end + r) as isize;
        for y in reach.filter_map(|y| border.index(y, h)) {
            if self.slot[y].is_none() {
                self.slot[y] = Some(self.rows.len() / w);
                self.rows.extend((y * w..(y + 1) * w).map(source));
            }
        }
        self.line.resize(w + 2 * r, S::ZERO);
        for row in self.rows.chunks_exact_mut(w) {
            blur_row(row, &mut self.line, kernel, border);
        }
    }

    /// Output row `y` of the column pass over the rows held (those of `y`'s band).
    fn column_row<W: KernelFloat>(
        &mut self,
        y: usize,
        kernel: &GaussianKernel<W>,
        border: Border,
    ) -> &[S]
    where
        S: Sample<W>,
    {
        let (w, h) = (self.width, self.height);
        self.column.resize(w, S::ZERO);
        let (rows, slot) = (&self.rows, &self.slot);
        let held = |yy: usize| {
            // `fill` held every row the band's kernel reaches.
            let k = slot[yy].unwrap_or_default();
            &rows[k * w..(k + 1) * w]
        };
        blur_column_row(&mut self.column, y, held, h, kernel, border);
        &self.column
    }
}

/// Checks the image's shape; whether blurring it changes anything (not for the identity kernel
/// or an empty image).
fn needs_blur<W: KernelFloat, S>(
    image: &[S],
    width: usize,
    height: usize,
    kernel: &GaussianKernel<W>,
) -> Result<bool, BlurError> {
    if width.checked_mul(height) != Some(image.len()) {
        return Err(BlurError::Shape {
            len: image.len(),
            width,
            height,
        });
    }
    Ok(!(kernel.is_identity() || image.is_empty()))
}

/// The row pass over one row, in place; `line` is scratch of `row.len() + 2 radius`.
#[inline]
fn blur_row<W: KernelFloat, S: Sample<W>>(
    row: &mut [S],
    line: &mut [S],
    kernel: &GaussianKernel<W>,
    border: Border,
) {
    pad(line, row, kernel.radius(), border, S::ZERO);
    convolve_padded(row, line, kernel);
}

/// Output row `y` of the column pass over the rows `row(yy)` of an image `height` rows tall
/// (the row pass's result): a weighted sum of whole input rows, in kernel order.
#[inline]
fn blur_column_row<'a, W: KernelFloat, S: Sample<W> + 'a>(
    out: &mut [S],
    y: usize,
    row: impl Fn(usize) -> &'a [S],
    height: usize,
    kernel: &GaussianKernel<W>,
    border: Border,
) {
    let r = kernel.radius();
    out.fill(S::ZERO);
    for (j, &w) in kernel.weights.iter().enumerate() {
        let Some(yy) = border.index((y + j) as isize - r as isize, height) else {
            continue;
        };
        for (o, &v) in out.iter_mut().zip(row(yy)) {
            *o = o.add_weighted(w, v);
        }
    }
    if kernel.divisor.is_some() {
        out.iter_mut().for_each(|o| *o = kernel.finish(*o));
    }
}

#[cfg(test)]
#[path = "gaussian_blur_tests.rs"]
mod tests;

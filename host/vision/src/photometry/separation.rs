//! Direct/global separation with high-frequency illumination (Nayar et al. 2006), with the
//! projector black-level correction of DESIGN section 4.
//!
//! Conventions
//! - Inputs are linear camera values (the frames' scale), one image per shift of the stripe
//!   pattern, all from the same projector; the images may also contain a constant offset from
//!   light that does not change with the pattern (other projectors showing black, ambient), which
//!   the caller removes beforehand if it knows it (it biases only the global component).
//! - `black_level` b is the projector's emitted light for a black pixel as a fraction of white
//!   (`calib::ProjectorResponse::black_level`); stripes are binary, so the response curve's gamma
//!   plays no role here.
//! - Output radiances are "under full white": `direct + global` equals the white image.
//!
//! Model per pixel and channel, for a stripe pattern that lights half of the projector pixels:
//! `Lmax = Ld + (1 + b)/2 Lg` and `Lmin = b Ld + (1 + b)/2 Lg`, hence
//! `Ld = (Lmax - Lmin)/(1 - b)` and `Lg = 2 (Lmin - b Lmax)/(1 - b^2)`.
//!
//! Limits (measured by the tests of this module, see `/work/notes/photometry.md`):
//! - Saturated samples break `Lmax`: such pixels are flagged and their outputs are zero.
//! - Projector defocus and a camera footprint straddling a stripe edge lower the contrast
//!   `Lmax - Lmin`; with 3-px stripes shifted 1 px, a footprint up to 2 projector pixels still
//!   sees one fully lit and one fully dark shift, so the estimate stays exact without blur.
//! - The method assumes the global light is a smooth function of the pattern (half of it from lit
//!   pixels whatever the shift). A scattering kernel that is not wide compared to the stripe period
//!   leaks global light into the direct estimate; the leak is measured, not corrected.
//! - `max`/`min` of noisy samples are biased (up and down by about 0.85 sigma with three samples per
//!   level), which biases `Ld` up and `Lg` down by about 1.7 sigma of the frame noise.

use std::mem::MaybeUninit;

use image::Rgb32FImage;

/// Errors of the separation.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SeparationError {
    /// Fewer than two shifted frames were given.
    #[error("separation needs at least 2 shifted high-frequency frames, got {0}")]
    TooFewFrames(usize),
    /// The frames do not all have the same size.
    #[error("high-frequency frame {index} is {got:?}, the first one is {expected:?}")]
    SizeMismatch {
        index: usize,
        got: (u32, u32),
        expected: (u32, u32),
    },
    /// The black level is outside [0, 1).
    #[error("projector black level {0} is outside [0, 1)")]
    BadBlackLevel(f64),
    /// The blur correction needs exactly one frame per stripe shift.
    #[error("blur correction needs {expected} frames (2 x stripe width), got {got}")]
    ShiftCount { expected: usize, got: usize },
    /// The per-pixel leak map of the kernel-aware separation has the wrong length.
    #[error("leak map has {got} pixels, the frames {expected}")]
    LeakSize { expected: usize, got: usize },
}

/// Parameters of the separation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeparationParams {
    /// Projector black level b (fraction of white emitted by a black pixel).
    pub black_level: f32,
    /// A sample at or above this linear value is treated as saturated.
    pub saturation: f32,
    /// Blur of the stripes as seen by a camera pixel (projector defocus combined with the camera
    /// footprint), Gaussian sigma in projector pixels. 0 applies Nayar's formulas as they are;
    /// above 0 the contrast lost to the blur at the pixel's stripe phase is restored (see
    /// [`blurred_contrast`]) and the global part is taken from the mean of the shifts.
    pub blur_px: f32,
    /// Stripe width of the pattern in projector pixels (the frames are the `2 * stripe_px` shifts);
    /// needed only for the blur correction.
    pub stripe_px: u32,
}

impl Default for SeparationParams {
    fn default() -> Self {
        Self {
            black_level: 0.0,
            // 12-bit sensor: the top code is 1.0; keep one code of margin.
            saturation: 1.0 - 1.0 / 4095.0,
            blur_px: 0.0,
            stripe_px: 3,
        }
    }
}

/// Why a pixel has no separation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum SeparationFlag {
    /// Separated normally.
    Ok = 0,
    /// A sample was saturated in some channel; outputs are zero.
    Saturated = 1,
    /// A sample was not finite; outputs are zero.
    NonFinite = 2,
}

/// Direct and global images plus per-pixel flags and counters.
#[derive(Debug, Clone)]
pub struct Separation {
    pub direct: Rgb32FImage,
    pub global: Rgb32FImage,
    /// Row-major [`SeparationFlag`] per pixel.
    pub flags: Vec<SeparationFlag>,
    pub stats: SeparationStats,
}

/// What the separation had to clamp or refuse.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SeparationStats {
    pub pixels: u64,
    pub saturated_pixels: u64,
    pub non_finite_pixels: u64,
    /// Channel values where a negative direct or global was clamped to zero.
    pub clamped_negative: u64,
}

impl SeparationStats {
    /// Counts a pixel the kernels flagged (and left at zero) by its flag.
    #[inline(always)]
    fn count_flagged(&mut self, status: SeparationFlag) {
        self.saturated_pixels += u64::from(status == SeparationFlag::Saturated);
        self.non_finite_pixels += u64::from(status == SeparationFlag::NonFinite);
    }
}

/// A pixel's flag from whether all its samples are finite and its brightest sample per channel:
/// non-finite first, then saturated. Shared by the sharp and the blurred kernels.
#[inline(always)]
fn pixel_status(finite: bool, lmax: &[f32], saturation: f32) -> SeparationFlag {
    if !finite {
        SeparationFlag::NonFinite
    } else if lmax.iter().any(|&v| v >= saturation) {
        SeparationFlag::Saturated
    } else {
        SeparationFlag::Ok
    }
}

/// Direct and global radiance of one channel from the extreme samples; never negative.
/// Returns `(direct, global, clamped)`.
pub fn separate_sample(lmax: f32, lmin: f32, black_level: f32) -> (f32, f32, bool) {
    let b = black_level;
    let direct = (lmax - lmin) / (1.0 - b);
    let global = 2.0 * (lmin - b * lmax) / (1.0 - b * b);
    // Noise can push the global part of a purely direct pixel (and, through `b`, vice versa)
    // below zero; clamp and keep the sum `direct + global` where possible.
    let total = direct + global;
    match (direct < 0.0, global < 0.0) {
        (false, false) => (direct, global, false),
        (true, false) => (0.0, total.max(0.0), true),
        (false, true) => (total.max(0.0), 0.0, true),
        (true, true) => (0.0, 0.0, true),
    }
}

/// Separates the direct and global components from the shifted stripe frames of one projector.
pub fn separate(
    frames: &[&Rgb32FImage],
    params: &SeparationParams,
) -> Result<Separation, SeparationError> {
    if frames.len() < 2 {
        return Err(SeparationError::TooFewFrames(frames.len()));
    }
    let b = params.black_level;
    if !(0.0..1.0).contains(&b) {
        return Err(SeparationError::BadBlackLevel(b as f64));
    }
    if params.blur_px > 0.0 && frames.len() != 2 * params.stripe_px as usize {
        return Err(SeparationError::ShiftCount {
            expected: 2 * params.stripe_px as usize,
            got: frames.len(),
        });
    }
    let (w, h) = frames[0].dimensions();
    for (index, f) in frames.iter().enumerate() {
        if f.dimensions() != (w, h) {
            return Err(SeparationError::SizeMismatch {
                index,
                got: f.dimensions(),
                expected: (w, h),
            });
        }
    }
    let raws: Vec<&[f32]> = frames.iter().map(|f| f.as_raw().as_slice()).collect();
    let shifts = ShiftTables::new(raws.len(), params);
    let n = w as usize * h as usize;
    let (direct, global, flags, stats) = separate_all(&raws, n, params, &shifts);
    let to_image =
        |v: Vec<f32>| Rgb32FImage::from_raw(w, h, v).unwrap_or_else(|| Rgb32FImage::new(w, h));
    Ok(Separation {
        direct: to_image(direct),
        global: to_image(global),
        flags,
        stats,
    })
}

/// Pixels per chunk of the parallel loop: a chunk's extremes (2 x 24 KB) and its six frame
/// slices (6 x 24 KB) stay in the core's L2 cache while each frame is streamed through once.
const CHUNK_PIXELS: usize = 2048;

/// The outputs of [`separate`] for the `n` pixels of `raws`, chunk by chunk on every core. Why
/// the outputs are written into uninitialised capacity: each of the two 17 MB outputs of a
/// full-size separation was zeroed (`calloc`) and then overwritten, an extra pass over memory in
/// a loop that is bound by memory traffic; now every value is written exactly once (the chunk
/// kernels write each output value and flag of their chunk, flagged pixels included).
fn separate_all(
    raws: &[&[f32]],
    n: usize,
    params: &SeparationParams,
    shifts: &ShiftTables,
) -> (Vec<f32>, Vec<f32>, Vec<SeparationFlag>, SeparationStats) {
    use rayon::prelude::*;
    let mut direct: Vec<f32> = mlsss_core::resources::vec_on_huge_pages(n * 3);
    let mut global: Vec<f32> = mlsss_core::resources::vec_on_huge_pages(n * 3);
    let mut flags: Vec<SeparationFlag> = Vec::with_capacity(n);
    let partial = direct.spare_capacity_mut()[..n * 3]
        .par_chunks_mut(CHUNK_PIXELS * 3)
        .zip(global.spare_capacity_mut()[..n * 3].par_chunks_mut(CHUNK_PIXELS * 3))
        .zip(flags.spare_capacity_mut()[..n].par_chunks_mut(CHUNK_PIXELS))
        .enumerate()
        .map(|(ci, ((d, g), fl))| {
            let first = ci * CHUNK_PIXELS;
            if shifts.contrast.is_some() {
                let extremes = BandExtremes::gather(raws, first, fl.len(), shifts);
                separate_band(&extremes, params, shifts, d, g, fl)
            } else {
                separate_chunk_sharp_best(raws, first, params, d, g, fl)
            }
        })
        .reduce(SeparationStats::default, SeparationStats::add);
    // SAFETY: the three spare capacities were split into chunks covering exactly their first
    // `n * 3`, `n * 3` and `n` elements, and both chunk kernels write every element of the
    // chunks they are given (one `write` per output value and per flag, in loops over the whole
    // chunk with no early exit), so these elements are initialised.
    unsafe {
        direct.set_len(n * 3);
        global.set_len(n * 3);
        flags.set_len(n);
    }
    let stats = SeparationStats {
        pixels: n as u64,
        ..partial
    };
    (direct, global, flags, stats)
}

impl SeparationStats {
    fn add(self, other: Self) -> Self {
        Self {
            pixels: self.pixels + other.pixels,
            saturated_pixels: self.saturated_pixels + other.saturated_pixels,
            non_finite_pixels: self.non_finite_pixels + other.non_finite_pixels,
            clamped_negative: self.clamped_negative + other.clamped_negative,
        }
    }
}

/// [`separate_chunk_sharp`], compiled for AVX2 where the CPU has it (eight lanes instead of
/// four for the extremes and the divisions; the same IEEE operations, no FMA, hence the same
/// bits: test).
fn separate_chunk_sharp_best(
    raws: &[&[f32]],
    first: usize,
    params: &SeparationParams,
    direct: &mut [MaybeUninit<f32>],
    global: &mut [MaybeUninit<f32>],
    flags: &mut [MaybeUninit<SeparationFlag>],
) -> SeparationStats {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, the one feature the variant is compiled for.
        return unsafe { separate_chunk_sharp_avx2(raws, first, params, direct, global, flags) };
    }
    separate_chunk_sharp(raws, first, params, direct, global, flags)
}

/// [`separate_chunk_sharp`] compiled with AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn separate_chunk_sharp_avx2(
    raws: &[&[f32]],
    first: usize,
    params: &SeparationParams,
    direct: &mut [MaybeUninit<f32>],
    global: &mut [MaybeUninit<f32>],
    flags: &mut [MaybeUninit<SeparationFlag>],
) -> SeparationStats {
    separate_chunk_sharp(raws, first, params, direct, global, flags)
}

/// Nayar's formulas without blur correction for the pixels `first..first + flags.len()`, in one
/// read of each frame: the extremes of every value (six frames read side by side when there
/// are six, else frame after frame into the chunk's buffers), then the outputs of every value
/// (branch-free, [`separate_sample`]'s arithmetic in its order), then the flags, with zero
/// outputs for flagged pixels. Every output value and flag of the chunk is written. The same
/// results per value as [`separate_sample`] on that pixel's own max and min (test).
#[inline(always)]
fn separate_chunk_sharp(
    raws: &[&[f32]],
    first: usize,
    params: &SeparationParams,
    direct: &mut [MaybeUninit<f32>],
    global: &mut [MaybeUninit<f32>],
    flags: &mut [MaybeUninit<SeparationFlag>],
) -> SeparationStats {
    let values = flags.len() * 3;
    let mut lmax = [f32::NEG_INFINITY; CHUNK_PIXELS * 3];
    let mut lmin = [f32::INFINITY; CHUNK_PIXELS * 3];
    // 0 while every sample of the value is finite (an integer mask, not `bool`s: it vectorises
    // with the extremes).
    let mut bad = [0u32; CHUNK_PIXELS * 3];
    let (lmax, lmin, bad) = (&mut lmax[..values], &mut lmin[..values], &mut bad[..values]);
    let range = first * 3..first * 3 + values;
    match raws {
        [a, b, c, d, e, f] => {
            // The booth's six shifts: all six read side by side, the extremes kept in registers
            // (frame after frame, each value's max, min and mask went through the cache six
            // times; the kernel is bound by memory traffic).
            let frames = [a, b, c, d, e, f].map(|raw| &raw[range.clone()]);
            extremes_of_six(frames, lmax, lmin, bad);
        }
        _ => {
            for raw in raws {
                let frame = &raw[range.clone()];
                for (((mx, mn), bad), &v) in lmax
                    .iter_mut()
                    .zip(lmin.iter_mut())
                    .zip(bad.iter_mut())
                    .zip(frame)
                {
                    *mx = mx.max(v);
                    *mn = mn.min(v);
                    *bad |= u32::from(!v.is_finite());
                }
            }
        }
    }
    let b = params.black_level;
    let mut stats = SeparationStats::default();
    // Every value's outputs as if its pixel were fine (a loop the compiler vectorises); the few
    // flagged pixels are zeroed below.
    let outputs = direct.iter_mut().zip(global.iter_mut());
    for ((d_out, g_out), (&mx, &mn)) in outputs.zip(lmax.iter().zip(lmin.iter())) {
        let (d, g, clamped) = separate_sample_branch_free(mx, mn, b);
        d_out.write(d);
        g_out.write(g);
        stats.clamped_negative += u64::from(clamped);
    }
    let pixels = lmax
        .chunks_exact(3)
        .zip(lmin.chunks_exact(3))
        .zip(bad.chunks_exact(3))
        .zip(direct.chunks_exact_mut(3))
        .zip(global.chunks_exact_mut(3))
        .zip(flags.iter_mut());
    for (((((mx, mn), bad), d_out), g_out), flag) in pixels {
        let status = pixel_status((bad[0] | bad[1] | bad[2]) == 0, mx, params.saturation);
        flag.write(status);
        if status != SeparationFlag::Ok {
            stats.count_flagged(status);
            for c in 0..3 {
                // Only separated pixels count their clamps.
                let (_, _, clamped) = separate_sample_branch_free(mx[c], mn[c], b);
                stats.clamped_negative -= u64::from(clamped);
                d_out[c].write(0.0);
                g_out[c].write(0.0);
            }
        }
    }
    stats
}

/// Per value, the max and min over six frames and whether any sample is not finite.
#[inline(always)]
fn extremes_of_six(frames: [&[f32]; 6], lmax: &mut [f32], lmin: &mut [f32], bad: &mut [u32]) {
    let [a, b, c, d, e, f] = frames;
    let out = lmax.iter_mut().zip(lmin.iter_mut()).zip(bad.iter_mut());
    let samples = a.iter().zip(b).zip(c).zip(d).zip(e).zip(f);
    for (((mx, mn), bad), (((((&a, &b), &c), &d), &e), &f)) in out.zip(samples) {
        // In frame order from -inf/+inf, as the frame-after-frame loop does (the same results,
        // NaN samples included: `max`/`min` skip them).
        *mx = f32::NEG_INFINITY.max(a).max(b).max(c).max(d).max(e).max(f);
        *mn = f32::INFINITY.min(a).min(b).min(c).min(d).min(e).min(f);
        *bad = [a, b, c, d, e, f]
            .iter()
            .fold(0, |m, v| m | u32::from(!v.is_finite()));
    }
}

/// [`separate_sample`] with selects instead of a match (the same arithmetic in the same order,
/// hence the same results), so that a loop over values vectorises.
#[inline(always)]
fn separate_sample_branch_free(lmax: f32, lmin: f32, black_level: f32) -> (f32, f32, bool) {
    let b = black_level;
    let direct = (lmax - lmin) / (1.0 - b);
    let global = 2.0 * (lmin - b * lmax) / (1.0 - b * b);
    let total = direct + global;
    let (direct_negative, global_negative) = (direct < 0.0, global < 0.0);
    let rest = total.max(0.0);
    let d = if direct_negative {
        0.0
    } else if global_negative {
        rest
    } else {
        direct
    };
    let g = if global_negative {
        0.0
    } else if direct_negative {
        rest
    } else {
        global
    };
    (d, g, direct_negative | global_negative)
}

/// What every pixel of one separation shares, computed once: the weights of the first DFT
/// coefficient over the shifts, and (with blur) the contrast against the stripe phase.
struct ShiftTables {
    /// `(cos, sin)` of `2 pi s / shifts` for shift `s`.
    phasors: Vec<(f32, f32)>,
    /// `omega = 2 pi / shifts`.
    omega: f32,
    contrast: Option<ContrastTable>,
}

impl ShiftTables {
    fn new(shifts: usize, params: &SeparationParams) -> Self {
        let omega = std::f32::consts::TAU / shifts as f32;
        Self {
            phasors: (0..shifts)
                .map(|s| ((omega * s as f32).cos(), (omega * s as f32).sin()))
                .collect(),
            omega,
            contrast: (params.blur_px > 0.0)
                .then(|| ContrastTable::new(params.stripe_px as f32, params.blur_px)),
        }
    }
}

/// [`blurred_contrast`] of one stripe width and blur, sampled at [`ContrastTable::CELLS`] + 1
/// phases and interpolated linearly. Why: the exact value costs 60 exponentials per pixel (two
/// CDFs for 5 stripe images at each of 6 shifts), a third of the full-size separation. The
/// contrast is smooth in the phase except where the brightest or darkest shift changes, so the
/// interpolation is within ~1e-4 of it (test).
struct ContrastTable {
    values: Vec<f32>,
}

impl ContrastTable {
    const CELLS: usize = 4096;

    fn new(stripe: f32, blur: f32) -> Self {
        Self {
            values: (0..=Self::CELLS)
                .map(|i| blurred_contrast(i as f32 / Self::CELLS as f32, stripe, blur))
                .collect(),
        }
    }

    /// The contrast at phase `frac` in [0, 1].
    fn at(&self, frac: f32) -> f32 {
        let x = frac.clamp(0.0, 1.0) * Self::CELLS as f32;
        let i = (x as usize).min(Self::CELLS - 1);
        let t = x - i as f32;
        self.values[i] + t * (self.values[i + 1] - self.values[i])
    }
}

/// Per-value extremes and sums of one band of pixels over the shifted frames (and, with the blur
/// correction, the first DFT coefficient of each pixel's channel sum). Gathered frame by frame:
/// each frame's band is read once, in order, by loops the compiler vectorises; this replaced a
/// per-pixel loop across the frames, with the same arithmetic in the same order per value.
struct BandExtremes {
    lmax: Vec<f32>,
    lmin: Vec<f32>,
    /// Per-value sums over the shifts (empty without blur correction).
    sum: Vec<f32>,
    finite: Vec<bool>,
    /// Real and imaginary parts of the first DFT coefficient per pixel (empty without blur
    /// correction, which alone needs the stripe phase).
    re: Vec<f32>,
    im: Vec<f32>,
}

impl BandExtremes {
    fn gather(raws: &[&[f32]], first_pixel: usize, pixels: usize, shifts: &ShiftTables) -> Self {
        let values = pixels * 3;
        let phase = shifts.contrast.is_some();
        let mut band = Self {
            lmax: vec![f32::NEG_INFINITY; values],
            lmin: vec![f32::INFINITY; values],
            sum: vec![0.0; if phase { values } else { 0 }],
            finite: vec![true; values],
            re: vec![0.0; if phase { pixels } else { 0 }],
            im: vec![0.0; if phase { pixels } else { 0 }],
        };
        for (raw, &(cos, sin)) in raws.iter().zip(&shifts.phasors) {
            let frame = &raw[first_pixel * 3..first_pixel * 3 + values];
            let accumulators = band
                .lmax
                .iter_mut()
                .zip(band.lmin.iter_mut())
                .zip(band.finite.iter_mut());
            for (((lmax, lmin), finite), &v) in accumulators.zip(frame) {
                *lmax = lmax.max(v);
                *lmin = lmin.min(v);
                *finite &= v.is_finite();
            }
            if phase {
                // The sums serve only the blur correction's global part.
                for (sum, &v) in band.sum.iter_mut().zip(frame) {
                    *sum += v;
                }
                let coefficient = band.re.iter_mut().zip(band.im.iter_mut());
                for ((re, im), rgb) in coefficient.zip(frame.chunks_exact(3)) {
                    let grey: f32 = rgb.iter().sum();
                    *re += grey * cos;
                    *im -= grey * sin;
                }
            }
        }
        band
    }
}

/// Direct and global of each pixel of a band from its [`BandExtremes`] (with blur correction);
/// flagged pixels get zero outputs. Writes every output value and flag of the band.
fn separate_band(
    band: &BandExtremes,
    params: &SeparationParams,
    shifts: &ShiftTables,
    direct: &mut [MaybeUninit<f32>],
    global: &mut [MaybeUninit<f32>],
    flags: &mut [MaybeUninit<SeparationFlag>],
) -> SeparationStats {
    let mut stats = SeparationStats::default();
    let b = params.black_level;
    let pixels = direct
        .chunks_exact_mut(3)
        .zip(global.chunks_exact_mut(3))
        .zip(flags.iter_mut())
        .enumerate();
    for (p, ((d_out, g_out), flag)) in pixels {
        let o = p * 3;
        let (lmax, lmin) = (&band.lmax[o..o + 3], &band.lmin[o..o + 3]);
        let status = pixel_status(
            band.finite[o..o + 3].iter().all(|&f| f),
            lmax,
            params.saturation,
        );
        flag.write(status);
        if status != SeparationFlag::Ok {
            stats.count_flagged(status);
            for c in 0..3 {
                d_out[c].write(0.0);
                g_out[c].write(0.0);
            }
            continue;
        }
        let stripe = params.stripe_px as f32;
        // Position of the pixel in the pattern (projector px, modulo one): see `blurred_contrast`.
        let position = stripe / 2.0 - band.im[p].atan2(band.re[p]) / shifts.omega;
        let contrast = shifts
            .contrast
            .as_ref()
            .map_or(1.0, |table| table.at(position.rem_euclid(1.0)));
        for c in 0..3 {
            let mean = band.sum[o + c] / shifts.phasors.len() as f32;
            // The mean over all shifts is (1 + b)/2 of the white image whatever the blur.
            let total = 2.0 * mean / (1.0 + b);
            let d = ((lmax[c] - lmin[c]) / ((1.0 - b) * contrast)).min(total);
            let (d, g, clamped) = if d >= 0.0 && total >= d {
                (d, total - d, false)
            } else {
                (d.clamp(0.0, total.max(0.0)), (total - d).max(0.0), true)
            };
            d_out[c].write(d);
            g_out[c].write(g);
            stats.clamped_negative += clamped as u64;
        }
    }
    stats
}

/// Contrast `max - min` over the integer shifts of a square wave (`stripe` px on, `stripe` px
/// off) blurred by a Gaussian of sigma `blur` px, for a pixel at sub-pixel position `frac` in
/// [0, 1) of the pattern. 1 for a sharp pattern; e.g. 0.93 at the worst phase for sigma 0.7 px
/// and 3-px stripes.
pub fn blurred_contrast(frac: f32, stripe: f32, blur: f32) -> f32 {
    let (mut max, mut min) = (f32::MIN, f32::MAX);
    for k in 0..(2 * stripe as u32) {
        let v = blurred_square_wave(frac + k as f32, stripe, blur);
        max = max.max(v);
        min = min.min(v);
    }
    // Never divide by less than a tenth: a washed-out pixel is reported low, not amplified noise.
    (max - min).max(0.1)
}

/// The lit fraction at position `y` (projector px) of a square wave `stripe` px on from 0, `stripe`
/// px off, blurred by a Gaussian of sigma `blur` px.
pub(crate) fn blurred_square_wave(y: f32, stripe: f32, blur: f32) -> f32 {
    let period = 2.0 * stripe;
    let y = y.rem_euclid(period);
    if blur <= 0.0 {
        return if y < stripe { 1.0 } else { 0.0 };
    }
    (-2..=2)
        .map(|m| {
            let start = m as f32 * period;
            normal_cdf((y - start) / blur) - normal_cdf((y - start - stripe) / blur)
        })
        .sum()
}

/// Standard normal CDF (Abramowitz & Stegun 7.1.26, absolute error below 1.5e-7).
fn normal_cdf(z: f32) -> f32 {
    let x = (z as f64).abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erf = 1.0 - poly * (-x * x).exp();
    let half = 0.5 * (1.0 + erf);
    (if z >= 0.0 { half } else { 1.0 - half }) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_1d};

    /// A 1-D booth: camera pixels looking at a row of projector pixels through a footprint of
    /// `footprint` projector px starting at `phase`, with Gaussian projector defocus `defocus`
    /// (px) and a Gaussian global kernel of sigma `kernel` (px). Returns, per camera pixel, the
    /// samples under the 6 stripe shifts and the true (direct, global) under white.
    struct Row {
        black: f64,
        footprint: f64,
        phase: f64,
        defocus: f64,
        kernel: f64,
    }

    /// Circular blur (the row is one period), truncated at 4 sigma.
    fn gauss_blur(signal: &[f64], sigma: f64) -> Vec<f64> {
        let kernel = GaussianKernel::new(sigma, 4.0, Normalisation::Outputs);
        blur_1d(signal, &kernel, Border::Wrap)
    }

    fn v_len(n: usize) -> usize {
        n
    }

    impl Row {
        /// Samples on a fine grid (10 sub-samples per projector pixel) over a periodic row.
        fn simulate(&self, ld: f64, lg: f64, camera_pixels: usize) -> (Vec<[f32; 6]>, f64, f64) {
            const SUB: usize = 10;
            // One period of the pattern, wrapped: every convolution below is circular.
            let proj_px = 6usize;
            let mut out = vec![[0f32; 6]; camera_pixels];
            for shift in 0..6 {
                let emission: Vec<f64> = (0..proj_px * SUB)
                    .map(|i| {
                        let u = (i / SUB) as i64;
                        let lit = (u - shift).rem_euclid(6) < 3;
                        if lit { 1.0 } else { self.black }
                    })
                    .collect();
                let focused = gauss_blur(&emission, self.defocus * SUB as f64);
                let scattered = gauss_blur(&focused, self.kernel * SUB as f64);
                for (k, o) in out.iter_mut().enumerate() {
                    let start = ((self.phase + k as f64 * self.footprint) * SUB as f64) as usize;
                    let len = ((self.footprint * SUB as f64).round() as usize).max(1);
                    let n = v_len(proj_px * SUB);
                    let avg = |v: &[f64]| {
                        (start..start + len).map(|i| v[i % n]).sum::<f64>() / len as f64
                    };
                    o[shift as usize] = (ld * avg(&focused) + lg * avg(&scattered)) as f32;
                }
            }
            (out, ld, lg)
        }

        /// Worst relative errors with the blur-aware separation told the true blur.
        fn worst_errors_corrected(&self, ld: f64, lg: f64) -> (f64, f64) {
            let (samples, ld, lg) = self.simulate(ld, lg, 13);
            let frames = images(&samples);
            let refs: Vec<&Rgb32FImage> = frames.iter().collect();
            // The camera footprint (a box) adds footprint^2 / 12 to the blur variance.
            let blur = (self.defocus.powi(2) + self.footprint.powi(2) / 12.0).sqrt() as f32;
            let params = SeparationParams {
                black_level: self.black as f32,
                blur_px: blur,
                ..Default::default()
            };
            let sep = separate(&refs, &params).unwrap();
            let mut worst = (0.0f64, 0.0f64);
            for x in 0..samples.len() as u32 {
                let d = sep.direct.get_pixel(x, 0).0[0] as f64;
                let g = sep.global.get_pixel(x, 0).0[0] as f64;
                worst.0 = worst.0.max(((d - ld) / ld).abs());
                worst.1 = worst.1.max(((g - lg) / lg).abs());
            }
            worst
        }

        /// Worst relative errors of direct and global over the camera pixels.
        fn worst_errors(&self, ld: f64, lg: f64) -> (f64, f64) {
            let (samples, ld, lg) = self.simulate(ld, lg, 13);
            let mut worst = (0.0f64, 0.0f64);
            for s in samples {
                let max = s.iter().cloned().fold(f32::MIN, f32::max);
                let min = s.iter().cloned().fold(f32::MAX, f32::min);
                let (d, g, _) = separate_sample(max, min, self.black as f32);
                worst.0 = worst.0.max(((d as f64 - ld) / ld).abs());
                worst.1 = worst.1.max(((g as f64 - lg) / lg).abs());
            }
            worst
        }
    }

    fn row() -> Row {
        Row {
            black: 0.02,
            footprint: 0.5,
            phase: 0.0,
            defocus: 0.0,
            kernel: 30.0,
        }
    }

    #[test]
    fn black_level_formula_recovers_direct_and_global_exactly() {
        // Hand-derived: Ld = 0.3, Lg = 0.2, b = 0.05.
        let (ld, lg, b) = (0.3f32, 0.2f32, 0.05f32);
        let lmax = ld + (1.0 + b) / 2.0 * lg;
        let lmin = b * ld + (1.0 + b) / 2.0 * lg;
        let (d, g, clamped) = separate_sample(lmax, lmin, b);
        assert!((d - ld).abs() < 1e-6 && (g - lg).abs() < 1e-6 && !clamped);
        // Ignoring the black level would be wrong by more than 5%.
        let (d0, g0, _) = separate_sample(lmax, lmin, 0.0);
        assert!((d0 - ld).abs() / ld > 0.04 && (g0 - lg).abs() / lg > 0.05);
    }

    #[test]
    fn wide_kernel_and_any_footprint_up_to_two_pixels_is_exact() {
        for footprint in [0.4, 1.0, 1.9] {
            for phase in [0.0, 0.3, 0.5, 0.77] {
                let r = Row {
                    footprint,
                    phase,
                    ..row()
                };
                let (ed, eg) = r.worst_errors(0.3, 0.2);
                // The global kernel (sigma 30 px) still has a residual ripple of ~1e-3.
                assert!(
                    ed < 0.01 && eg < 0.01,
                    "footprint {footprint} phase {phase}: {ed} {eg}"
                );
            }
        }
    }

    #[test]
    fn footprint_wider_than_two_pixels_loses_contrast() {
        let r = Row {
            footprint: 2.6,
            phase: 0.5,
            ..row()
        };
        let (ed, _) = r.worst_errors(0.3, 0.2);
        assert!(
            ed > 0.1,
            "a 2.6-px footprint should underestimate direct, error {ed}"
        );
    }

    #[test]
    fn defocus_loses_contrast_and_the_blur_correction_restores_it() {
        // The booth's projectors defocus by 0.5-0.7 px: plain Nayar loses over 5% of direct at the
        // worst stripe phase, 60% at 1.5 px.
        let (ed, _) = Row {
            defocus: 0.7,
            ..row()
        }
        .worst_errors(0.3, 0.2);
        assert!(ed > 0.05, "defocus 0.7 uncorrected: {ed}");
        let (ed, _) = Row {
            defocus: 1.5,
            ..row()
        }
        .worst_errors(0.3, 0.2);
        assert!(ed > 0.5, "defocus 1.5 uncorrected: {ed}");
        for defocus in [0.5, 0.7, 1.0, 1.5] {
            let (cd, cg) = Row { defocus, ..row() }.worst_errors_corrected(0.3, 0.2);
            assert!(
                cd < 0.005 && cg < 0.005,
                "defocus {defocus} corrected: {cd} {cg}"
            );
        }
    }

    #[test]
    fn global_kernel_narrower_than_the_period_leaks_into_direct() {
        // Gaussian scattering kernel of sigma 3 px (half the 6-px period): still within 1%.
        let (cd, cg) = Row {
            kernel: 3.0,
            defocus: 0.6,
            ..row()
        }
        .worst_errors_corrected(0.3, 0.2);
        assert!(cd < 0.01 && cg < 0.01, "sigma 3 px: {cd} {cg}");
        // Sigma 2 px: about 8% of direct is leaked global light; sigma 1 px: about 40%. Neither
        // the formula nor the blur correction can tell such light from direct light.
        let (cd, cg) = Row {
            kernel: 2.0,
            defocus: 0.6,
            ..row()
        }
        .worst_errors_corrected(0.3, 0.2);
        assert!(cd > 0.05 && cg > 0.07, "sigma 2 px: {cd} {cg}");
        let (ed, eg) = Row {
            kernel: 1.0,
            ..row()
        }
        .worst_errors(0.3, 0.2);
        assert!(ed > 0.3 && eg > 0.4, "sigma 1 px: direct {ed} global {eg}");
    }

    #[test]
    fn contrast_table_follows_the_exact_contrast() {
        for (stripe, blur) in [(3.0, 0.3), (3.0, 0.7), (2.0, 1.5), (4.0, 0.05)] {
            let table = ContrastTable::new(stripe, blur);
            let worst = (0..=10_000)
                .map(|i| i as f32 / 10_000.0)
                .map(|f| (table.at(f) - blurred_contrast(f, stripe, blur)).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 2e-4, "stripe {stripe} blur {blur}: {worst}");
        }
    }

    #[test]
    fn blurred_contrast_matches_hand_values() {
        // Sharp pattern: full contrast at any phase.
        assert!((blurred_contrast(0.37, 3.0, 0.0) - 1.0).abs() < 1e-6);
        // Sigma 1 px, pixel centred on a stripe: 2 * (Phi(1.5) - Phi(-1.5)) - 1 (up to the
        // neighbouring stripes' tails, < 1e-3).
        let expected = 2.0 * (0.933_193 - 0.066_807) - 1.0;
        assert!((blurred_contrast(0.5, 3.0, 1.0) - expected).abs() < 2e-3);
    }

    fn images(samples: &[[f32; 6]]) -> Vec<Rgb32FImage> {
        (0..6)
            .map(|s| {
                Rgb32FImage::from_fn(samples.len() as u32, 1, |x, _| {
                    let v = samples[x as usize][s];
                    image::Rgb([v, v * 0.5, v * 0.25])
                })
            })
            .collect()
    }

    #[test]
    fn saturated_and_non_finite_pixels_are_flagged_and_zero() {
        let mut samples = vec![[0.5, 0.5, 0.5, 0.1, 0.1, 0.1]; 4];
        samples[1][0] = 1.0;
        samples[2][3] = f32::NAN;
        samples[3] = [0.1, 0.1, 0.1, 0.12, 0.12, 0.12]; // min - b max < 0 never; max-min tiny
        let frames = images(&samples);
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let sep = separate(
            &refs,
            &SeparationParams {
                black_level: 0.02,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(sep.flags[0], SeparationFlag::Ok);
        assert_eq!(sep.flags[1], SeparationFlag::Saturated);
        assert_eq!(sep.flags[2], SeparationFlag::NonFinite);
        assert_eq!(sep.direct.get_pixel(1, 0).0, [0.0; 3]);
        assert_eq!(sep.global.get_pixel(2, 0).0, [0.0; 3]);
        assert_eq!(sep.stats.saturated_pixels, 1);
        assert_eq!(sep.stats.non_finite_pixels, 1);
        let d = sep.direct.get_pixel(0, 0).0;
        assert!((d[0] - 0.4 / 0.98).abs() < 1e-6 && (d[1] - 0.2 / 0.98).abs() < 1e-6);
        for v in sep.direct.as_raw().iter().chain(sep.global.as_raw()) {
            assert!(v.is_finite() && *v >= 0.0);
        }
    }

    #[test]
    fn every_pixel_of_a_multi_band_image_follows_the_max_min_formula() {
        // 37 x 23 px (several row bands, a width that no band size divides), 6 shifts of
        // pseudo-random values, one saturated and one non-finite pixel: each output is Nayar's
        // formula on that pixel's own max and min, computed here pixel by pixel.
        let (w, h, shifts) = (37u32, 23u32, 6usize);
        let value = |s: usize, i: usize| ((i * 7919 + s * 104_729) % 1000) as f32 / 1100.0;
        let mut frames: Vec<Rgb32FImage> = (0..shifts)
            .map(|s| {
                let data = (0..(w * h * 3) as usize).map(|i| value(s, i)).collect();
                Rgb32FImage::from_raw(w, h, data).unwrap()
            })
            .collect();
        frames[2].get_pixel_mut(5, 9).0[1] = 1.0;
        frames[4].get_pixel_mut(30, 17).0[2] = f32::INFINITY;
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let params = SeparationParams {
            black_level: 0.03,
            ..Default::default()
        };
        let sep = separate(&refs, &params).unwrap();
        for y in 0..h {
            for x in 0..w {
                let flag = sep.flags[(y * w + x) as usize];
                if (x, y) == (5, 9) || (x, y) == (30, 17) {
                    assert_ne!(flag, SeparationFlag::Ok, "pixel {x},{y}");
                    assert_eq!(sep.direct.get_pixel(x, y).0, [0.0; 3]);
                    continue;
                }
                assert_eq!(flag, SeparationFlag::Ok, "pixel {x},{y}");
                for c in 0..3 {
                    let samples = frames.iter().map(|f| f.get_pixel(x, y).0[c]);
                    let max = samples.clone().fold(f32::MIN, f32::max);
                    let min = samples.fold(f32::MAX, f32::min);
                    let (d, g, _) = separate_sample(max, min, 0.03);
                    assert_eq!(sep.direct.get_pixel(x, y).0[c], d, "pixel {x},{y}");
                    assert_eq!(sep.global.get_pixel(x, y).0[c], g, "pixel {x},{y}");
                }
            }
        }
        assert_eq!(sep.flags[(9 * w + 5) as usize], SeparationFlag::Saturated);
        assert_eq!(sep.flags[(17 * w + 30) as usize], SeparationFlag::NonFinite);
    }

    /// The AVX2 build of the sharp chunk kernel writes the portable one's outputs, flags and
    /// counts, bit for bit, for six shifts and for five (skipped where the CPU has no AVX2).
    #[test]
    fn avx2_chunk_kernel_equals_the_portable_one() {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            use rand::{Rng, SeedableRng};
            let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
            let pixels = CHUNK_PIXELS - 5;
            for shifts in [6, 5] {
                let frames: Vec<Vec<f32>> = (0..shifts)
                    .map(|_| {
                        (0..pixels * 3)
                            .map(|_| match rng.gen_range(0..300) {
                                0 => f32::NAN,
                                1 => f32::NEG_INFINITY,
                                2 => 1.0,
                                _ => rng.gen_range(-0.01..0.99f32),
                            })
                            .collect()
                    })
                    .collect();
                let raws: Vec<&[f32]> = frames.iter().map(|f| f.as_slice()).collect();
                let params = SeparationParams {
                    black_level: 0.04,
                    ..Default::default()
                };
                let run = |avx2: bool| {
                    let mut d = vec![MaybeUninit::new(0.0f32); pixels * 3];
                    let mut g = vec![MaybeUninit::new(0.0f32); pixels * 3];
                    let mut f = vec![MaybeUninit::new(SeparationFlag::Ok); pixels];
                    let stats = if avx2 {
                        // SAFETY: AVX2 was detected above.
                        unsafe {
                            separate_chunk_sharp_avx2(&raws, 0, &params, &mut d, &mut g, &mut f)
                        }
                    } else {
                        separate_chunk_sharp(&raws, 0, &params, &mut d, &mut g, &mut f)
                    };
                    // SAFETY: initialised above (and overwritten by the kernel).
                    let bits = |v: &[MaybeUninit<f32>]| {
                        v.iter()
                            .map(|x| unsafe { x.assume_init() }.to_bits())
                            .collect::<Vec<_>>()
                    };
                    let flags: Vec<SeparationFlag> =
                        f.iter().map(|x| unsafe { x.assume_init() }).collect();
                    (bits(&d), bits(&g), flags, stats)
                };
                assert_eq!(run(true), run(false));
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(24))]

        /// Images of up to three chunks, with saturated, NaN and infinite samples scattered in:
        /// every pixel's flag and outputs are those of the pixel-by-pixel formula (the fused
        /// chunk kernel writes every value once, flagged pixels included), and the counters
        /// count them.
        #[test]
        fn fused_separation_equals_the_per_pixel_formula(
            seed in 0u64..1_000_000,
            w in 1u32..90,
            h in 1u32..70,
            shifts in 2usize..8,
            black_level in 0.0f32..0.1,
        ) {
            use rand::{Rng, SeedableRng};
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let frames: Vec<Rgb32FImage> = (0..shifts)
                .map(|_| {
                    let data = (0..(w * h * 3) as usize)
                        .map(|_| match rng.gen_range(0..400) {
                            0 => f32::NAN,
                            1 => f32::INFINITY,
                            2 => 1.0,
                            _ => rng.gen_range(0.0..0.99f32),
                        })
                        .collect();
                    Rgb32FImage::from_raw(w, h, data).unwrap()
                })
                .collect();
            let refs: Vec<&Rgb32FImage> = frames.iter().collect();
            let params = SeparationParams { black_level, ..Default::default() };
            let sep = separate(&refs, &params).unwrap();
            let mut expected = SeparationStats { pixels: u64::from(w * h), ..Default::default() };
            for i in 0..(w * h) as usize {
                let samples = |c: usize| frames.iter().map(move |f| f.as_raw()[i * 3 + c]);
                let finite = (0..3).all(|c| samples(c).all(f32::is_finite));
                let max = |c: usize| samples(c).fold(f32::NEG_INFINITY, f32::max);
                let min = |c: usize| samples(c).fold(f32::INFINITY, f32::min);
                let flag = if !finite {
                    expected.non_finite_pixels += 1;
                    SeparationFlag::NonFinite
                } else if (0..3).any(|c| max(c) >= params.saturation) {
                    expected.saturated_pixels += 1;
                    SeparationFlag::Saturated
                } else {
                    SeparationFlag::Ok
                };
                proptest::prop_assert_eq!(sep.flags[i], flag);
                for c in 0..3 {
                    let (d, g) = if flag == SeparationFlag::Ok {
                        let (d, g, clamped) = separate_sample(max(c), min(c), black_level);
                        expected.clamped_negative += u64::from(clamped);
                        (d, g)
                    } else {
                        (0.0, 0.0)
                    };
                    proptest::prop_assert_eq!(sep.direct.as_raw()[i * 3 + c].to_bits(), d.to_bits());
                    proptest::prop_assert_eq!(sep.global.as_raw()[i * 3 + c].to_bits(), g.to_bits());
                }
            }
            proptest::prop_assert_eq!(sep.stats, expected);
        }
    }

    #[test]
    fn negative_global_from_noise_is_clamped_and_counted() {
        // A purely direct pixel whose dark samples read below b * max through noise.
        let (d, g, clamped) = separate_sample(0.5, 0.005, 0.02);
        assert!(clamped && g == 0.0);
        assert!((d - (0.495 / 0.98 + 2.0 * (0.005 - 0.01) / (1.0 - 0.0004))).abs() < 1e-6);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let a = Rgb32FImage::new(4, 3);
        let b = Rgb32FImage::new(3, 4);
        assert!(matches!(
            separate(&[&a], &SeparationParams::default()),
            Err(SeparationError::TooFewFrames(1))
        ));
        assert!(matches!(
            separate(&[&a, &b], &SeparationParams::default()),
            Err(SeparationError::SizeMismatch { index: 1, .. })
        ));
        assert!(matches!(
            separate(
                &[&a, &a],
                &SeparationParams {
                    black_level: 1.0,
                    ..Default::default()
                }
            ),
            Err(SeparationError::BadBlackLevel(_))
        ));
    }
}

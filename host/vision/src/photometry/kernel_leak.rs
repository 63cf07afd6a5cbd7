//! Direct/global separation that knows the global light has a finite kernel (ours, DESIGN
//! section 4 stage 4).
//!
//! Nayar et al. assume the global light does not follow the stripes. In skin at the booth's scale
//! it does: a pixel's subsurface light comes from a kernel only a few projector pixels wide, so
//! the stripes reach the camera with a contrast of their own, and `Lmax - Lmin` holds that part of
//! the global light as well as the direct light. This module removes it when the kernel's
//! transfer at the stripe frequency (the *leak* `lambda`, 0 for a kernel much wider than the
//! stripe period, 1 for one much narrower than a projector pixel) is known per pixel and channel.
//!
//! Model, per pixel and channel, for the `2 stripe` shifts `s` of a square wave: with `P_s` the
//! emitted pattern (level `b + (1 - b) square`), `B` the projector defocus and camera footprint,
//! `K` the normalised subsurface kernel along the stripes' axis,
//! `I_s = Ld (B * P_s)(u0) + Lg (K * B * P_s)(u0)`.
//! Take the first DFT coefficient over the shifts, `F = sum_s I_s exp(-i 2 pi s / (2 stripe))`:
//! the black level drops out, and for a symmetric kernel whose transfer beyond the first harmonic
//! is negligible next to the blur's, `|F| = (1 - b) h1 (Ld + lambda Lg)`, where `h1` is the
//! first-harmonic magnitude of the blurred pattern at the pixel's phase (read from the phase of
//! `F`, as the blur correction of [`super::separation`] does). With the total
//! `T = Ld + Lg = 2 mean_s(I_s) / (1 + b)`:
//!
//! `Ld = (|F| / ((1 - b) h1) - lambda T) / (1 - lambda)`, `Lg = T - Ld`.
//!
//! Why the first harmonic rather than `max - min`: it uses all shifts (half the noise of the
//! extremes and no upward bias of a maximum), and the kernel's effect on it is one number.
//!
//! Limits (tests below): exact for analytic kernels (Gaussian, exponential) up to the aliased
//! harmonics (< 0.5 % of the direct part with the booth's blur); a kernel whose leak approaches 1
//! is indistinguishable from direct light at this stripe period, so pixels with
//! `lambda >= max_leak` are flagged [`LeakFlag::NarrowKernel`] and get all their light as global.
//! An asymmetric kernel (forward scattering) turns the global phasor against the direct one;
//! the magnitude then undercounts the leak slightly (not corrected).

use image::Rgb32FImage;
use rayon::prelude::*;

use super::separation::{SeparationError, blurred_square_wave};

/// Leak of a 1-D Gaussian kernel of sigma `sigma_px` for square-wave stripes `stripe_px` wide:
/// its transfer `exp(-2 pi^2 sigma^2 f^2)` at the stripe frequency `f = 1 / (2 stripe)`.
pub fn gaussian_leak(sigma_px: f64, stripe_px: f64) -> f64 {
    let f = 1.0 / (2.0 * stripe_px);
    (-2.0 * (std::f64::consts::PI * sigma_px * f).powi(2)).exp()
}

/// Leak of a 1-D exponential kernel `exp(-|d| / length) / (2 length)` (the profile of a
/// diffusion-like kernel away from its centre): `1 / (1 + (2 pi length f)^2)`.
pub fn exponential_leak(length_px: f64, stripe_px: f64) -> f64 {
    let f = 1.0 / (2.0 * stripe_px);
    1.0 / (1.0 + (std::f64::consts::TAU * length_px * f).powi(2))
}

/// Parameters of the kernel-aware separation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LeakParams {
    /// Projector black level b (fraction of white).
    pub black_level: f32,
    /// A sample at or above this linear value is saturated.
    pub saturation: f32,
    /// Stripe blur seen by a camera pixel (defocus and footprint), Gaussian sigma, projector px.
    pub blur_px: f32,
    /// Stripe width in projector px; the frames are its `2 stripe_px` shifts.
    pub stripe_px: u32,
    /// Leaks at or above this are flagged [`LeakFlag::NarrowKernel`] (direct 0, all light global):
    /// dividing by `1 - lambda` would amplify noise without bound.
    pub max_leak: f32,
}

impl Default for LeakParams {
    fn default() -> Self {
        Self {
            black_level: 0.0,
            saturation: 1.0 - 1.0 / 4095.0,
            blur_px: 0.0,
            stripe_px: 3,
            max_leak: 0.95,
        }
    }
}

/// Why a pixel was not separated normally.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[repr(u8)]
pub enum LeakFlag {
    Ok = 0,
    /// A sample was saturated; outputs are zero.
    Saturated = 1,
    /// A sample or the leak was not finite; outputs are zero.
    NonFinite = 2,
    /// The kernel is too narrow for the stripes in some channel (leak >= `max_leak`): that
    /// channel's light is all reported as global.
    NarrowKernel = 3,
}

/// Counters of the kernel-aware separation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LeakStats {
    pub pixels: u64,
    pub saturated_pixels: u64,
    pub non_finite_pixels: u64,
    pub narrow_kernel_pixels: u64,
    /// Channel values whose direct part was clamped into `[0, total]`.
    pub clamped: u64,
}

/// Direct and global images with per-pixel flags.
#[derive(Debug, Clone)]
pub struct LeakSeparation {
    pub direct: Rgb32FImage,
    pub global: Rgb32FImage,
    pub flags: Vec<LeakFlag>,
    pub stats: LeakStats,
}

/// Separates the shifted stripe frames of one projector, removing from the stripe contrast the
/// part the global light keeps: `leak[i]` is pixel `i`'s kernel transfer at the stripe frequency
/// per channel (row-major; all zeros gives a first-harmonic Nayar separation).
pub fn separate_with_leak(
    frames: &[&Rgb32FImage],
    leak: &[[f32; 3]],
    params: &LeakParams,
) -> Result<LeakSeparation, SeparationError> {
    let (w, h) = check_frames(frames, params)?;
    let n = w as usize * h as usize;
    if leak.len() != n {
        return Err(SeparationError::LeakSize {
            expected: n,
            got: leak.len(),
        });
    }
    let harmonic = HarmonicTable::new(frames.len(), params.stripe_px as f32, params.blur_px);
    Ok(split_pixels(frames, (w, h), |raws, i| {
        separate_pixel(raws, i, leak[i], params, &harmonic)
    }))
}

/// The stripes' totals alone: each pixel's total `2 mean / (1 + b)` per channel as its global
/// part, direct 0, flagged as [`separate_with_leak`] flags it with a zero leak (saturated,
/// non-finite; never a narrow kernel). What a direct part read from elsewhere needs (the
/// separate stage's specular lobe replaces every direct part the stripes' harmonics give), at a
/// fraction of the split's cost: no harmonics, phase or magnitudes (full-size booth, four
/// projectors: 0.17 CPU-s against 0.67).
pub fn stripe_totals(
    frames: &[&Rgb32FImage],
    params: &LeakParams,
) -> Result<LeakSeparation, SeparationError> {
    let size = check_frames(frames, params)?;
    Ok(split_pixels(frames, size, |raws, i| {
        let mut out = PixelOut {
            direct: [0.0; 3],
            global: [0.0; 3],
            flag: LeakFlag::Ok,
            clamped: 0,
        };
        match pixel_mean(raws, i, params) {
            Ok(mean) => {
                let b = params.black_level;
                out.global = mean.map(|m| (2.0 * m / (1.0 + b)).max(0.0));
            }
            Err(flag) => out.flag = flag,
        }
        out
    }))
}

/// Runs `per_pixel` (frames' raw RGB values, pixel index) over every pixel of the `size`
/// frames, in parallel bands of rows, and gathers the images, flags and counters.
fn split_pixels(
    frames: &[&Rgb32FImage],
    (w, h): (u32, u32),
    per_pixel: impl Fn(&[&[f32]], usize) -> PixelOut + Sync,
) -> LeakSeparation {
    let n = w as usize * h as usize;
    let raws: Vec<&[f32]> = frames.iter().map(|f| f.as_raw().as_slice()).collect();
    let mut direct = vec![0.0f32; n * 3];
    let mut global = vec![0.0f32; n * 3];
    let mut flags = vec![LeakFlag::Ok; n];
    let chunk = 16 * w as usize;
    let partial: Vec<LeakStats> = direct
        .par_chunks_mut(chunk * 3)
        .zip(global.par_chunks_mut(chunk * 3))
        .zip(flags.par_chunks_mut(chunk))
        .enumerate()
        .map(|(ci, ((d, g), fl))| {
            let mut stats = LeakStats::default();
            for (p, flag) in fl.iter_mut().enumerate() {
                let out = per_pixel(&raws, ci * chunk + p);
                *flag = out.flag;
                d[p * 3..p * 3 + 3].copy_from_slice(&out.direct);
                g[p * 3..p * 3 + 3].copy_from_slice(&out.global);
                stats.add_pixel(&out);
            }
            stats
        })
        .collect();
    let mut stats = LeakStats {
        pixels: n as u64,
        ..Default::default()
    };
    for s in partial {
        stats.saturated_pixels += s.saturated_pixels;
        stats.non_finite_pixels += s.non_finite_pixels;
        stats.narrow_kernel_pixels += s.narrow_kernel_pixels;
        stats.clamped += s.clamped;
    }
    let to_image =
        |v: Vec<f32>| Rgb32FImage::from_raw(w, h, v).unwrap_or_else(|| Rgb32FImage::new(w, h));
    LeakSeparation {
        direct: to_image(direct),
        global: to_image(global),
        flags,
        stats,
    }
}

/// Makes the direct part colourless and smooth, keeping each pixel's total: the direct part
/// becomes the mean over channels, averaged over separated neighbours with a Gaussian of
/// `sigma_px` camera px (0: no averaging), at most each channel's total. Why: skin's surface
/// reflection is a dielectric's, colourless under white light and smooth where the surface is,
/// while the per-pixel estimate carries the noise of the stripe frames several times over
/// (`1 / (1 - lambda)`); the averaging trades that noise for blur at highlight edges.
pub fn colourless_smoothed_direct(sep: &mut LeakSeparation, sigma_px: f64) {
    use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d};
    let (w, h) = sep.direct.dimensions();
    let (w, h) = (w as usize, h as usize);
    let ok: Vec<bool> = sep.flags.iter().map(|f| *f == LeakFlag::Ok).collect();
    let mut grey: Vec<f32> = sep
        .direct
        .pixels()
        .zip(&ok)
        .map(|(p, &ok)| {
            if ok {
                p.0.iter().sum::<f32>() / 3.0
            } else {
                0.0
            }
        })
        .collect();
    let mut weight: Vec<f32> = ok.iter().map(|&ok| f32::from(u8::from(ok))).collect();
    if sigma_px > 0.0 {
        let kernel = GaussianKernel::new(sigma_px as f32, 3.0, Normalisation::Outputs);
        // Both have the image's size, so the blur cannot fail; keep the unsmoothed values if
        // it ever did.
        let smoothed = blur_2d(&mut grey, w, h, &kernel, Border::Clamp)
            .and_then(|()| blur_2d(&mut weight, w, h, &kernel, Border::Clamp));
        if smoothed.is_err() {
            return;
        }
    }
    let direct = sep.direct.as_mut();
    let global = sep.global.as_mut();
    for (i, &ok) in ok.iter().enumerate() {
        if !ok {
            continue;
        }
        let d = if weight[i] > 1e-6 {
            grey[i] / weight[i]
        } else {
            0.0
        };
        for c in 0..3 {
            let total = direct[i * 3 + c] + global[i * 3 + c];
            let kept = d.clamp(0.0, total.max(0.0));
            direct[i * 3 + c] = kept;
            global[i * 3 + c] = total - kept;
        }
    }
}

/// The frames' common size, after checking their number and the parameters.
fn check_frames(
    frames: &[&Rgb32FImage],
    params: &LeakParams,
) -> Result<(u32, u32), SeparationError> {
    let shifts = 2 * params.stripe_px as usize;
    if frames.len() < 2 {
        return Err(SeparationError::TooFewFrames(frames.len()));
    }
    if frames.len() != shifts {
        return Err(SeparationError::ShiftCount {
            expected: shifts,
            got: frames.len(),
        });
    }
    let b = params.black_level;
    if !(0.0..1.0).contains(&b) {
        return Err(SeparationError::BadBlackLevel(b as f64));
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
    Ok((w, h))
}

/// First-harmonic magnitude `h1` of the blurred stripe pattern sampled at the shifts, against the
/// pixel's phase in the pattern, tabulated (as `separation::ContrastTable`, same reason).
struct HarmonicTable {
    phasors: Vec<(f32, f32)>,
    omega: f32,
    stripe: f32,
    values: Vec<f32>,
}

impl HarmonicTable {
    const CELLS: usize = 1024;

    fn new(shifts: usize, stripe: f32, blur: f32) -> Self {
        let omega = std::f32::consts::TAU / shifts as f32;
        let phasors: Vec<(f32, f32)> = (0..shifts)
            .map(|s| ((omega * s as f32).cos(), (omega * s as f32).sin()))
            .collect();
        let values = (0..=Self::CELLS)
            .map(|i| {
                let frac = i as f32 / Self::CELLS as f32;
                let (re, im) = phasors.iter().enumerate().fold(
                    (0.0f32, 0.0f32),
                    |(re, im), (s, &(cos, sin))| {
                        let v = blurred_square_wave(frac + s as f32, stripe, blur);
                        (re + v * cos, im - v * sin)
                    },
                );
                phasor_magnitude(re, im)
            })
            .collect();
        Self {
            phasors,
            omega,
            stripe,
            values,
        }
    }

    /// `h1` for a pixel whose first DFT coefficient is `(re, im)`.
    fn at(&self, re: f32, im: f32) -> f32 {
        let position = (self.stripe / 2.0 - im.atan2(re) / self.omega).rem_euclid(1.0);
        let x = position * Self::CELLS as f32;
        let i = (x as usize).min(Self::CELLS - 1);
        let t = x - i as f32;
        self.values[i] + t * (self.values[i + 1] - self.values[i])
    }
}

/// One pixel's outcome.
struct PixelOut {
    direct: [f32; 3],
    global: [f32; 3],
    flag: LeakFlag,
    clamped: u64,
}

impl LeakStats {
    fn add_pixel(&mut self, out: &PixelOut) {
        match out.flag {
            LeakFlag::Ok => {}
            LeakFlag::Saturated => self.saturated_pixels += 1,
            LeakFlag::NonFinite => self.non_finite_pixels += 1,
            LeakFlag::NarrowKernel => self.narrow_kernel_pixels += 1,
        }
        self.clamped += out.clamped;
    }
}

/// First DFT coefficient and mean over the shifts, per channel and for the channel sum (the
/// phase reference), or the flag that stops the pixel.
struct PixelHarmonics {
    re: [f32; 3],
    im: [f32; 3],
    mean: [f32; 3],
    grey: (f32, f32),
}

fn pixel_harmonics(
    raws: &[&[f32]],
    i: usize,
    params: &LeakParams,
    table: &HarmonicTable,
) -> Result<PixelHarmonics, LeakFlag> {
    let mut h = PixelHarmonics {
        re: [0.0; 3],
        im: [0.0; 3],
        mean: [0.0; 3],
        grey: (0.0, 0.0),
    };
    let mut saturated = false;
    for (raw, &(cos, sin)) in raws.iter().zip(&table.phasors) {
        for c in 0..3 {
            let v = raw[i * 3 + c];
            if !v.is_finite() {
                return Err(LeakFlag::NonFinite);
            }
            saturated |= v >= params.saturation;
            h.re[c] += v * cos;
            h.im[c] -= v * sin;
            h.mean[c] += v / raws.len() as f32;
            h.grey.0 += v * cos;
            h.grey.1 -= v * sin;
        }
    }
    if saturated {
        return Err(LeakFlag::Saturated);
    }
    Ok(h)
}

/// The mean over the shifts per channel (summed as [`pixel_harmonics`] sums it), or the flag
/// that stops the pixel.
fn pixel_mean(raws: &[&[f32]], i: usize, params: &LeakParams) -> Result<[f32; 3], LeakFlag> {
    let mut mean = [0.0f32; 3];
    let mut saturated = false;
    for raw in raws {
        for (c, m) in mean.iter_mut().enumerate() {
            let v = raw[i * 3 + c];
            if !v.is_finite() {
                return Err(LeakFlag::NonFinite);
            }
            saturated |= v >= params.saturation;
            *m += v / raws.len() as f32;
        }
    }
    if saturated {
        return Err(LeakFlag::Saturated);
    }
    Ok(mean)
}

fn separate_pixel(
    raws: &[&[f32]],
    i: usize,
    leak: [f32; 3],
    params: &LeakParams,
    table: &HarmonicTable,
) -> PixelOut {
    let zero = |flag| PixelOut {
        direct: [0.0; 3],
        global: [0.0; 3],
        flag,
        clamped: 0,
    };
    if leak.iter().any(|l| !l.is_finite()) {
        return zero(LeakFlag::NonFinite);
    }
    let h = match pixel_harmonics(raws, i, params, table) {
        Ok(h) => h,
        Err(flag) => return zero(flag),
    };
    let b = params.black_level;
    // Never divide by a vanishing pattern harmonic: a washed-out pixel reads low instead.
    let h1 = table.at(h.grey.0, h.grey.1).max(0.1);
    let mut out = zero(LeakFlag::Ok);
    for (c, &lambda) in leak.iter().enumerate() {
        let total = (2.0 * h.mean[c] / (1.0 + b)).max(0.0);
        let lambda = lambda.max(0.0);
        if lambda >= params.max_leak {
            out.flag = LeakFlag::NarrowKernel;
            out.global[c] = total;
            continue;
        }
        let contrast = phasor_magnitude(h.re[c], h.im[c]) / ((1.0 - b) * h1);
        let direct = (contrast - lambda * total) / (1.0 - lambda);
        let kept = direct.clamp(0.0, total);
        out.clamped += u64::from(kept != direct);
        out.direct[c] = kept;
        out.global[c] = total - kept;
    }
    out
}

/// `|re + i im|` through f64: the squares of f32 values can neither overflow nor underflow there,
/// so the careful scaling of `f32::hypot` (a libm call, the largest cost of the slit leak's reading
/// at full size when it was used there) buys nothing.
pub(crate) fn phasor_magnitude(re: f32, im: f32) -> f32 {
    (f64::from(re).powi(2) + f64::from(im).powi(2)).sqrt() as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photometry::separation::{SeparationParams, separate};
    use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_1d};

    /// Sub-samples per projector pixel of the 1-D booth below.
    const SUB: usize = 20;

    /// Global kernel of the analytic scenes.
    #[derive(Clone, Copy, Debug)]
    enum Kernel {
        Gaussian(f64),
        Exponential(f64),
    }

    impl Kernel {
        fn leak(self, stripe: f64) -> f64 {
            match self {
                Kernel::Gaussian(s) => gaussian_leak(s, stripe),
                Kernel::Exponential(l) => exponential_leak(l, stripe),
            }
        }

        /// Circular convolution of one period (`signal`, SUB samples per px) with the kernel.
        fn apply(self, signal: &[f64]) -> Vec<f64> {
            match self {
                Kernel::Gaussian(s) => gauss(signal, s),
                Kernel::Exponential(l) => {
                    let n = signal.len() as i64;
                    let len = l * SUB as f64;
                    // Wrap the kernel over enough periods that its tail is below 1e-9.
                    let reach = (len * 21.0) as i64;
                    let weights: Vec<f64> = (-reach..=reach)
                        .map(|d| (-(d as f64).abs() / len).exp())
                        .collect();
                    let norm: f64 = weights.iter().sum();
                    (0..n)
                        .map(|x| {
                            (-reach..=reach)
                                .zip(&weights)
                                .map(|(d, w)| w * signal[(x + d).rem_euclid(n) as usize])
                                .sum::<f64>()
                                / norm
                        })
                        .collect()
                }
            }
        }
    }

    fn gauss(signal: &[f64], sigma_px: f64) -> Vec<f64> {
        if sigma_px <= 0.0 {
            return signal.to_vec();
        }
        let kernel = GaussianKernel::new(sigma_px * SUB as f64, 5.0, Normalisation::Outputs);
        blur_1d(signal, &kernel, Border::Wrap)
    }

    /// A 1-D booth over one pattern period: camera pixels of `footprint` projector px at
    /// phases spread over the period, projector defocus `defocus`, black level `black`, and a
    /// global kernel. Returns the frames (one row, grey in R, scaled in G and B) and the truth.
    struct Scene {
        black: f64,
        defocus: f64,
        footprint: f64,
        kernel: Kernel,
        ld: f64,
        lg: f64,
    }

    impl Scene {
        fn frames(&self, pixels: usize) -> Vec<Rgb32FImage> {
            let stripe = 3usize;
            let n = 2 * stripe * SUB;
            (0..2 * stripe)
                .map(|shift| {
                    let emission: Vec<f64> = (0..n)
                        .map(|i| {
                            let u = (i / SUB) as i64;
                            let lit =
                                (u - shift as i64).rem_euclid(2 * stripe as i64) < stripe as i64;
                            if lit { 1.0 } else { self.black }
                        })
                        .collect();
                    let focused = gauss(&emission, self.defocus);
                    let scattered = self.kernel.apply(&focused);
                    let len = ((self.footprint * SUB as f64).round() as usize).max(1);
                    Rgb32FImage::from_fn(pixels as u32, 1, |x, _| {
                        let start = (x as usize * n) / pixels;
                        let avg = |v: &[f64]| {
                            (start..start + len).map(|i| v[i % n]).sum::<f64>() / len as f64
                        };
                        let v = (self.ld * avg(&focused) + self.lg * avg(&scattered)) as f32;
                        image::Rgb([v, 0.5 * v, 0.25 * v])
                    })
                })
                .collect()
        }

        fn blur(&self) -> f32 {
            (self.defocus.powi(2) + self.footprint.powi(2) / 12.0).sqrt() as f32
        }

        /// Worst relative errors of (direct, global) over the pixels, red channel.
        fn worst(&self, direct: &Rgb32FImage, global: &Rgb32FImage) -> (f64, f64) {
            direct
                .pixels()
                .zip(global.pixels())
                .map(|(d, g)| {
                    (
                        ((d.0[0] as f64 - self.ld) / self.ld).abs(),
                        ((g.0[0] as f64 - self.lg) / self.lg).abs(),
                    )
                })
                .fold((0.0, 0.0), |a, e| (a.0.max(e.0), a.1.max(e.1)))
        }

        fn kernel_aware(&self, leak: f64) -> (f64, f64) {
            let frames = self.frames(17);
            let refs: Vec<&Rgb32FImage> = frames.iter().collect();
            let params = LeakParams {
                black_level: self.black as f32,
                blur_px: self.blur(),
                ..Default::default()
            };
            let leaks = vec![[leak as f32; 3]; 17];
            let sep = separate_with_leak(&refs, &leaks, &params).unwrap();
            assert!(sep.flags.iter().all(|f| *f == LeakFlag::Ok));
            self.worst(&sep.direct, &sep.global)
        }

        fn nayar(&self) -> (f64, f64) {
            let frames = self.frames(17);
            let refs: Vec<&Rgb32FImage> = frames.iter().collect();
            let params = SeparationParams {
                black_level: self.black as f32,
                blur_px: self.blur(),
                ..Default::default()
            };
            let sep = separate(&refs, &params).unwrap();
            self.worst(&sep.direct, &sep.global)
        }
    }

    fn skin_like(kernel: Kernel) -> Scene {
        // Skin's proportions: the direct (surface) part is a few percent of the light.
        Scene {
            black: 0.02,
            defocus: 0.6,
            footprint: 0.45,
            kernel,
            ld: 0.02,
            lg: 0.4,
        }
    }

    #[test]
    fn analytic_leaks_match_hand_values() {
        // f = 1/6: Gaussian sigma 1 px: exp(-2 pi^2 / 36) = 0.578; exponential 1 px:
        // 1 / (1 + (pi / 3)^2) = 0.4770.
        assert!((gaussian_leak(1.0, 3.0) - 0.577_925).abs() < 1e-5);
        assert!((exponential_leak(1.0, 3.0) - 0.476_958).abs() < 1e-5);
        assert_eq!(gaussian_leak(0.0, 3.0), 1.0);
        assert!(gaussian_leak(6.0, 3.0) < 1e-5);
    }

    #[test]
    fn known_kernel_recovers_direct_and_global_where_nayar_leaks() {
        for kernel in [
            Kernel::Gaussian(1.0),
            Kernel::Gaussian(2.0),
            Kernel::Exponential(2.0),
            Kernel::Exponential(0.7),
        ] {
            let scene = skin_like(kernel);
            let (nd, ng) = scene.nayar();
            // Plain Nayar reads the stripes' global contrast as direct light: several times
            // the direct part on skin-like proportions.
            assert!(nd > 1.0 && ng > 0.05, "{kernel:?}: nayar {nd} {ng}");
            let (kd, kg) = scene.kernel_aware(kernel.leak(3.0));
            // Within 1 % of the direct part for wide kernels, 5-7 % for the narrowest (leak
            // 0.6): the pattern's blur model (a Gaussian for the footprint's box) is off by a
            // few 1e-3, which the solve amplifies by `lambda Lg / ((1 - lambda) Ld)`, here ~15.
            assert!(
                kd < 0.08 && kg < 0.005,
                "{kernel:?}: kernel-aware {kd} {kg}"
            );
        }
    }

    #[test]
    fn zero_leak_matches_nayar_on_wide_kernels() {
        let scene = Scene {
            ld: 0.3,
            lg: 0.2,
            ..skin_like(Kernel::Gaussian(30.0))
        };
        let (kd, kg) = scene.kernel_aware(0.0);
        assert!(kd < 0.01 && kg < 0.01, "{kd} {kg}");
    }

    #[test]
    fn a_wrong_leak_moves_the_split_the_predicted_way() {
        // Told a leak 0.05 too low, the direct estimate grows by about 0.05 Lg / (1 - lambda).
        let kernel = Kernel::Gaussian(1.5);
        let scene = skin_like(kernel);
        let lambda = kernel.leak(3.0);
        let frames = scene.frames(17);
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let params = LeakParams {
            black_level: 0.02,
            blur_px: scene.blur(),
            ..Default::default()
        };
        let low = separate_with_leak(&refs, &[[(lambda - 0.05) as f32; 3]; 17], &params).unwrap();
        let expected = scene.ld + 0.05 * (scene.ld + scene.lg) / (1.0 - lambda + 0.05);
        for d in low.direct.pixels() {
            assert!(
                ((d.0[0] as f64 - expected) / expected).abs() < 0.05,
                "{} vs {expected}",
                d.0[0]
            );
        }
    }

    /// Skin-like frames with a saturated pixel (1), a NaN (2) and an out-of-range one (5).
    fn garbled_frames() -> Vec<Rgb32FImage> {
        let scene = skin_like(Kernel::Gaussian(1.0));
        let mut frames = scene.frames(6);
        frames[0].put_pixel(1, 0, image::Rgb([1.0, 0.5, 0.5]));
        frames[2].put_pixel(2, 0, image::Rgb([f32::NAN, 0.1, 0.1]));
        frames[3].put_pixel(5, 0, image::Rgb([-3.0, f32::MAX, 0.0]));
        frames
    }

    fn garbled_params() -> LeakParams {
        LeakParams {
            black_level: 0.02,
            blur_px: 0.6,
            ..Default::default()
        }
    }

    #[test]
    fn narrow_kernels_saturation_and_garbage_are_flagged_never_nan() {
        let frames = garbled_frames();
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let mut leaks = vec![[0.5f32; 3]; 6];
        leaks[3] = [0.99, 0.2, 0.2];
        leaks[4] = [f32::INFINITY, 0.0, 0.0];
        let params = garbled_params();
        let sep = separate_with_leak(&refs, &leaks, &params).unwrap();
        assert_eq!(sep.flags[1], LeakFlag::Saturated);
        assert_eq!(sep.flags[2], LeakFlag::NonFinite);
        assert_eq!(sep.flags[3], LeakFlag::NarrowKernel);
        assert_eq!(sep.flags[4], LeakFlag::NonFinite);
        assert_eq!(sep.flags[5], LeakFlag::Saturated);
        // The narrow channel is all global, the others separated.
        let (d3, g3) = (sep.direct.get_pixel(3, 0).0, sep.global.get_pixel(3, 0).0);
        assert!(d3[0] == 0.0 && g3[0] > 0.0 && g3[1] > 0.0);
        assert_eq!(sep.stats.narrow_kernel_pixels, 1);
        for v in sep.direct.as_raw().iter().chain(sep.global.as_raw()) {
            assert!(v.is_finite() && *v >= 0.0, "{v}");
        }
    }

    #[test]
    fn stripe_totals_are_the_zero_leak_splits_totals_and_flags() {
        let frames = garbled_frames();
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let params = garbled_params();
        let (w, h) = frames[0].dimensions();
        let zero = vec![[0.0f32; 3]; (w * h) as usize];
        let split = separate_with_leak(&refs, &zero, &params).unwrap();
        let totals = stripe_totals(&refs, &params).unwrap();
        assert_eq!(totals.flags, split.flags);
        assert_eq!(totals.stats.saturated_pixels, split.stats.saturated_pixels);
        assert_eq!(
            totals.stats.non_finite_pixels,
            split.stats.non_finite_pixels
        );
        assert!(totals.direct.iter().all(|v| *v == 0.0));
        for ((d, g), t) in split
            .direct
            .iter()
            .zip(split.global.iter())
            .zip(totals.global.iter())
        {
            assert!(
                (d + g - t).abs() <= 1e-6 * t.max(1e-3),
                "{d} + {g} against {t}"
            );
        }
    }

    #[test]
    fn random_frames_never_give_nan_or_negative_light() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let frames: Vec<Rgb32FImage> = (0..6)
            .map(|_| Rgb32FImage::from_fn(64, 4, |_, _| image::Rgb([next(), next(), next()])))
            .collect();
        let leaks: Vec<[f32; 3]> = (0..256)
            .map(|_| [next() * 1.2 - 0.1, next(), next()])
            .collect();
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let sep = separate_with_leak(&refs, &leaks, &LeakParams::default()).unwrap();
        for v in sep.direct.as_raw().iter().chain(sep.global.as_raw()) {
            assert!(v.is_finite() && *v >= 0.0, "{v}");
        }
    }

    #[test]
    fn colourless_smoothing_keeps_totals_and_averages_noise() {
        // A colourless direct of 0.02 with per-channel noise, global coloured.
        let (w, h) = (16u32, 16u32);
        let mut state = 7u32;
        let mut noise = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let direct = Rgb32FImage::from_fn(w, h, |_, _| {
            image::Rgb([
                0.02 + 0.02 * noise(),
                0.02 + 0.02 * noise(),
                0.02 + 0.02 * noise(),
            ])
        });
        let global = Rgb32FImage::from_pixel(w, h, image::Rgb([0.4, 0.25, 0.2]));
        let totals: Vec<f32> = direct
            .as_raw()
            .iter()
            .zip(global.as_raw())
            .map(|(d, g)| d + g)
            .collect();
        let mut sep = LeakSeparation {
            direct,
            global,
            flags: vec![LeakFlag::Ok; (w * h) as usize],
            stats: LeakStats::default(),
        };
        colourless_smoothed_direct(&mut sep, 2.0);
        for (i, p) in sep.direct.pixels().enumerate() {
            assert!(p.0[0] == p.0[1] && p.0[1] == p.0[2]);
            assert!((p.0[0] - 0.02).abs() < 0.003, "{}", p.0[0]);
            for c in 0..3 {
                let sum = p.0[c] + sep.global.as_raw()[i * 3 + c];
                assert!((sum - totals[i * 3 + c]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        let a = Rgb32FImage::new(4, 3);
        let frames = vec![&a; 6];
        assert!(matches!(
            separate_with_leak(&frames, &[[0.0; 3]; 5], &LeakParams::default()),
            Err(SeparationError::LeakSize { expected: 12, .. })
        ));
        assert!(matches!(
            separate_with_leak(&frames[..4], &[[0.0; 3]; 12], &LeakParams::default()),
            Err(SeparationError::ShiftCount { expected: 6, .. })
        ));
    }
}

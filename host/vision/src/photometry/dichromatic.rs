//! The direct part of a kernel-aware separation re-read with the dichromatic model: each pixel's
//! total `T` (RGB) is a colourless surface reflection plus subsurface light of the skin's body
//! colour, `T = Ld (1, 1, 1) + s rho`, and `Ld` is the least-squares coefficient of the grey axis.
//!
//! Why: the stripes and the slit sweep cannot tell skin's direct reflection from its kernel's core
//! (a large share of skin's subsurface light leaves within a projector pixel of where it entered,
//! so both stay flat up to the projector's Nyquist frequency; seen on the virtual booth's ground
//! truth). Colour can: the reflection is colourless, the core is skin coloured. The body colour
//! `rho` is read once per image, as the median chromaticity of the separation's global part over
//! its brighter pixels: the separation is wrong per pixel but its global part keeps the body's
//! colour; the per-pixel fit then places each pixel between white and that colour.
//!
//! Limits: one body colour per projector image (freckles, lips, make-up read as specular
//! changes); on light skin the direct light is a few percent of the total, so a chromaticity
//! error of a fraction of a percent is already a large relative error of the direct part.

use image::Rgb32FImage;

use super::kernel_leak::{LeakFlag, LeakSeparation};

/// Share of the separated pixels, darkest first, left out of the body-colour median (shadows and
/// edges, whose chromaticity is noise).
const DARK_SHARE: f64 = 0.3;

/// The body colour (chromaticity, sums to 1) of a split: per channel the median of
/// `g / sum(g)` over the separated pixels brighter than the darkest `DARK_SHARE`, with `g` the
/// pixel's total less its colourless direct part (the mean of the channels' direct parts, at most
/// each channel's total). `None` without such pixels.
pub fn body_colour(sep: &LeakSeparation) -> Option<[f32; 3]> {
    let direct = sep.direct.as_raw();
    let global = sep.global.as_raw();
    let subsurface: Vec<(usize, [f32; 3])> = sep
        .flags
        .iter()
        .enumerate()
        .filter(|(_, f)| **f == LeakFlag::Ok)
        .map(|(i, _)| {
            let d = (0..3).map(|c| direct[i * 3 + c]).sum::<f32>() / 3.0;
            let g = std::array::from_fn(|c| {
                let total = direct[i * 3 + c] + global[i * 3 + c];
                total - d.clamp(0.0, total.max(0.0))
            });
            (i, g)
        })
        .filter(|(_, g)| {
            let s: f32 = g.iter().sum();
            s > 0.0 && s.is_finite()
        })
        .collect();
    if subsurface.is_empty() {
        return None;
    }
    let sum = |g: &[f32; 3]| g.iter().sum::<f32>();
    let mut levels: Vec<f32> = subsurface.iter().map(|(_, g)| sum(g)).collect();
    let cut = ((levels.len() as f64 * DARK_SHARE) as usize).min(levels.len() - 1);
    let threshold = *levels.select_nth_unstable_by(cut, f32::total_cmp).1;
    let shares = subsurface
        .iter()
        .filter(|(_, g)| sum(g) >= threshold)
        .map(|(_, g)| *g);
    median_chromaticity(shares)
}

/// Per channel the median of `v / sum(v)` over `values` (each with a positive finite sum),
/// normalised to sum 1; `None` without values.
pub fn median_chromaticity(values: impl Iterator<Item = [f32; 3]>) -> Option<[f32; 3]> {
    let mut shares: [Vec<f32>; 3] = Default::default();
    for v in values {
        let s: f32 = v.iter().sum();
        for (c, share) in shares.iter_mut().enumerate() {
            share.push(v[c] / s);
        }
    }
    if shares[0].is_empty() {
        return None;
    }
    let colour: [f32; 3] = std::array::from_fn(|c| {
        let mid = shares[c].len() / 2;
        *shares[c].select_nth_unstable_by(mid, f32::total_cmp).1
    });
    let total: f32 = colour.iter().sum();
    (total > 0.0).then(|| colour.map(|v| v / total))
}

/// The grey coefficient of `total` in the basis `(1, 1, 1)`, `rho` (least squares over the three
/// channels), clamped to `[0, min channel]`; 0 when `rho` is grey (no colour to tell them apart).
pub fn grey_coefficient(total: [f32; 3], rho: [f32; 3]) -> f32 {
    let a12: f32 = rho.iter().sum();
    let a22: f32 = rho.iter().map(|r| r * r).sum();
    let b1: f32 = total.iter().sum();
    let b2: f32 = total.iter().zip(&rho).map(|(t, r)| t * r).sum();
    let det = 3.0 * a22 - a12 * a12;
    if det <= 1e-4 * a12 * a12 || !det.is_finite() {
        return 0.0;
    }
    let ld = (a22 * b1 - a12 * b2) / det;
    let floor = total.iter().copied().fold(f32::INFINITY, f32::min).max(0.0);
    if ld.is_finite() {
        ld.clamp(0.0, floor)
    } else {
        0.0
    }
}

/// Replaces the separation's direct part by the dichromatic one (see the module documentation)
/// on every pixel with a total (flag `Ok` or `NarrowKernel`; the flags are kept), averaged over
/// such neighbours with a Gaussian of `sigma_px` camera px (0: per pixel),
/// keeping each pixel's total. Returns the body colour used, `None` (and the separation
/// unchanged) when it could not be read.
pub fn dichromatic_direct(sep: &mut LeakSeparation, sigma_px: f64) -> Option<[f32; 3]> {
    let rho = body_colour(sep)?;
    let direct = sep.direct.as_raw();
    let global = sep.global.as_raw();
    // Pixels the stripes could not split (kernel too narrow in some channel) still have their
    // total, which is all the fit needs.
    let ok: Vec<bool> = sep
        .flags
        .iter()
        .map(|f| matches!(f, LeakFlag::Ok | LeakFlag::NarrowKernel))
        .collect();
    let totals: Vec<[f32; 3]> = (0..ok.len())
        .map(|i| std::array::from_fn(|c| direct[i * 3 + c] + global[i * 3 + c]))
        .collect();
    let grey: Vec<f32> = totals
        .iter()
        .zip(&ok)
        .map(|(t, &ok)| if ok { grey_coefficient(*t, rho) } else { 0.0 })
        .collect();
    set_grey_direct(&mut sep.direct, &mut sep.global, grey, &ok, sigma_px);
    Some(rho)
}

/// Sets the `direct` part of a split of the pixels `ok` to the colourless `grey` (one value per
/// pixel), averaged over such neighbours with a Gaussian of `sigma_px` camera px (0: per pixel)
/// and clamped into each channel's total `direct + global`, which every pixel keeps; the rest
/// of the pixels are left as they are.
pub fn set_grey_direct(
    direct: &mut Rgb32FImage,
    global: &mut Rgb32FImage,
    mut grey: Vec<f32>,
    ok: &[bool],
    sigma_px: f64,
) {
    use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d};
    let (w, h) = direct.dimensions();
    let (w, h) = (w as usize, h as usize);
    let mut weight: Vec<f32> = ok.iter().map(|&ok| f32::from(u8::from(ok))).collect();
    if sigma_px > 0.0 {
        let kernel = GaussianKernel::new(sigma_px as f32, 3.0, Normalisation::Outputs);
        // Both have the image's size, so the blur cannot fail; keep per-pixel values if it did.
        let mut smoothed = grey.clone();
        let mut smoothed_weight = weight.clone();
        if blur_2d(&mut smoothed, w, h, &kernel, Border::Clamp)
            .and_then(|()| blur_2d(&mut smoothed_weight, w, h, &kernel, Border::Clamp))
            .is_ok()
        {
            grey = smoothed;
            weight = smoothed_weight;
        }
    }
    let direct = direct.as_mut();
    let global = global.as_mut();
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photometry::kernel_leak::{
        LeakParams, colourless_smoothed_direct, separate_with_leak,
    };
    use crate::photometry::slit_leak::{LeakReading, SweepGeometry, leak_from_slits};
    use image::Rgb32FImage;
    use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_1d};

    /// Sub-samples per projector px of the 1-D booth below.
    const SUB: usize = 10;
    /// Pattern period of the 1-D booth, projector px: a multiple of the slit period (10) and of
    /// the stripe period (6).
    const PERIOD: usize = 30;
    const DEFOCUS: f64 = 0.6;
    const BLACK: f64 = 0.02;

    /// A skin-like analytic kernel per channel: a share `core` of the light leaves where it
    /// entered (a delta: the part no pattern a projector draws can tell from a reflection), the
    /// rest spreads as a Gaussian of sigma `sigma` px.
    #[derive(Clone, Copy)]
    struct Kernel {
        core: f64,
        sigma: f64,
    }

    fn gauss(signal: &[f64], sigma_px: f64) -> Vec<f64> {
        let kernel = GaussianKernel::new(sigma_px * SUB as f64, 5.0, Normalisation::Outputs);
        blur_1d(signal, &kernel, Border::Wrap)
    }

    /// A row of camera pixels at phases spread over the period, each with its own colourless
    /// reflection `ld[p]` and subsurface light `s[p] rho` spread by `kernels`.
    struct Scene {
        ld: Vec<f64>,
        s: Vec<f64>,
        rho: [f64; 3],
        kernels: [Kernel; 3],
    }

    impl Scene {
        /// The frame of an emitted pattern (`lit(u)` for projector column `u`).
        fn frame(&self, lit: impl Fn(usize) -> bool) -> Rgb32FImage {
            let n = PERIOD * SUB;
            let emission: Vec<f64> = (0..n)
                .map(|i| if lit(i / SUB) { 1.0 } else { BLACK })
                .collect();
            let focused = gauss(&emission, DEFOCUS);
            let spread: Vec<Vec<f64>> = self
                .kernels
                .iter()
                .map(|k| {
                    let wide = gauss(&focused, k.sigma);
                    focused
                        .iter()
                        .zip(&wide)
                        .map(|(f, w)| k.core * f + (1.0 - k.core) * w)
                        .collect()
                })
                .collect();
            let pixels = self.ld.len();
            Rgb32FImage::from_fn(pixels as u32, 1, |x, _| {
                let at = (x as usize * n * 7 / 3 / pixels + SUB / 2) % n;
                let p = x as usize;
                image::Rgb(std::array::from_fn(|c| {
                    (self.ld[p] * focused[at] + self.s[p] * self.rho[c] * spread[c][at]) as f32
                }))
            })
        }

        /// Direct relative RMS error of the kernel-aware split with the harmonics reading, its
        /// direct part read by `dichromatic` or the colourless mean.
        fn direct_error(&self, dichromatic: bool) -> f64 {
            let slits: Vec<Rgb32FImage> = (0..10).map(|o| self.frame(|u| u % 10 == o)).collect();
            let stripes: Vec<Rgb32FImage> = (0..6)
                .map(|shift| self.frame(|u| (u + 6 - shift) % 6 < 3))
                .collect();
            let white = self.frame(|_| true);
            let pixels = |img: &Rgb32FImage| img.pixels().map(|p| p.0).collect::<Vec<_>>();
            let slit_pixels: Vec<Vec<[f32; 3]>> = slits.iter().map(pixels).collect();
            let slit_refs: Vec<&[[f32; 3]]> = slit_pixels.iter().map(|s| s.as_slice()).collect();
            let geometry = SweepGeometry {
                slit_width_px: 1,
                stripe_px: 3,
                black_level: BLACK as f32,
                blur_px: DEFOCUS as f32,
            };
            let (leak, _) = leak_from_slits(
                &slit_refs,
                &pixels(&white),
                &geometry,
                LeakReading::Harmonics,
            );
            let refs: Vec<&Rgb32FImage> = stripes.iter().collect();
            let params = LeakParams {
                black_level: BLACK as f32,
                blur_px: DEFOCUS as f32,
                ..LeakParams::default()
            };
            let mut sep = separate_with_leak(&refs, &leak, &params).unwrap();
            if dichromatic {
                assert!(dichromatic_direct(&mut sep, 0.0).is_some());
            } else {
                colourless_smoothed_direct(&mut sep, 0.0);
            }
            let (mut err, mut norm) = (0.0, 0.0);
            for (p, d) in sep.direct.pixels().enumerate() {
                for v in d.0 {
                    err += (f64::from(v) - self.ld[p]).powi(2);
                    norm += self.ld[p].powi(2);
                }
            }
            (err / norm).sqrt()
        }
    }

    /// `count` pixels whose reflection is `share(p)` of their light (`p` in [0, 1)).
    fn scene(count: usize, share: impl Fn(f64) -> f64, kernels: [Kernel; 3]) -> Scene {
        let rho = [0.55, 0.25, 0.2];
        let (mut ld, mut s) = (Vec::new(), Vec::new());
        for p in 0..count {
            let brightness = 0.3 + 0.5 * ((p * 37 % count) as f64 / count as f64);
            let a = share(p as f64 / count as f64);
            // Grey reflection `a` of the pixel's mean light: ld = a (ld + s / 3).
            ld.push(brightness * a);
            s.push(brightness * (1.0 - a) * 3.0);
        }
        Scene {
            ld,
            s,
            rho,
            kernels,
        }
    }

    #[test]
    fn colour_tells_the_reflection_from_a_kernel_core_the_stripes_cannot() {
        // Light-skin proportions: a reflection of `floor` of the light everywhere and highlights
        // up to 40 % more on two pixels in five; part of each channel's subsurface light leaves
        // within the pixel it entered (a core no projector pattern tells from a reflection).
        let kernels = [
            Kernel {
                core: 0.25,
                sigma: 2.0,
            },
            Kernel {
                core: 0.5,
                sigma: 1.2,
            },
            Kernel {
                core: 0.5,
                sigma: 1.0,
            },
        ];
        for (floor, bound) in [(0.0, 1e-3), (0.02, 0.15)] {
            let scene = scene(60, |p| floor + (p - 0.6).max(0.0), kernels);
            let colourless = scene.direct_error(false);
            let dichromatic = scene.direct_error(true);
            // The harmonics read the reflection in the slits as kernel: no direct part is left
            // for the colourless mean.
            assert!(colourless > 0.9, "floor {floor}: colourless {colourless}");
            // The body colour is read where most pixels show little reflection: exact without a
            // floor; the floor is read as body colour (0.12 of the direct light here).
            assert!(
                dichromatic < bound,
                "floor {floor}: dichromatic {dichromatic}"
            );
        }
    }

    #[test]
    fn grey_coefficient_recovers_a_colourless_reflection() {
        let rho = [0.55, 0.25, 0.2];
        for (ld, s) in [(0.0, 1.0), (0.05, 1.0), (0.4, 0.3), (1.0, 0.0)] {
            let total = rho.map(|r| ld + s * r);
            let got = grey_coefficient(total, rho);
            assert!((got - ld).abs() < 1e-5, "{ld}, {s}: {got}");
        }
        // A grey body colour cannot be told from the reflection: no direct part, never NaN.
        assert_eq!(grey_coefficient([0.3; 3], [1.0 / 3.0; 3]), 0.0);
        assert_eq!(grey_coefficient([f32::NAN; 3], [0.5, 0.3, 0.2]), 0.0);
    }
}

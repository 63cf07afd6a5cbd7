//! The global (subsurface) light of a slit frame, the input of the profiles.
//!
//! A slit frame of projector K holds: the direct reflection where the slit lands, the subsurface
//! light of the slit, and flat offsets from the projector's black level `b` (its "dark" pixels
//! still emit `b`) and from the other projectors' black level (stray). With the separation of the
//! white frame (`Ld`, `Lg` under level 1) and the projector's response `b + (1 - b) level`:
//!
//! `frame = Ld (b + (1 - b) lit) + b Lg + (1 - b) G + stray`
//!
//! where `G` is the global light of the slit alone at full level on a black background (what the
//! profiles need, in the same units as a full-white frame) and `lit` the fraction of the pixel's
//! view that the slit lights. Hence
//!
//! `G = (frame - Ld (b + (1 - b) lit) - b Lg - stray) / (1 - b)`.
//!
//! `lit` is not a 0/1 mask: the projector's defocus and the camera pixel's footprint blur the slit
//! edges, so it is the box of the slit convolved with a Gaussian of `blur_px` (projector pixels,
//! the same blur the separation stage corrects for). A hard mask would leave a fraction of the
//! direct reflection at every slit edge, right where the profile peaks.
//! Negative values (noise) are kept: the EM clamps them at 0 itself.
//!
//! Conventions: projector pixel centres at integer coordinates (as `capture::patterns`); images
//! camera-sized, row-major, RGB in the frames' units.

use rayon::prelude::*;

use mlsss_core::capture::{Axis, Pattern};

use super::profiles::slit_distance_px;

/// Errors of the slit global extraction.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum SlitGlobalError {
    /// The pattern handed over is not a slit.
    #[error("pattern {0} is not a slit")]
    NotASlit(String),
    /// An input image has the wrong number of pixels.
    #[error("{what} has {got} pixels, the frame {want}")]
    SizeMismatch {
        what: &'static str,
        got: usize,
        want: usize,
    },
    /// The black level leaves no contrast (`b >= 1`) or is not a number.
    #[error("black level {0} leaves no slit contrast")]
    BadBlackLevel(f32),
}

/// Inputs for one projector, per camera pixel (RGB).
#[derive(Debug, Clone, Copy)]
pub struct WhiteSeparation<'a> {
    pub direct: &'a [[f32; 3]],
    pub global: &'a [[f32; 3]],
    /// Light of the other projectors' black level present in every frame (zeros if unknown).
    pub stray: &'a [[f32; 3]],
    /// Projector black level (fraction of white).
    pub black_level: f32,
    /// Blur of the slit edges seen by a camera pixel (projector pixels, standard deviation).
    pub blur_px: f32,
}

/// Fraction of a pixel at projector coordinate `coord` (along the slit's profile axis) lit by a
/// comb of slits `width` px wide every `period` px from `offset`, with edges blurred by a Gaussian
/// of `blur_px`.
pub fn lit_fraction(coord: f64, width: u32, period: u32, offset: u32, blur_px: f64) -> f64 {
    let d = slit_distance_px(coord, width, period, offset);
    let half = f64::from(width) / 2.0;
    if blur_px <= 1e-6 {
        return if d.abs() < half { 1.0 } else { 0.0 };
    }
    let p = f64::from(period);
    // Most pixels are far from every slit: beyond UNLIT_SIGMAS every `erf` below is exactly
    // +-1 (it rounds to 1 from 6 on), so the sum is exactly 0 without computing it.
    let clear = UNLIT_SIGMAS * blur_px;
    if d.abs() - half > clear && p / 2.0 - half > clear {
        return 0.0;
    }
    blurred_comb(d, half, p, blur_px)
}

/// The light of the blurred slit nearest a pixel `d` px from its centre and of its two
/// neighbours (the blur never reaches further in practice): slits `2 half` wide every `p` px,
/// edges blurred by a Gaussian of `blur_px`.
fn blurred_comb(d: f64, half: f64, p: f64, blur_px: f64) -> f64 {
    let phi =
        |t: f64| 0.5 * (1.0 + mlsss_core::special::erf(t / (blur_px * std::f64::consts::SQRT_2)));
    let clear = UNLIT_SIGMAS * blur_px;
    [-p, 0.0, p]
        .iter()
        .map(|shift| {
            let c = d + shift;
            // A slit whose both edges lie beyond UNLIT_SIGMAS on the same side adds exactly 0
            // (both `phi` are exactly 0 or exactly 1): its two `erf` calls are skipped (a third
            // of the calls of a pixel near a slit, whose neighbours usually lie that far).
            if c.abs() - half > clear {
                0.0
            } else {
                phi(half - c) - phi(-half - c)
            }
        })
        .sum::<f64>()
        .clamp(0.0, 1.0)
}

/// Distance from a slit edge, in blur sigmas, beyond which [`lit_fraction`] is exactly 0:
/// `erf(10 / sqrt 2)` is 1 in double precision (so is `erf` of anything from 6 on).
const UNLIT_SIGMAS: f64 = 10.0;

/// Global component of one slit frame at full level on a black background (see the module doc).
/// `coords[i]` is the projector coordinate of pixel `i`; pixels without one are treated as unlit
/// by the slit (only the flat offsets are removed).
pub fn slit_global(
    frame: &[[f32; 3]],
    pattern: &Pattern,
    coords: &[Option<(f32, f32)>],
    white: &WhiteSeparation,
) -> Result<Vec<[f32; 3]>, SlitGlobalError> {
    let extraction = Extraction::new(frame.len(), pattern, coords, white)?;
    // Pixels are independent: split them across threads (same values as in sequence).
    Ok(frame
        .par_iter()
        .enumerate()
        .map(|(i, &f)| extraction.at(i, f))
        .collect())
}

/// [`slit_global`] at the camera pixels `pixels` alone (row-major indices of a frame of
/// `coords.len()` pixels): `frame[n]` is pixel `pixels[n]`'s value, and so is the result's.
/// The same values as the whole frame's at those pixels.
pub fn slit_global_at(
    frame: &[[f32; 3]],
    pixels: &[usize],
    pattern: &Pattern,
    coords: &[Option<(f32, f32)>],
    white: &WhiteSeparation,
) -> Result<Vec<[f32; 3]>, SlitGlobalError> {
    if frame.len() != pixels.len() {
        return Err(SlitGlobalError::SizeMismatch {
            what: "frame at the pixels",
            got: frame.len(),
            want: pixels.len(),
        });
    }
    let n = coords.len();
    if let Some(&outside) = pixels.iter().find(|&&i| i >= n) {
        return Err(SlitGlobalError::SizeMismatch {
            what: "pixel index",
            got: outside,
            want: n,
        });
    }
    let extraction = Extraction::new(n, pattern, coords, white)?;
    Ok(frame
        .par_iter()
        .zip(pixels)
        .map(|(&f, &i)| extraction.at(i, f))
        .collect())
}

/// One slit frame's extraction, checked and ready to apply pixel by pixel.
struct Extraction<'a> {
    axis: Axis,
    width: u32,
    period: u32,
    offset: u32,
    coords: &'a [Option<(f32, f32)>],
    white: &'a WhiteSeparation<'a>,
    blur: f64,
}

impl<'a> Extraction<'a> {
    /// Checks the pattern, the sizes of the per-pixel inputs against a frame of `n` pixels, and
    /// the black level.
    fn new(
        n: usize,
        pattern: &Pattern,
        coords: &'a [Option<(f32, f32)>],
        white: &'a WhiteSeparation<'a>,
    ) -> Result<Self, SlitGlobalError> {
        let Pattern::Slit {
            axis,
            width,
            period,
            offset,
        } = *pattern
        else {
            return Err(SlitGlobalError::NotASlit(pattern.label()));
        };
        for (what, got) in [
            ("coordinate map", coords.len()),
            ("direct image", white.direct.len()),
            ("global image", white.global.len()),
            ("stray image", white.stray.len()),
        ] {
            if got != n {
                return Err(SlitGlobalError::SizeMismatch { what, got, want: n });
            }
        }
        let b = white.black_level;
        if !(0.0..1.0).contains(&b) {
            return Err(SlitGlobalError::BadBlackLevel(b));
        }
        Ok(Self {
            axis,
            width,
            period,
            offset,
            coords,
            white,
            blur: f64::from(white.blur_px.max(0.0)),
        })
    }

    /// The global light of pixel `i`, whose frame value is `f` (`i` within the checked size).
    #[inline]
    fn at(&self, i: usize, f: [f32; 3]) -> [f32; 3] {
        let white = self.white;
        let b = white.black_level;
        let lit = self.coords[i].map_or(0.0, |(u, v)| {
            let coord = match self.axis {
                Axis::X => u,
                Axis::Y => v,
            };
            lit_fraction(
                f64::from(coord),
                self.width,
                self.period,
                self.offset,
                self.blur,
            ) as f32
        });
        let level = b + (1.0 - b) * lit;
        let mut out = [0.0f32; 3];
        for (c, o) in out.iter_mut().enumerate() {
            let rest =
                f[c] - white.direct[i][c] * level - b * white.global[i][c] - white.stray[i][c];
            *o = rest / (1.0 - b);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn removes_direct_on_the_slit_and_the_flat_offsets() {
        // Four pixels at projector columns 0, 3, 6, 9; slit on columns 3..5 (centre 4).
        let coords: Vec<Option<(f32, f32)>> = (0..4).map(|k| Some((3.0 * k as f32, 0.0))).collect();
        let pattern = Pattern::Slit {
            axis: Axis::X,
            width: 3,
            period: 30,
            offset: 3,
        };
        let (b, ld, lg, stray, profile) =
            (0.02f32, 0.3f32, 0.5f32, 0.01f32, [0.05, 0.4, 0.1, 0.02]);
        // Pixel 1 (column 3) sits 1 px from the slit centre, well inside with no blur.
        let frame: Vec<[f32; 3]> = (0..4)
            .map(|k| {
                let lit = if k == 1 { 1.0 } else { 0.0 };
                let v = ld * (b + (1.0 - b) * lit) + b * lg + (1.0 - b) * profile[k] + stray;
                [v, v, v]
            })
            .collect();
        let white = WhiteSeparation {
            direct: &[[ld; 3]; 4],
            global: &[[lg; 3]; 4],
            stray: &[[stray; 3]; 4],
            black_level: b,
            blur_px: 0.0,
        };
        let g = slit_global(&frame, &pattern, &coords, &white).unwrap();
        for k in 0..4 {
            assert!((g[k][1] - profile[k]).abs() < 1e-6, "{k}: {:?}", g[k]);
        }
    }

    #[test]
    fn blurred_lit_fraction_integrates_the_box() {
        // Slit on columns 0, 1, 2 (centre 1, edges at -0.5 and 2.5).
        let unblurred = |u: f64| lit_fraction(u, 3, 30, 0, 0.0);
        assert_eq!(unblurred(1.0), 1.0);
        assert_eq!(unblurred(2.4), 1.0);
        assert_eq!(unblurred(2.6), 0.0);
        // At an edge a blurred box is half lit; at the centre of a 3-px slit with sigma 0.5 it
        // is erf(1.5 / (0.5 sqrt 2)) = 0.99730.
        assert!((lit_fraction(2.5, 3, 30, 0, 0.5) - 0.5).abs() < 1e-9);
        assert!(
            (lit_fraction(1.0, 3, 30, 0, 0.5) - libm::erf(1.5 / (0.5 * 2f64.sqrt()))).abs() < 1e-9
        );
        // Summed over a period sampled every pixel, the lit fraction is the slit width.
        let total: f64 = (0..30)
            .map(|u| lit_fraction(f64::from(u) + 0.37, 3, 30, 0, 0.8))
            .sum();
        assert!((total - 3.0).abs() < 1e-6, "{total}");
    }

    /// The three blurred slits summed in full, without either shortcut for far slits.
    fn full_comb(d: f64, half: f64, p: f64, blur_px: f64) -> f64 {
        let phi = |t: f64| {
            0.5 * (1.0 + mlsss_core::special::erf(t / (blur_px * std::f64::consts::SQRT_2)))
        };
        [-p, 0.0, p]
            .iter()
            .map(|shift| {
                let c = d + shift;
                phi(half - c) - phi(-half - c)
            })
            .sum::<f64>()
            .clamp(0.0, 1.0)
    }

    #[test]
    fn far_pixels_and_far_slits_are_skipped_exactly_as_the_full_sum_says() {
        for (width, period, blur) in [
            (3, 30, 0.5),
            (4, 40, 0.9),
            (2, 12, 0.4),
            (3, 30, 1.4),
            (3, 30, 3.0),
            (2, 12, 2.0),
        ] {
            for i in 0..4000 {
                let coord = -7.0 + i as f64 * 0.0173;
                let d = slit_distance_px(coord, width, period, 1);
                let full = full_comb(d, f64::from(width) / 2.0, f64::from(period), blur);
                let fast = lit_fraction(coord, width, period, 1, blur);
                assert_eq!(fast.to_bits(), full.to_bits(), "{coord} {width} {period}");
            }
        }
    }

    /// At chosen pixels the extraction gives the whole frame's values there, bit for bit, and
    /// refuses a frame or pixel list that does not match.
    #[test]
    fn at_chosen_pixels_equals_the_whole_frame_there() {
        let n = 500;
        let coords: Vec<Option<(f32, f32)>> = (0..n)
            .map(|i| (i % 7 != 0).then_some((0.37 * i as f32, 0.11 * i as f32)))
            .collect();
        let value = |i: usize, k: u32| {
            (((i as u32).wrapping_mul(2_654_435_761) ^ k) % 1000) as f32 / 1000.0
        };
        let rgb = |k: u32| -> Vec<[f32; 3]> {
            (0..n)
                .map(|i| [value(i, k), value(i, k + 1), value(i, k + 2)])
                .collect()
        };
        let (frame, direct, global, stray) = (rgb(0), rgb(3), rgb(6), rgb(9));
        let white = WhiteSeparation {
            direct: &direct,
            global: &global,
            stray: &stray,
            black_level: 0.03,
            blur_px: 0.7,
        };
        let pattern = Pattern::Slit {
            axis: Axis::X,
            width: 3,
            period: 30,
            offset: 4,
        };
        let whole = slit_global(&frame, &pattern, &coords, &white).unwrap();
        let pixels: Vec<usize> = (0..n).filter(|i| i % 3 != 1).collect();
        let picked: Vec<[f32; 3]> = pixels.iter().map(|&i| frame[i]).collect();
        let at = slit_global_at(&picked, &pixels, &pattern, &coords, &white).unwrap();
        assert_eq!(at.len(), pixels.len());
        for (g, &i) in at.iter().zip(&pixels) {
            assert_eq!(g.map(f32::to_bits), whole[i].map(f32::to_bits), "pixel {i}");
        }
        assert!(slit_global_at(&picked[1..], &pixels, &pattern, &coords, &white).is_err());
        assert!(slit_global_at(&picked[..1], &[n], &pattern, &coords, &white).is_err());
    }

    #[test]
    fn refuses_other_patterns_and_mismatched_sizes() {
        let white = WhiteSeparation {
            direct: &[[0.0; 3]; 2],
            global: &[[0.0; 3]; 2],
            stray: &[[0.0; 3]; 2],
            black_level: 0.0,
            blur_px: 0.0,
        };
        let frame = [[0.0f32; 3]; 2];
        let coords = [None, None];
        assert!(matches!(
            slit_global(&frame, &Pattern::White, &coords, &white),
            Err(SlitGlobalError::NotASlit(_))
        ));
        let slit = Pattern::Slit {
            axis: Axis::Y,
            width: 3,
            period: 30,
            offset: 0,
        };
        assert!(matches!(
            slit_global(&frame, &slit, &coords[..1], &white),
            Err(SlitGlobalError::SizeMismatch { .. })
        ));
    }
}

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
    lit_fraction_with(coord, width, period, offset, blur_px, &mut |t| {
        edge_light(t, blur_px)
    })
}

/// [`lit_fraction`] with the light of a blurred edge `t` px inside it, [`edge_light`]`(t,
/// blur_px)`, taken from `edge` (which may remember it: [`EdgeMemo`]).
fn lit_fraction_with(
    coord: f64,
    width: u32,
    period: u32,
    offset: u32,
    blur_px: f64,
    edge: &mut impl FnMut(f64) -> f64,
) -> f64 {
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
    blurred_comb(d, half, p, blur_px, edge)
}

/// Light of a slit edge blurred by a Gaussian of `blur_px` at `t` px inside the lit side:
/// `Phi(t / blur_px)`.
fn edge_light(t: f64, blur_px: f64) -> f64 {
    0.5 * (1.0 + mlsss_core::special::erf(t / (blur_px * std::f64::consts::SQRT_2)))
}

/// The light of the blurred slit nearest a pixel `d` px from its centre and of its two
/// neighbours (the blur never reaches further in practice): slits `2 half` wide every `p` px,
/// edges blurred by a Gaussian of `blur_px`, whose light `edge` gives ([`edge_light`]).
fn blurred_comb(d: f64, half: f64, p: f64, blur_px: f64, edge: &mut impl FnMut(f64) -> f64) -> f64 {
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
                edge(half - c) - edge(-half - c)
            }
        })
        .sum::<f64>()
        .clamp(0.0, 1.0)
}

/// The [`edge_light`] values one pixel has asked for, by the bits of the edge's distance `t`.
///
/// Why: consecutive slits of a sweep share their edges (offsets a slit width apart), so the
/// slit frames of one pixel ask for the light of the same edges again; the distances come out
/// exactly equal (a coordinate of an `f32` minus integers and halves, exact in `f64`). The same
/// distance gives the same value, so a remembered one is bit for bit what `erf` would give
/// again. `erf` was 14 % of the profiles stage's CPU time at full size (perf; blur 0.6 px, 3-px
/// slits every 3 px, where a pixel reaches five slits of an axis and their six edges).
struct EdgeMemo {
    blur_px: f64,
    distances: [u64; Self::CAPACITY],
    values: [f64; Self::CAPACITY],
    len: usize,
}

impl EdgeMemo {
    /// Edges remembered; a pixel meets about a dozen (further ones are computed again).
    const CAPACITY: usize = 24;

    fn new(blur_px: f64) -> Self {
        Self {
            blur_px,
            distances: [0; Self::CAPACITY],
            values: [0.0; Self::CAPACITY],
            len: 0,
        }
    }

    /// [`edge_light`]`(t, blur_px)`.
    #[inline]
    fn light(&mut self, t: f64) -> f64 {
        let bits = t.to_bits();
        if let Some(k) = self.distances[..self.len].iter().position(|&d| d == bits) {
            return self.values[k];
        }
        let value = edge_light(t, self.blur_px);
        if self.len < Self::CAPACITY {
            self.distances[self.len] = bits;
            self.values[self.len] = value;
            self.len += 1;
        }
        value
    }
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
        let blur = self.blur;
        let lit = self.lit_with(self.coords[i], &mut |t| edge_light(t, blur));
        PixelWhite::of(self.white, i).global_light(f, lit)
    }

    /// The fraction of the view of a pixel at projector `coords` that the slit lights (0
    /// without coordinates), with the light of the slit edges from `edge`
    /// ([`lit_fraction_with`]).
    #[inline]
    fn lit_with(&self, coords: Option<(f32, f32)>, edge: &mut impl FnMut(f64) -> f64) -> f32 {
        coords.map_or(0.0, |(u, v)| {
            let coord = match self.axis {
                Axis::X => u,
                Axis::Y => v,
            };
            lit_fraction_with(
                f64::from(coord),
                self.width,
                self.period,
                self.offset,
                self.blur,
                edge,
            ) as f32
        })
    }
}

/// The white separation at one pixel: what every slit frame of the pixel shares.
struct PixelWhite {
    direct: [f32; 3],
    global: [f32; 3],
    stray: [f32; 3],
    black_level: f32,
}

impl PixelWhite {
    /// Pixel `i` of `white` (`i` within its images).
    #[inline]
    fn of(white: &WhiteSeparation, i: usize) -> Self {
        Self {
            direct: white.direct[i],
            global: white.global[i],
            stray: white.stray[i],
            black_level: white.black_level,
        }
    }

    /// The module doc's `G` of a frame value `f` whose slit lights `lit` of the pixel's view.
    #[inline]
    fn global_light(&self, f: [f32; 3], lit: f32) -> [f32; 3] {
        let b = self.black_level;
        let level = b + (1.0 - b) * lit;
        let mut out = [0.0f32; 3];
        for (c, o) in out.iter_mut().enumerate() {
            let rest = f[c] - self.direct[c] * level - b * self.global[c] - self.stray[c];
            *o = rest / (1.0 - b);
        }
        out
    }
}

/// [`slit_global`] of several slit frames of one projector (one white separation), pixel by
/// pixel: a pixel's value in every frame together. The same values as each frame's
/// [`slit_global`]; the frames of a pixel share the `erf` of the slit edges they have in
/// common (computed once per pixel).
pub struct SweepExtraction<'a> {
    frames: Vec<Extraction<'a>>,
    pixels: usize,
}

impl<'a> SweepExtraction<'a> {
    /// Checks the `patterns` (slits) and the per-pixel inputs against frames of `n` pixels.
    pub fn new(
        n: usize,
        patterns: &[Pattern],
        coords: &'a [Option<(f32, f32)>],
        white: &'a WhiteSeparation<'a>,
    ) -> Result<Self, SlitGlobalError> {
        let frames = patterns
            .iter()
            .map(|pattern| Extraction::new(n, pattern, coords, white))
            .collect::<Result<_, _>>()?;
        Ok(Self { frames, pixels: n })
    }

    /// The global light of pixel `i` in the frames `frames` (indices into the patterns given):
    /// frame `j`'s value there is `value(j)`, its global light goes to `out[3 (j - frames.start)..]`.
    /// Refuses a pixel outside the frames, a range past the patterns, or an `out` of another
    /// length than 3 values a frame.
    pub fn pixel(
        &self,
        i: usize,
        frames: std::ops::Range<usize>,
        value: impl Fn(usize) -> [f32; 3],
        out: &mut [f32],
    ) -> Result<(), SlitGlobalError> {
        if i >= self.pixels {
            return Err(SlitGlobalError::SizeMismatch {
                what: "pixel index",
                got: i,
                want: self.pixels,
            });
        }
        let Some(extractions) = self.frames.get(frames.clone()) else {
            return Err(SlitGlobalError::SizeMismatch {
                what: "frame range",
                got: frames.end,
                want: self.frames.len(),
            });
        };
        if out.len() != 3 * extractions.len() {
            return Err(SlitGlobalError::SizeMismatch {
                what: "output of the pixel",
                got: out.len(),
                want: 3 * extractions.len(),
            });
        }
        let Some(first) = extractions.first() else {
            return Ok(());
        };
        // The frames share the white separation and the coordinates (`SweepExtraction::new`
        // checks every one against the same): read once for all of them, not once a frame
        // (600 000 pixels x the 10 frames of an axis on one core: 185 -> 162-169 ms).
        let (white, coords) = (PixelWhite::of(first.white, i), first.coords[i]);
        let mut memo = EdgeMemo::new(first.blur);
        for ((j, e), o) in frames.zip(extractions).zip(out.chunks_exact_mut(3)) {
            let lit = e.lit_with(coords, &mut |t| memo.light(t));
            o.copy_from_slice(&white.global_light(value(j), lit));
        }
        Ok(())
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

    /// A sweep extracted pixel by pixel, sharing the edges' `erf` between its frames, gives
    /// every frame's [`slit_global`] bit for bit (slits of both axes, offsets a width apart so
    /// that edges are shared, blurs from none to wide, pixels without coordinates), and refuses
    /// a pixel, frame range or output that does not fit.
    #[test]
    fn sweep_pixel_by_pixel_equals_each_frame_extracted_alone() {
        let n = 3000;
        let value = |i: usize, k: u32| {
            (((i as u32).wrapping_mul(2_654_435_761) ^ k.wrapping_mul(40_503)) % 10_000) as f32
                / 10_000.0
        };
        let coords: Vec<Option<(f32, f32)>> = (0..n)
            .map(|i| {
                (i % 11 != 0).then_some((
                    -3.0 + 1400.0 * value(i, 91),
                    0.173 * i as f32 - 40.0 + value(i, 92),
                ))
            })
            .collect();
        let rgb = |k: u32| -> Vec<[f32; 3]> {
            (0..n)
                .map(|i| [value(i, k), value(i, k + 1), value(i, k + 2)])
                .collect()
        };
        let (direct, global, stray) = (rgb(3), rgb(6), rgb(9));
        let patterns = crate::chain_tests::slit_patterns();
        let frames: Vec<Vec<[f32; 3]>> = (0..patterns.len() as u32)
            .map(|j| rgb(20 + 3 * j))
            .collect();
        for blur_px in [0.0, 0.35, 0.6216, 1.3, 4.0] {
            let white = WhiteSeparation {
                direct: &direct,
                global: &global,
                stray: &stray,
                black_level: 0.02,
                blur_px,
            };
            let alone: Vec<Vec<[f32; 3]>> = patterns
                .iter()
                .zip(&frames)
                .map(|(pattern, frame)| slit_global(frame, pattern, &coords, &white).unwrap())
                .collect();
            let sweep = SweepExtraction::new(n, &patterns, &coords, &white).unwrap();
            for range in [0..10, 10..20, 0..20, 4..7] {
                let mut out = vec![0.0f32; 3 * range.len()];
                for i in 0..n {
                    sweep
                        .pixel(i, range.clone(), |j| frames[j][i], &mut out)
                        .unwrap();
                    for (j, o) in range.clone().zip(out.chunks_exact(3)) {
                        assert_eq!(
                            o.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                            alone[j][i].map(f32::to_bits),
                            "blur {blur_px}, pixel {i}, frame {j}"
                        );
                    }
                }
            }
            let mut out = vec![0.0f32; 30];
            assert!(sweep.pixel(n, 0..10, |j| frames[j][0], &mut out).is_err());
            assert!(sweep.pixel(0, 15..25, |j| frames[j][0], &mut out).is_err());
            assert!(sweep.pixel(0, 0..9, |j| frames[j][0], &mut out).is_err());
        }
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

//! Step 2 of the algorithm: each bit decided against its inverse, and whether it is reliable.

use rayon::prelude::*;

use super::lit_test::{BLOCK, Lighting, LitLevels, pair_chi_square, pair_variance};
use super::{BitPair, DecodeParams};

/// Bits of one axis at one pixel: the raw Gray code and which bits are reliable.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct PixelBits {
    pub(super) gray: u16,
    pub(super) reliable: u16,
    pub(super) lighting: Lighting,
}

/// Bits of every pixel of one axis and their summed relative contrast (for the confidence).
pub(super) type AxisBits = (Vec<PixelBits>, Vec<f32>);

/// Steps 1 and 2 in one read of the frames: the lit test of every pixel and the bits of both
/// axes, block by block (each pair's variance serves both). Why: the frames are 40 full-size f32
/// images (210 MB for a 1280 x 1024 capture); reading them once instead of three times (lit
/// test, then each axis) cut the memory traffic of these steps by half. The bits come back
/// unmasked: after the partly-lit demotion, [`mask_unlit`] clears those of pixels not lit. The
/// same operations in the same order per pixel as [`super::lit_test::classify_lighting`] and
/// [`decide_bits`] (test).
pub(super) fn first_pass(
    x: &[BitPair],
    y: &[BitPair],
    white_black: Option<(&[f32], &[f32])>,
    amplitude: &[f32],
    params: &DecodeParams,
) -> (Vec<Lighting>, AxisBits, AxisBits) {
    let n = amplitude.len();
    let levels = LitLevels::new(
        x.len() + y.len() + usize::from(white_black.is_some()),
        params,
    );
    let mut lighting = vec![Lighting::Unlit; n];
    let (mut u_bits, mut u_contrast) = (vec![PixelBits::default(); n], vec![0.0f32; n]);
    let (mut v_bits, mut v_contrast) = (vec![PixelBits::default(); n], vec![0.0f32; n]);
    lighting
        .par_chunks_mut(BLOCK)
        .zip(u_bits.par_chunks_mut(BLOCK))
        .zip(u_contrast.par_chunks_mut(BLOCK))
        .zip(v_bits.par_chunks_mut(BLOCK))
        .zip(v_contrast.par_chunks_mut(BLOCK))
        .enumerate()
        .for_each(
            |(block, ((((lighting, u_bits), u_contrast), v_bits), v_contrast))| {
                let range = block * BLOCK..block * BLOCK + lighting.len();
                let mut sum = [0.0f64; BLOCK];
                let sum = &mut sum[..lighting.len()];
                let amp = &amplitude[range.clone()];
                decide_pairs(x, amp, range.start, params, sum, u_bits, u_contrast);
                decide_pairs(y, amp, range.start, params, sum, v_bits, v_contrast);
                if let Some((white, black)) = white_black {
                    let (w, b) = (
                        white.get(range.clone()).unwrap_or_default(),
                        black.get(range).unwrap_or_default(),
                    );
                    for ((s, &w), &b) in sum.iter_mut().zip(w).zip(b) {
                        *s += pair_chi_square(w, b, params);
                    }
                }
                for (l, &s) in lighting.iter_mut().zip(sum.iter()) {
                    *l = levels.classify(s);
                }
            },
        );
    (lighting, (u_bits, u_contrast), (v_bits, v_contrast))
}

/// One axis's bits of the pixels `start..start + bits.len()` and their chi-square terms added to
/// `sum`, one frame pair at a time: [`decide_pairs_portable`], compiled for AVX2 where the CPU
/// has it. Why: the loop is f64 divisions and square roots, two lanes wide in the baseline
/// x86-64 build and four with AVX2; the same IEEE operations in the same order either way (no
/// FMA is enabled, so no product is fused), hence the same bits (test).
fn decide_pairs(
    pairs: &[BitPair],
    amplitude: &[f32],
    start: usize,
    params: &DecodeParams,
    sum: &mut [f64],
    bits: &mut [PixelBits],
    contrast: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, the one feature `decide_pairs_avx2` is compiled for.
        unsafe { decide_pairs_avx2(pairs, amplitude, start, params, sum, bits, contrast) };
        return;
    }
    decide_pairs_portable(pairs, amplitude, start, params, sum, bits, contrast);
}

/// [`decide_pairs_portable`] compiled with AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn decide_pairs_avx2(
    pairs: &[BitPair],
    amplitude: &[f32],
    start: usize,
    params: &DecodeParams,
    sum: &mut [f64],
    bits: &mut [PixelBits],
    contrast: &mut [f32],
) {
    decide_pairs_portable(pairs, amplitude, start, params, sum, bits, contrast);
}

/// The body of [`decide_pairs`] (inlined into each instruction-set variant).
#[inline(always)]
fn decide_pairs_portable(
    pairs: &[BitPair],
    amplitude: &[f32],
    start: usize,
    params: &DecodeParams,
    sum: &mut [f64],
    bits: &mut [PixelBits],
    contrast: &mut [f32],
) {
    let nbits = pairs.len();
    // The contrast reference: the pixel's modulation, never below its noise.
    let mut amp = [0.0f32; BLOCK];
    let amp = &mut amp[..bits.len()];
    for (a, &m) in amp.iter_mut().zip(amplitude) {
        *a = m.max(f32::MIN_POSITIVE);
    }
    // The bits in plain arrays while the pairs stream through (the loop then vectorises; on the
    // `PixelBits` structs it ran one pixel at a time), stored into `bits` at the end.
    let mut gray = [0u16; BLOCK];
    let mut reliable = [0u16; BLOCK];
    let (gray, reliable) = (&mut gray[..bits.len()], &mut reliable[..bits.len()]);
    for (j, pair) in pairs.iter().enumerate() {
        let bit = nbits - 1 - j;
        let range = start..start + bits.len();
        let (pattern, inverse) = (
            pair.pattern.get(range.clone()).unwrap_or_default(),
            pair.inverse.get(range).unwrap_or_default(),
        );
        let pixels = gray
            .iter_mut()
            .zip(reliable.iter_mut())
            .zip(contrast.iter_mut())
            .zip(sum.iter_mut());
        for (((((g, r), c), s), &a), (&p, &q)) in
            pixels.zip(amp.iter()).zip(pattern.iter().zip(inverse))
        {
            let d = p - q;
            let variance = pair_variance(p, q, params);
            // `pair_chi_square`, with the variance the bit test also needs.
            let dd = d as f64;
            *s += dd * dd / variance;
            let sigma = variance.sqrt() as f32;
            let relative = d.abs() / a;
            *g |= u16::from(d > 0.0) << bit;
            let is_reliable =
                d.abs() >= params.min_bit_snr * sigma && relative >= params.min_bit_contrast;
            *r |= u16::from(is_reliable) << bit;
            *c += relative.min(1.0);
        }
    }
    for ((b, &g), &r) in bits.iter_mut().zip(gray.iter()).zip(reliable.iter()) {
        b.gray = g;
        b.reliable = r;
    }
}

/// Pixels that are not clearly lit have no bits (and no contrast); lit ones are marked lit.
pub(super) fn mask_unlit(bits: &mut [PixelBits], contrast: &mut [f32], lighting: &[Lighting]) {
    bits.par_iter_mut()
        .zip(contrast.par_iter_mut())
        .zip(lighting.par_iter())
        .with_min_len(BLOCK)
        .for_each(|((b, c), &l)| {
            if l == Lighting::Lit {
                b.lighting = l;
            } else {
                *b = PixelBits {
                    lighting: l,
                    ..PixelBits::default()
                };
                *c = 0.0;
            }
        });
}

/// The reference of [`first_pass`]'s bits (tests): decides every bit of every pixel against its inverse. Also returns the summed relative contrast
/// of the bits (for the confidence).
#[cfg(test)]
pub(super) fn decide_bits(
    pairs: &[BitPair],
    amplitude: &[f32],
    lighting: &[Lighting],
    params: &DecodeParams,
) -> (Vec<PixelBits>, Vec<f32>) {
    let n = amplitude.len().min(lighting.len());
    let mut bits = vec![PixelBits::default(); n];
    let mut contrast = vec![0.0f32; n];
    bits.par_chunks_mut(BLOCK)
        .zip(contrast.par_chunks_mut(BLOCK))
        .enumerate()
        .for_each(|(block, (bits, contrast))| {
            let start = block * BLOCK;
            let range = start..start + bits.len();
            decide_block(
                pairs,
                &amplitude[range.clone()],
                &lighting[range.clone()],
                range.start,
                params,
                bits,
                contrast,
            );
        });
    (bits, contrast)
}

/// [`decide_bits`] for the pixels `start..start + bits.len()`, one frame pair at a time.
#[cfg(test)]
fn decide_block(
    pairs: &[BitPair],
    amplitude: &[f32],
    lighting: &[Lighting],
    start: usize,
    params: &DecodeParams,
    bits: &mut [PixelBits],
    contrast: &mut [f32],
) {
    let nbits = pairs.len();
    // The contrast reference: the pixel's modulation, never below its noise.
    let mut amp = [0.0f32; BLOCK];
    let amp = &mut amp[..bits.len()];
    for (a, &m) in amp.iter_mut().zip(amplitude) {
        *a = m.max(f32::MIN_POSITIVE);
    }
    for (j, pair) in pairs.iter().enumerate() {
        let bit = nbits - 1 - j;
        let range = start..start + bits.len();
        let (pattern, inverse) = (
            pair.pattern.get(range.clone()).unwrap_or_default(),
            pair.inverse.get(range).unwrap_or_default(),
        );
        for ((((b, c), &a), &p), &q) in bits
            .iter_mut()
            .zip(contrast.iter_mut())
            .zip(amp.iter())
            .zip(pattern)
            .zip(inverse)
        {
            let d = p - q;
            let sigma = pair_variance(p, q, params).sqrt() as f32;
            let relative = d.abs() / a;
            if d > 0.0 {
                b.gray |= 1 << bit;
            }
            if d.abs() >= params.min_bit_snr * sigma && relative >= params.min_bit_contrast {
                b.reliable |= 1 << bit;
            }
            *c += relative.min(1.0);
        }
    }
    // Pixels that are not clearly lit have no bits (and no contrast).
    for ((b, c), &l) in bits.iter_mut().zip(contrast.iter_mut()).zip(lighting) {
        if l == Lighting::Lit {
            b.lighting = l;
        } else {
            *b = PixelBits {
                lighting: l,
                ..PixelBits::default()
            };
            *c = 0.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::gray_code::lit_test::{classify_lighting, demote_partly_lit};
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    /// The straightforward bit decisions: one pixel at a time, every pair in turn.
    fn decide_pixel(
        pairs: &[BitPair],
        i: usize,
        amp: f32,
        lighting: Lighting,
        params: &DecodeParams,
    ) -> (PixelBits, f32) {
        let mut bits = PixelBits {
            lighting,
            ..PixelBits::default()
        };
        let mut contrast = 0.0;
        if lighting != Lighting::Lit {
            return (bits, contrast);
        }
        let amp = amp.max(f32::MIN_POSITIVE);
        for (j, pair) in pairs.iter().enumerate() {
            let bit = pairs.len() - 1 - j;
            let (p, q) = (pair.pattern[i], pair.inverse[i]);
            let d = p - q;
            let sigma = pair_variance(p, q, params).sqrt() as f32;
            if d > 0.0 {
                bits.gray |= 1 << bit;
            }
            if d.abs() >= params.min_bit_snr * sigma && d.abs() / amp >= params.min_bit_contrast {
                bits.reliable |= 1 << bit;
            }
            contrast += (d.abs() / amp).min(1.0);
        }
        (bits, contrast)
    }

    /// The straightforward lit test: the chi-square sum of one pixel, pair after pair.
    fn lighting_of_pixel(
        pairs: &[&BitPair],
        wb: (&[f32], &[f32]),
        i: usize,
        params: &DecodeParams,
    ) -> Lighting {
        let terms = pairs.len() + 1;
        let lit = crate::geometry::gray_code::lit_test::chi_square_quantile(
            terms,
            params.lit_false_alarm as f64,
        );
        let dim = crate::geometry::gray_code::lit_test::chi_square_quantile(
            terms,
            params.dim_false_alarm as f64,
        );
        let chi = |a: f32, b: f32| {
            let d = (a - b) as f64;
            d * d / crate::geometry::gray_code::lit_test::pair_variance(a, b, params)
        };
        let mut s: f64 = pairs.iter().map(|p| chi(p.pattern[i], p.inverse[i])).sum();
        s += chi(wb.0[i], wb.1[i]);
        if s >= lit {
            Lighting::Lit
        } else if s >= dim {
            Lighting::Dim
        } else {
            Lighting::Unlit
        }
    }

    /// Frames of `n` pixels at levels spread from noise to full scale.
    fn random_pairs(seed: u64, n: usize, count: usize) -> (Vec<BitPair>, Vec<f32>, Vec<f32>) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let level: Vec<f32> = (0..n)
            .map(|_| 10f32.powf(rng.gen_range(-4.0..0.0)))
            .collect();
        let frame = |rng: &mut rand_pcg::Pcg64| -> Vec<f32> {
            level
                .iter()
                .map(|&l| l * rng.gen_range(0.0..1.0f32))
                .collect()
        };
        let pairs = (0..count)
            .map(|_| BitPair {
                pattern: frame(&mut rng),
                inverse: frame(&mut rng),
            })
            .collect();
        let white = level.clone();
        let black = frame(&mut rng).iter().map(|v| 0.05 * v).collect();
        (pairs, white, black)
    }

    /// The AVX2 build of the pair loop gives the portable one's bits, sums and contrasts,
    /// bit for bit (skipped where the CPU has no AVX2).
    #[test]
    fn avx2_pair_loop_equals_the_portable_one() {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // One block (the loop's unit), not a multiple of any vector width.
            let n = BLOCK - 37;
            let (pairs, white, black) = random_pairs(7, n, 10);
            let amplitude: Vec<f32> = white.iter().zip(&black).map(|(w, b)| w - b).collect();
            for params in [
                DecodeParams::default(),
                DecodeParams {
                    min_bit_snr: 2.5,
                    ..DecodeParams::for_8_bit()
                },
            ] {
                let run = |avx2: bool| {
                    let mut sum = vec![0.0f64; n];
                    let mut bits = vec![PixelBits::default(); n];
                    let mut contrast = vec![0.0f32; n];
                    if avx2 {
                        // SAFETY: AVX2 was detected above.
                        unsafe {
                            decide_pairs_avx2(
                                &pairs,
                                &amplitude,
                                0,
                                &params,
                                &mut sum,
                                &mut bits,
                                &mut contrast,
                            )
                        };
                    } else {
                        decide_pairs_portable(
                            &pairs,
                            &amplitude,
                            0,
                            &params,
                            &mut sum,
                            &mut bits,
                            &mut contrast,
                        );
                    }
                    (
                        sum.iter().map(|s| s.to_bits()).collect::<Vec<_>>(),
                        bits,
                        contrast.iter().map(|c| c.to_bits()).collect::<Vec<_>>(),
                    )
                };
                assert_eq!(run(true), run(false));
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// The blocked lit test, partly-lit check and bit decisions give exactly the
        /// per-pixel results, across block boundaries.
        #[test]
        fn blocked_loops_equal_the_per_pixel_decisions(
            seed in 0u64..1_000_000,
            width in 1usize..90,
            height in 1usize..70,
            count in 1usize..9,
            snr in 0.5f32..4.0,
        ) {
            let n = width * height;
            let params = DecodeParams { min_bit_snr: snr, dim_false_alarm: 0.01, lit_false_alarm: 1e-4, ..DecodeParams::default() };
            let (pairs, white, black) = random_pairs(seed, n, count);
            let refs: Vec<&BitPair> = pairs.iter().collect();
            let lighting = classify_lighting(&refs, Some((&white, &black)), &params);
            for (i, &l) in lighting.iter().enumerate() {
                prop_assert_eq!(l, lighting_of_pixel(&refs, (&white, &black), i, &params));
            }
            let amplitude: Vec<f32> = white.iter().zip(&black).map(|(w, b)| w - b).collect();
            let mut demoted = lighting.clone();
            demote_partly_lit(&mut demoted, &amplitude, width, 2, 0.5);
            for (i, &l) in demoted.iter().enumerate() {
                let (x, y) = ((i % width) as isize, (i / width) as isize);
                let mut brightest = 0.0f32;
                for ny in (y - 2).max(0)..(y + 3).min(height as isize) {
                    for nx in (x - 2).max(0)..(x + 3).min(width as isize) {
                        let j = ny as usize * width + nx as usize;
                        if lighting[j] == Lighting::Lit {
                            brightest = brightest.max(amplitude[j]);
                        }
                    }
                }
                let expected = if lighting[i] == Lighting::Lit && amplitude[i] < 0.5 * brightest {
                    Lighting::Dim
                } else {
                    lighting[i]
                };
                prop_assert_eq!(l, expected);
            }
            let (bits, contrast) = decide_bits(&pairs, &amplitude, &demoted, &params);
            for i in 0..n {
                let (b, c) = decide_pixel(&pairs, i, amplitude[i], demoted[i], &params);
                prop_assert_eq!(bits[i], b);
                prop_assert_eq!(contrast[i].to_bits(), c.to_bits());
            }
            // The one-read pass the decoder runs, the pairs split into two axes: the same
            // lighting and, once demoted and masked, the same bits of each axis.
            let split = count / 2;
            let (x, y) = pairs.split_at(split);
            let (mut fused, (mut ub, mut uc), (mut vb, mut vc)) =
                first_pass(x, y, Some((&white, &black)), &amplitude, &params);
            prop_assert_eq!(&fused, &lighting);
            demote_partly_lit(&mut fused, &amplitude, width, 2, 0.5);
            mask_unlit(&mut ub, &mut uc, &fused);
            mask_unlit(&mut vb, &mut vc, &fused);
            for (axis, (b, c)) in [(x, (&ub, &uc)), (y, (&vb, &vc))] {
                for i in 0..n {
                    let (rb, rc) = decide_pixel(axis, i, amplitude[i], demoted[i], &params);
                    prop_assert_eq!(b[i], rb);
                    prop_assert_eq!(c[i].to_bits(), rc.to_bits());
                }
            }
        }
    }
}

//! Step 2 of the algorithm: each bit decided against its inverse, and whether it is reliable.

use rayon::prelude::*;

use super::lit_test::{BLOCK, Lighting, pair_variance};
use super::{BitPair, DecodeParams};

/// Bits of one axis at one pixel: the raw Gray code and which bits are reliable.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct PixelBits {
    pub(super) gray: u16,
    pub(super) reliable: u16,
    pub(super) lighting: Lighting,
}

/// Decides every bit of every pixel against its inverse. Also returns the summed relative contrast
/// of the bits (for the confidence).
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

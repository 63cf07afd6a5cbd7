//! Step 2 of the algorithm: each bit decided against its inverse, and whether it is reliable.

use rayon::prelude::*;

use super::lit_test::{Lighting, pair_variance};
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
    let nbits = pairs.len();
    amplitude
        .par_iter()
        .zip(lighting.par_iter())
        .enumerate()
        .map(|(i, (&amp, &lighting))| {
            let mut bits = PixelBits {
                lighting,
                ..PixelBits::default()
            };
            let mut contrast = 0.0;
            if lighting != Lighting::Lit {
                return (bits, contrast);
            }
            // The contrast reference: the pixel's modulation, never below its noise.
            let amp = amp.max(f32::MIN_POSITIVE);
            for (j, pair) in pairs.iter().enumerate() {
                let bit = nbits - 1 - j;
                let (p, q) = (pair.pattern[i], pair.inverse[i]);
                let d = p - q;
                let sigma = pair_variance(p, q, params).sqrt() as f32;
                let relative = d.abs() / amp;
                if d > 0.0 {
                    bits.gray |= 1 << bit;
                }
                if d.abs() >= params.min_bit_snr * sigma && relative >= params.min_bit_contrast {
                    bits.reliable |= 1 << bit;
                }
                contrast += relative.min(1.0);
            }
            (bits, contrast)
        })
        .unzip()
}

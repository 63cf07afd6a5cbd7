//! Standard normal deviates in f32, many at a time: Box-Muller over the photon lanes' random
//! streams (`lane_rng`) and fast maths (`fast_math`), compiled for AVX-512, AVX2 and portable
//! vectors and picked at run time like the photon step. For callers that need hundreds of
//! millions of deviates (the virtual booth's camera noise) and no more than f32 of each.
//!
//! A stream is a pure function of (seed, stream): `LANES` xoshiro128++ streams seeded as a photon
//! batch's are. Every instruction set gives the same bits (the lane operations are IEEE, the fused
//! multiply-adds exactly rounded), and so does any way of splitting the output into `fill` calls.
//! Each block of `BLOCK` deviates is one Box-Muller step of every lane: deviate `i < LANES` is
//! lane i's r cos phi, deviate `LANES + i` its r sin phi (independent of the first, as Box-Muller
//! gives them; lane i's next pair comes from its next two draws).
//!
//! Accuracy (tests below): a deviate is within 2e-6 of the exact Box-Muller value of the same two
//! 32-bit draws, r (cos, sin) phi with r = sqrt(-2 ln u) evaluated in f64: r is within 1e-7
//! relative (`ln`'s bound through the square root; checked for every u in [1/2, 1] and on a sweep
//! below), `sin_cos_quarter` within 1.2e-7 absolute, so |error| <= 6.66 (1e-7 + 1.2e-7 + 2^-24)
//! < 2e-6. Measured on 6.4 million deviates: 6.8e-7 absolute, 2.5e-7 relative at most. The
//! distribution is Box-Muller's exact normal but for the draws' granularity: u takes 2^31 equally
//! likely values (then rounded to f32, 2^-24 relative, which moves the radius's CDF by at most
//! 6e-8), so the largest radius is sqrt(-2 ln 2^-32) = sqrt(64 ln 2) = 6.66 and no deviate
//! exceeds 6.66 in magnitude: a standard normal exceeds it with probability 2.7e-11 (one deviate
//! in 37 billion; 0.01 in the ~5e8 of a whole `mlsss demo --quick`). The angle is uniform on a
//! grid of 2^25 steps of the circle.
//!
//! Why f32 is enough for camera noise: the noisy values are stored in f32 and then quantised to
//! 12-bit codes. An error of 2e-6 standard deviations of the noise, whose standard deviation is
//! at most 75 codes (the booth's 12000 e- full well at saturation and analog gain 4), is at most
//! 1.5e-4 of a code; storing a value near 1 in f32 already rounds it by 2.4e-4 of a code.

use super::lane_rng::LaneRng;
use super::photon_lanes::{Isa, portable};
use super::simd::LANES;

/// Deviates per Box-Muller step of all lanes.
pub const BLOCK: usize = 2 * LANES;

/// A stream of independent standard normal deviates, as f32.
pub struct NormalStream {
    rng: LaneRng,
    isa: Isa,
    /// Deviates of the last block not yet handed out: `block[next..]`.
    block: [f32; BLOCK],
    next: usize,
}

impl NormalStream {
    /// The stream `stream` of `seed`: a pure function of the two (streams of one seed, and
    /// equal streams of different seeds, are independent).
    pub fn new(seed: u64, stream: u64) -> Self {
        Self::with_isa(seed, stream, Isa::detect())
    }

    fn with_isa(seed: u64, stream: u64, isa: Isa) -> Self {
        Self {
            rng: LaneRng::for_batch(seed ^ NORMAL_SEED_DOMAIN, stream),
            isa,
            block: [0.0; BLOCK],
            next: BLOCK,
        }
    }

    /// Fills `out` with the stream's next `out.len()` deviates.
    pub fn fill(&mut self, out: &mut [f32]) {
        let kept = (BLOCK - self.next).min(out.len());
        out[..kept].copy_from_slice(&self.block[self.next..self.next + kept]);
        self.next += kept;
        let rest = &mut out[kept..];
        let whole = rest.len() - rest.len() % BLOCK;
        let (blocks, tail) = rest.split_at_mut(whole);
        self.fill_blocks(blocks);
        if !tail.is_empty() {
            let mut block = [0.0f32; BLOCK];
            self.fill_blocks(&mut block);
            self.block = block;
            tail.copy_from_slice(&self.block[..tail.len()]);
            self.next = tail.len();
        }
    }

    /// Fills `out` (a whole number of blocks) with fresh blocks, on the best instruction set.
    fn fill_blocks(&mut self, out: &mut [f32]) {
        debug_assert!(out.len().is_multiple_of(BLOCK));
        match self.isa {
            // SAFETY: `Isa::detect` chose these only where the CPU has the features.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { fill_blocks_avx512(&mut self.rng, out) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { fill_blocks_avx2(&mut self.rng, out) },
            _ => fill_blocks_portable(&mut self.rng, out),
        }
    }
}

/// Mixed into the seed so that a normal stream never shares its lanes' states with the photon
/// batch of the same (seed, batch) (a caller may use one seed for both).
const NORMAL_SEED_DOMAIN: u64 = 0x6761_7573_7369_616e;

/// One Box-Muller step per block, with `pair` the lane kernel of one instruction set.
#[inline(always)]
fn fill_blocks_with<V>(
    rng: &mut LaneRng,
    out: &mut [f32],
    pair: impl Fn(&mut LaneRng) -> (V, V),
    store: impl Fn(V) -> [f32; LANES],
) {
    for block in out.chunks_exact_mut(BLOCK) {
        let (cos_part, sin_part) = pair(rng);
        block[..LANES].copy_from_slice(&store(cos_part));
        block[LANES..].copy_from_slice(&store(sin_part));
    }
}

fn fill_blocks_portable(rng: &mut LaneRng, out: &mut [f32]) {
    fill_blocks_with(rng, out, portable::normal_pair, |v| v.store());
}

/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn fill_blocks_avx2(rng: &mut LaneRng, out: &mut [f32]) {
    // Closures, not the fn items: closures inherit this function's target features.
    #[allow(clippy::redundant_closure)]
    fill_blocks_with(
        rng,
        out,
        |rng| super::photon_lanes::avx2::normal_pair(rng),
        |v| v.store(),
    );
}

/// # Safety
/// The CPU must support AVX-512 F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn fill_blocks_avx512(rng: &mut LaneRng, out: &mut [f32]) {
    #[allow(clippy::redundant_closure)]
    fill_blocks_with(
        rng,
        out,
        |rng| super::photon_lanes::avx512::normal_pair(rng),
        |v| v.store(),
    );
}

#[cfg(test)]
mod tests;

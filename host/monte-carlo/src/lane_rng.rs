//! One random stream per photon lane: xoshiro128++ (Blackman & Vigna 2019) with its four 32-bit
//! state words stored lane-major, so all 16 lanes advance with one SIMD integer instruction per
//! operation (32-bit words: the lanes' f32 width; PCG's wide multiply does not vectorise).
//!
//! Each (seed, batch, lane) gets its own state from splitmix64, the seeding its authors recommend;
//! the streams are 2^128 - 1 long and a run draws far fewer than 2^64 numbers, so overlap between
//! them is not a practical concern.

use super::simd::LANES;

/// Lane-major xoshiro128++ state: `s[word][lane]`.
pub(crate) struct LaneRng {
    pub(crate) s: [[u32; LANES]; 4],
}

impl LaneRng {
    /// The streams of one batch: a pure function of (seed, batch).
    pub(crate) fn for_batch(seed: u64, batch: u64) -> Self {
        let mut s = [[0u32; LANES]; 4];
        let base = splitmix64(splitmix64(seed) ^ splitmix64(batch ^ 0x6a09_e667_f3bc_c909));
        for lane in 0..LANES {
            let mut state = base.wrapping_add((lane as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            for pair in s.chunks_exact_mut(2) {
                state = splitmix64(state);
                pair[0][lane] = state as u32;
                pair[1][lane] = (state >> 32) as u32;
            }
            // An all-zero state would stay zero; splitmix64 is a bijection, so this needs four
            // zero outputs in a row, but make it impossible rather than improbable.
            if s.iter().all(|w| w[lane] == 0) {
                s[0][lane] = 1;
            }
        }
        Self { s }
    }

    /// 32 random bits from one lane's stream (for the scalar boundary and roulette code).
    #[inline(always)]
    pub(crate) fn next_bits_of(&mut self, lane: usize) -> u32 {
        self.step(lane)
    }

    #[inline(always)]
    fn step(&mut self, lane: usize) -> u32 {
        let [s0, s1, s2, s3] = [
            self.s[0][lane],
            self.s[1][lane],
            self.s[2][lane],
            self.s[3][lane],
        ];
        let result = s0.wrapping_add(s3).rotate_left(7).wrapping_add(s0);
        let t = s1 << 9;
        let s2 = s2 ^ s0;
        let s3 = s3 ^ s1;
        let s1 = s1 ^ s2;
        let s0 = s0 ^ s3;
        let s2 = s2 ^ t;
        let s3 = s3.rotate_left(11);
        self.s[0][lane] = s0;
        self.s[1][lane] = s1;
        self.s[2][lane] = s2;
        self.s[3][lane] = s3;
        result
    }
}

/// Uniform in [0, 1) with all 32 bits (exact in f64), for the scalar code's probabilities.
#[inline(always)]
pub(crate) fn unit(bits: u32) -> f64 {
    f64::from(bits) * (1.0 / 4_294_967_296.0)
}

fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photon_lanes::portable::{next_bits, next_bits_n, units, units_open};
    use crate::simd::U32s;

    /// First output of xoshiro128++ from the state (1, 2, 3, 4), computed by hand from the
    /// reference C code: rotl(1 + 4, 7) + 1 = 5 * 2^7 + 1.
    #[test]
    fn matches_the_reference_algorithm() {
        let mut rng = LaneRng {
            s: [[1; LANES], [2; LANES], [3; LANES], [4; LANES]],
        };
        assert_eq!(rng.next_bits_of(0), 5 * (1 << 7) + 1);
        assert_eq!(next_bits(&mut rng).0[1], 5 * (1 << 7) + 1);
        // Lanes are independent copies of one algorithm: lane 0 has now made two steps and lane 1
        // one, so lane 0's third output is lane 1's third.
        assert_eq!(next_bits(&mut rng).0[0], rng.next_bits_of(1));
    }

    /// The step's three draws at once are each lane's next three scalar draws, in order, and
    /// leave the same state.
    #[test]
    fn draws_at_once_are_the_next_draws_in_order() {
        let mut at_once = LaneRng::for_batch(11, 5);
        let mut one_by_one = LaneRng::for_batch(11, 5);
        for _ in 0..4 {
            let draws: [U32s; 3] = next_bits_n(&mut at_once);
            for draw in draws {
                for (lane, &bits) in draw.0.iter().enumerate() {
                    assert_eq!(bits, one_by_one.next_bits_of(lane));
                }
            }
        }
        assert_eq!(at_once.s, one_by_one.s);
    }

    #[test]
    fn unit_draws_cover_their_intervals() {
        assert_eq!(unit(0), 0.0);
        assert!(unit(u32::MAX) < 1.0);
        assert!(units(U32s::splat(u32::MAX)).0[3] < 1.0);
        assert_eq!(units(U32s::splat(0)).0[3], 0.0);
        // The step's uniform: in (0, 1], never 0 (its log is taken), down to 2^-32.
        assert_eq!(units_open(U32s::splat(u32::MAX)).0[0], 1.0);
        assert_eq!(units_open(U32s::splat(0)).0[0], 2f32.powi(-32));
        // Mean and variance of many draws from one lane: 1/2 and 1/12 within 5 standard errors.
        let mut rng = LaneRng::for_batch(7, 3);
        let n = 100_000;
        let draws: Vec<f64> = (0..n).map(|_| unit(rng.next_bits_of(2))).collect();
        let mean = draws.iter().sum::<f64>() / n as f64;
        let var = draws.iter().map(|u| (u - mean).powi(2)).sum::<f64>() / n as f64;
        let se = (1.0 / 12.0 / n as f64).sqrt();
        assert!((mean - 0.5).abs() < 5.0 * se, "mean {mean}");
        assert!((var - 1.0 / 12.0).abs() < 0.002, "variance {var}");
    }

    #[test]
    fn batches_and_lanes_get_different_streams() {
        let mut a = LaneRng::for_batch(1, 0);
        let mut b = LaneRng::for_batch(1, 1);
        let first_a = next_bits(&mut a);
        let first_b = next_bits(&mut b);
        assert_ne!(first_a, first_b);
        assert!(first_a.0.iter().skip(1).all(|&x| x != first_a.0[0]));
    }
}

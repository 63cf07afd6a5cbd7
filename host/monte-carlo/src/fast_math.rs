//! Branch-free `ln`, `sin` and `cos` for the photon lanes: the constants and error bounds here, the
//! lane-vector code in `lane_kernels.rs` (compiled once per instruction set).
//!
//! `std`'s `f64::ln` and `sin_cos` call into libm, which the compiler cannot vectorise; these
//! versions are straight-line code (bit manipulation, one division, polynomials) that it turns into
//! SIMD when the photon loop runs over several lanes at once. They use the fdlibm / musl
//! polynomials (Sun Microsystems 1993, freely redistributable), without the special-case branches
//! that the transport never needs.
//!
//! Error bounds (checked by the tests below against `std` on a dense sweep):
//! - `ln`: relative error below 3e-16 (1.4 times f64 epsilon; measured worst 2.2e-16) for every
//!   positive normal `x`.
//! - `sin_cos_quarter`: absolute error below 2e-16 for |a| <= pi/4.
//!
//! They work on whole lane vectors. Neither handles zero, infinities, NaN or subnormals; the
//! callers never pass them.

// The constants are quoted digit for digit as fdlibm publishes them, so they can be checked.
#![allow(clippy::excessive_precision)]

/// ln(2) split so that `k * LN2_HI` is exact for the exponents of normal numbers.
pub(crate) const LN2_HI: f64 = 6.931_471_803_691_238_164_90e-1;
pub(crate) const LN2_LO: f64 = 1.908_214_929_270_587_700_02e-10;
/// Coefficients of the minimax polynomial R(z) ~ (ln((1+s)/(1-s)) - 2s) / s, z = s^2 (fdlibm).
pub(crate) const LG1: f64 = 6.666_666_666_666_735_130e-1;
pub(crate) const LG2: f64 = 3.999_999_999_940_941_908e-1;
pub(crate) const LG3: f64 = 2.857_142_874_366_239_149e-1;
pub(crate) const LG4: f64 = 2.222_219_843_214_978_396e-1;
pub(crate) const LG5: f64 = 1.818_357_216_161_805_012e-1;
pub(crate) const LG6: f64 = 1.531_383_769_920_937_332e-1;
pub(crate) const LG7: f64 = 1.479_819_860_511_658_591e-1;

pub(crate) const S1: f64 = -1.666_666_666_666_663_243_48e-1;
pub(crate) const S2: f64 = 8.333_333_333_322_489_461_24e-3;
pub(crate) const S3: f64 = -1.984_126_982_985_794_931_34e-4;
pub(crate) const S4: f64 = 2.755_731_370_707_006_767_89e-6;
pub(crate) const S5: f64 = -2.505_076_025_340_686_341_95e-8;
pub(crate) const S6: f64 = 1.589_690_995_211_550_102_21e-10;
pub(crate) const C1: f64 = 4.166_666_666_666_660_190_37e-2;
pub(crate) const C2: f64 = -1.388_888_888_887_410_957_49e-3;
pub(crate) const C3: f64 = 2.480_158_728_947_672_941_78e-5;
pub(crate) const C4: f64 = -2.755_731_435_139_066_330_35e-7;
pub(crate) const C5: f64 = 2.087_572_321_298_174_827_90e-9;
pub(crate) const C6: f64 = -1.135_964_755_778_819_482_65e-11;

#[cfg(test)]
mod tests {
    use crate::photon_lanes::portable::{ln, sin_cos_quarter};
    use crate::simd::{F64s, LANES};

    fn ln1(x: f64) -> f64 {
        ln(F64s::splat(x)).0[LANES - 1]
    }

    fn sin_cos1(a: f64) -> (f64, f64) {
        let (s, c) = sin_cos_quarter(F64s::splat(a));
        (s.0[0], c.0[0])
    }

    /// Relative error in units of f64's epsilon.
    fn rel_err(got: f64, want: f64) -> f64 {
        if want == 0.0 {
            got.abs()
        } else {
            ((got - want) / want).abs()
        }
    }

    #[test]
    fn ln_is_within_its_stated_bound_on_the_unit_interval_and_beyond() {
        let mut worst: f64 = 0.0;
        // Every 52-bit uniform the lanes can draw lies in (0, 1]; sweep it densely near 1 (where
        // ln -> 0) and geometrically down to 2^-52.
        for i in 1..=200_000u64 {
            let near_one = 1.0 - i as f64 * 2f64.powi(-40);
            let linear = i as f64 / 200_000.0;
            let geometric = 2f64.powf(-52.0 * i as f64 / 200_000.0);
            for x in [near_one, linear, geometric] {
                worst = worst.max(rel_err(ln1(x), x.ln()));
            }
        }
        for e in -1000..1000 {
            let x = 1.37 * 2f64.powi(e);
            worst = worst.max(rel_err(ln1(x), x.ln()));
        }
        assert!(worst < 3e-16, "worst relative error {worst:e}");
        assert_eq!(ln1(1.0), 0.0);
        let mixed = F64s([0.5, 1.0, 2.0, 1e-300, 3.0, 1e300, 0.1, 7.0]);
        for (got, x) in ln(mixed).0.iter().zip(mixed.0) {
            assert!(rel_err(*got, x.ln()) < 3e-16);
        }
    }

    #[test]
    fn sin_cos_is_within_its_stated_bound_on_a_quarter_turn() {
        let mut worst: f64 = 0.0;
        let quarter = std::f64::consts::FRAC_PI_4;
        for i in 0..=400_000 {
            let a = -quarter + 2.0 * quarter * i as f64 / 400_000.0;
            let (s, c) = sin_cos1(a);
            worst = worst.max((s - a.sin()).abs()).max((c - a.cos()).abs());
        }
        assert!(worst < 2e-16, "worst absolute error {worst:e}");
    }
}

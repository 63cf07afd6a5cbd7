//! `x.floor()` without a call into libm, for the per-sample hot loops of the renderer (bin
//! positions, bilinear corners) and of the slit profiles (`euclid_mod`, one per slit sample).
//!
//! Why: the build's baseline x86_64 has no rounding instruction, so `f64::floor` is a call into
//! libm (2.2 % of the full-size profiles stage's CPU time, perf). Truncating through `i64` is
//! exact below 2^52 in magnitude (every such `f64` with a fraction lies there), and one less than
//! a truncation above `x` is its floor; larger magnitudes, infinities and NaN go to `f64::floor`.
//! The one difference is the sign of a zero (`-0.0` gives `+0.0`), which neither caller sees.

/// `x.floor()`, but `-0.0` for `+0.0` (see the module's doc).
#[inline(always)]
pub(crate) fn floor(x: f64) -> f64 {
    const EXACT_BELOW: f64 = 4_503_599_627_370_496.0; // 2^52: every such float truncates exactly
    if x.abs() < EXACT_BELOW {
        let t = x as i64 as f64;
        if t > x { t - 1.0 } else { t }
    } else {
        x.floor()
    }
}

#[cfg(test)]
mod tests {
    use super::floor as floor_inline;

    /// The inline floor equals `f64::floor` bit for bit but for the sign of a zero.
    #[test]
    fn inline_floor_is_libms() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let check = |x: f64| {
            let (got, want) = (floor_inline(x), x.floor());
            let same = got.to_bits() == want.to_bits() || (got == 0.0 && want == 0.0);
            assert!(same || (got.is_nan() && want.is_nan()), "{x}: {got} {want}");
        };
        for _ in 0..200_000 {
            check(rng.gen_range(-5000.0..5000.0));
            check(rng.gen_range(-1.0..1.0));
        }
        for e in [0.5f64, 1.0, 2.0, 1e15, 4_503_599_627_370_496.0, 9e15, 1e300] {
            for x in [e, -e] {
                check(x);
                check(x.next_up());
                check(x.next_down());
            }
        }
        for x in [
            0.0,
            -0.0,
            4.9e-324,
            -4.9e-324,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ] {
            check(x);
        }
        assert_eq!(floor_inline(-0.5), -1.0);
        assert_eq!(floor_inline(-3.0), -3.0);
        assert_eq!(floor_inline(2.75), 2.0);
    }
}

//! The error function and its complement, fast enough for the EM's inner loop.
//!
//! Why not `libm::erfc`: it is FreeBSD's `s_erf.c`, whose tail branch (`|x| >= 1.25`, where most
//! slit-profile samples fall) calls the software `libm::exp` twice. Profiling the full-size fit
//! put those two calls at a quarter of the whole pipeline's CPU time. This is the same algorithm
//! with the same coefficients (Sun Microsystems, 1993; see the notice below), with one difference:
//! the tail computes `exp(-x^2 - 0.5625 + R/S)` with a single call of the standard library's `exp`
//! instead of splitting `x^2` across two calls. Rounding that exponent (about `x^2`) then costs a
//! relative error of up to `~2.5e-16 x^2`: 1e-14 at `x = 6` (a normal tail of 1e-16), 2e-13 at
//! `x = 27` where `erfc` underflows. Elsewhere the results are FreeBSD's to an ulp; the tests hold
//! both to `libm`.
//!
//! ```text
//! Copyright (C) 1993 by Sun Microsystems, Inc. All rights reserved.
//! Developed at SunPro, a Sun Microsystems, Inc. business.
//! Permission to use, copy, modify, and distribute this software is freely granted, provided
//! that this notice is preserved.
//! ```

// The coefficients are copied digit for digit from `s_erf.c` so they can be checked against it.
#![allow(clippy::excessive_precision)]

const ERX: f64 = 8.45062911510467529297e-01;
// erf on [0, 0.84375].
const EFX8: f64 = 1.02703333676410069053e+00;
const PP: [f64; 5] = [
    1.28379167095512558561e-01,
    -3.25042107247001499370e-01,
    -2.84817495755985104766e-02,
    -5.77027029648944159157e-03,
    -2.37630166566501626084e-05,
];
const QQ: [f64; 5] = [
    3.97917223959155352819e-01,
    6.50222499887672944485e-02,
    5.08130628187576562776e-03,
    1.32494738004321644526e-04,
    -3.96022827877536812320e-06,
];
// erf on [0.84375, 1.25].
const PA: [f64; 7] = [
    -2.36211856075265944077e-03,
    4.14856118683748331666e-01,
    -3.72207876035701323847e-01,
    3.18346619901161753674e-01,
    -1.10894694282396677476e-01,
    3.54783043256182359371e-02,
    -2.16637559486879084300e-03,
];
const QA: [f64; 6] = [
    1.06420880400844228286e-01,
    5.40397917702171048937e-01,
    7.18286544141962662868e-02,
    1.26171219808761642112e-01,
    1.36370839120290507362e-02,
    1.19844998467991074170e-02,
];
// erfc on [1.25, 1/0.35].
const RA: [f64; 8] = [
    -9.86494403484714822705e-03,
    -6.93858572707181764372e-01,
    -1.05586262253232909814e+01,
    -6.23753324503260060396e+01,
    -1.62396669462573470355e+02,
    -1.84605092906711035994e+02,
    -8.12874355063065934246e+01,
    -9.81432934416914548592e+00,
];
const SA: [f64; 8] = [
    1.96512716674392571292e+01,
    1.37657754143519042600e+02,
    4.34565877475229228821e+02,
    6.45387271733267880336e+02,
    4.29008140027567833386e+02,
    1.08635005541779435134e+02,
    6.57024977031928170135e+00,
    -6.04244152148580987438e-02,
];
// erfc on [1/0.35, 28].
const RB: [f64; 7] = [
    -9.86494292470009928597e-03,
    -7.99283237680523006574e-01,
    -1.77579549177547519889e+01,
    -1.60636384855821916062e+02,
    -6.37566443368389627722e+02,
    -1.02509513161107724954e+03,
    -4.83519191608651397019e+02,
];
const SB: [f64; 7] = [
    3.03380607434824582924e+01,
    3.25792512996573918826e+02,
    1.53672958608443695994e+03,
    3.19985821950859553908e+03,
    2.55305040643316442583e+03,
    4.74528541206955367215e+02,
    -2.24409524465858183362e+01,
];

/// `c[0] + c[1] z + ... ` (Horner).
fn poly(c: &[f64], z: f64) -> f64 {
    c.iter().rev().fold(0.0, |acc, &k| acc * z + k)
}

/// `1 + c[0] z + c[1] z^2 + ...`.
fn poly1(c: &[f64], z: f64) -> f64 {
    1.0 + z * poly(c, z)
}

/// `erf(|x|) - ERX` for `|x|` in `[0.84375, 1.25]`.
fn erf_near_one(ax: f64) -> f64 {
    let s = ax - 1.0;
    poly(&PA, s) / poly1(&QA, s)
}

/// `erfc(|x|)` for `|x|` in `[1.25, 28)`.
fn erfc_tail(ax: f64) -> f64 {
    let z = 1.0 / (ax * ax);
    let r = if ax < 1.0 / 0.35 {
        poly(&RA, z) / poly1(&SA, z)
    } else {
        poly(&RB, z) / poly1(&SB, z)
    };
    (-ax * ax - 0.5625 + r).exp() / ax
}

/// `erf(x)`.
pub fn erf(x: f64) -> f64 {
    if x.is_nan() {
        return x;
    }
    let ax = x.abs();
    if ax < 0.84375 {
        if ax < 3.725290298461914e-9 {
            // |x| < 2^-28: avoid underflow in x^2.
            return 0.125 * (8.0 * x + EFX8 * x);
        }
        let z = x * x;
        return x + x * (poly(&PP, z) / poly1(&QQ, z));
    }
    let y = if ax < 1.25 {
        ERX + erf_near_one(ax)
    } else if ax < 6.0 {
        1.0 - erfc_tail(ax)
    } else {
        1.0
    };
    y.copysign(x)
}

/// `erfc(x) = 1 - erf(x)`, with full relative accuracy in the upper tail (down to the underflow
/// near `x = 27`).
pub fn erfc(x: f64) -> f64 {
    if x.is_nan() {
        return x;
    }
    let ax = x.abs();
    if ax < 0.84375 {
        if ax < 1.3877787807814457e-17 {
            return 1.0 - x;
        }
        let z = x * x;
        let y = poly(&PP, z) / poly1(&QQ, z);
        return if x < 0.25 {
            1.0 - (x + x * y)
        } else {
            0.5 - (x - 0.5 + x * y)
        };
    }
    let upper = if ax < 1.25 {
        1.0 - ERX - erf_near_one(ax)
    } else if ax < 28.0 {
        erfc_tail(ax)
    } else {
        0.0
    };
    if x > 0.0 { upper } else { 2.0 - upper }
}

/// Cody's `ANORM` (W. J. Cody, "Rational Chebyshev approximations for the error function",
/// Math. Comp. 23, 1969; netlib SPECFUN `anorm.f`, public domain), the same approximations as
/// the erfc ones of that paper rescaled to the standard normal: `Q(y) = exp(-y^2/2) R(y)` with
/// `R = C/D` on `[0.67, sqrt 32]` and an asymptotic `(1/sqrt(2 pi) - P/Q (1/y^2) / y^2) / y`
/// beyond.
const ANORM_C: [f64; 9] = [
    0.39894151208813466764,
    8.8831497943883759412,
    93.506656132177855979,
    597.27027639480026226,
    2494.5375852903726711,
    6848.1904505362823326,
    11602.651437647350124,
    9842.7148383839780218,
    1.0765576773720192317e-8,
];
const ANORM_D: [f64; 8] = [
    22.266688044328115691,
    235.38790178262499861,
    1519.377599407554805,
    6485.558298266760755,
    18615.571640885098091,
    34900.952721145977266,
    38912.003286093271411,
    19685.429676859990727,
];
const ANORM_P: [f64; 6] = [
    0.21589853405795699,
    0.1274011611602473639,
    0.022235277870649807,
    0.001421619193227893466,
    2.9112874951168792e-5,
    0.02307344176494017303,
];
const ANORM_Q: [f64; 5] = [
    1.28426009614491121,
    0.468238212480865118,
    0.0659881378689285515,
    0.00378239633202758244,
    7.29751555083966205e-5,
];

/// `Q(y) exp(y^2 / 2)`, the standard normal upper tail `Q` without its Gaussian factor, for
/// `y >= 0.67448975` (Cody's `ANORM` rationals, see `ANORM_C`): no exponential inside.
///
/// Why: a slit box edge needs both the tail `Q(z)` and the density `phi(z)` at the same `z`,
/// and [`erfc`]'s tail branch computes its own `exp(-z^2/2)`; with this the caller computes the
/// exponential once for both (`boxed_gaussian::Edge`), one exponential per edge instead of two.
/// Accuracy: `exp(-y^2/2) * normal_tail_scaled(y)` carries the rounding of the exponent as
/// [`erfc`] does; measured against `libm::erfc` on a dense grid (step 1/256) it is within
/// `2e-15 + 2.2e-16 y^2` relative (the test's bound: `2e-15 + 2.5e-16 y^2`): 5e-15 at `y = 5`
/// (a tail of 3e-7), 2.4e-13 at `y = 36` where the tail is 1e-283, about twice [`erfc`]'s own
/// error.
pub fn normal_tail_scaled(y: f64) -> f64 {
    const SQRT_32: f64 = 5.656854249492380195206754896838792314;
    const INV_SQRT_2PI: f64 = 0.398942280401432677939946059934381868;
    if y <= SQRT_32 {
        let mut num = ANORM_C[8] * y;
        let mut den = y;
        for i in 0..7 {
            num = (num + ANORM_C[i]) * y;
            den = (den + ANORM_D[i]) * y;
        }
        (num + ANORM_C[7]) / (den + ANORM_D[7])
    } else {
        let r = 1.0 / (y * y);
        let mut num = ANORM_P[5] * r;
        let mut den = r;
        for i in 0..4 {
            num = (num + ANORM_P[i]) * r;
            den = (den + ANORM_Q[i]) * r;
        }
        let t = r * (num + ANORM_P[4]) / (den + ANORM_Q[4]);
        (INV_SQRT_2PI - t) / y
    }
}

/// [`normal_tail_scaled`] beyond `sqrt 32` (its asymptotic branch), with one division instead
/// of three: the rational in `r = 1/y^2` is multiplied out to polynomials in `y^2` (the
/// numerator `y^2 D / sqrt(2 pi) - N` has no cancellation there: `N` is under `1/32` of the
/// other term). Not bit-identical to [`normal_tail_scaled`] (a few ulps apart), so for callers
/// whose results may move in the last bits (a likelihood scan), not the EM.
///
/// Why: the dipole baseline's extinction search standardises most box edges beyond `sqrt 32`
/// sigmas (its narrow Gaussians), and the three divisions were the costliest part of a score.
pub fn normal_tail_scaled_far(y: f64) -> f64 {
    const INV_SQRT_2PI: f64 = 0.398942280401432677939946059934381868;
    let y2 = y * y;
    // y2^5 (N(r) and D(r)) with r = 1/y2, in Horner form over y2.
    let n = ANORM_P[5]
        + y2 * (ANORM_P[0]
            + y2 * (ANORM_P[1] + y2 * (ANORM_P[2] + y2 * (ANORM_P[3] + y2 * ANORM_P[4]))));
    let d = 1.0
        + y2 * (ANORM_Q[0]
            + y2 * (ANORM_Q[1] + y2 * (ANORM_Q[2] + y2 * (ANORM_Q[3] + y2 * ANORM_Q[4]))));
    (INV_SQRT_2PI * y2 * d - n) / (y * y2 * d)
}

/// fdlibm's split of `ln 2`: `k * LN2_HI` is exact for `|k| < 2^20`.
const LN2_HI: f64 = 6.93147180369123816490e-01;
const LN2_LO: f64 = 1.90821492927058770002e-10;
/// `1.5 * 2^52`: added to a value, rounds it to an integer held in the low bits of the mantissa.
const SHIFTER: f64 = 6755399441055744.0;
/// Below this [`exp_nonpositive`] returns 0 (`exp` is below half the smallest subnormal).
const EXP_UNDERFLOW: f64 = -745.1;
/// `1 / n!` for `n` in `0..=13`: `e^r`'s Taylor series, truncated below `5e-18` for
/// `|r| <= ln 2 / 2`.
const INV_FACTORIALS: [f64; 14] = [
    1.0,
    1.0,
    1.0 / 2.0,
    1.0 / 6.0,
    1.0 / 24.0,
    1.0 / 120.0,
    1.0 / 720.0,
    1.0 / 5040.0,
    1.0 / 40320.0,
    1.0 / 362880.0,
    1.0 / 3628800.0,
    1.0 / 39916800.0,
    1.0 / 479001600.0,
    1.0 / 6227020800.0,
];

/// `exp(x)` for `x <= 0`, as straight-line code: 0 below `-745.1` (where `exp` underflows).
/// Method: `x = k ln 2 + r` with `|r| <= ln 2 / 2` (Cody and Waite's two-part `ln 2`, fused),
/// `e^r` by its Taylor series to `r^13`, times `2^k` made from its bits in two halves (so a
/// subnormal result is rounded once). Within 4 ulps of `f64::exp` where the result is normal and
/// of the smallest subnormal below (the test sweeps `[-745.2, 0]`).
///
/// Why not `f64::exp`: [`gaussian_and_tail_avx512`] evaluates the same operations eight
/// lanes at a time, and the scalar callers must get its values bit for bit (libm's `exp` is
/// neither vectorisable nor the same in its last bits).
#[inline(always)]
pub fn exp_nonpositive(x: f64) -> f64 {
    let clamped = x.max(EXP_UNDERFLOW);
    let shifted = clamped.mul_add(std::f64::consts::LOG2_E, SHIFTER);
    let k = shifted - SHIFTER;
    let r = (-k).mul_add(LN2_LO, (-k).mul_add(LN2_HI, clamped));
    let mut p = INV_FACTORIALS[13];
    for &c in INV_FACTORIALS[..13].iter().rev() {
        p = p.mul_add(r, c);
    }
    // k in [-1075, 0] from the shifted value's low bits; 2^k as 2^(k/2) 2^(k - k/2), each a
    // normal number.
    let k_int = (shifted.to_bits() as i64).wrapping_sub(SHIFTER.to_bits() as i64);
    let half = k_int >> 1;
    let first = f64::from_bits(((half + 1023) as u64) << 52);
    let second = f64::from_bits(((k_int - half + 1023) as u64) << 52);
    let value = p * first * second;
    if x < EXP_UNDERFLOW { 0.0 } else { value }
}

/// The standard normal tail `Q(|z|)` as a slit box edge takes it, given `gauss = exp(-z^2/2)`:
/// `0.5 erfc(|z| / sqrt 2)` below `scaled_from` (no exponential there), `gauss` times
/// [`normal_tail_scaled`] from it on (`scaled_from >= 0.675`, the rational's range).
#[inline]
pub fn normal_tail_given_gaussian(z: f64, gauss: f64, scaled_from: f64) -> f64 {
    let y = z.abs();
    if y < scaled_from {
        0.5 * erfc(y / std::f64::consts::SQRT_2)
    } else {
        gauss * normal_tail_scaled(y)
    }
}

/// `exp(-z^2 / 2)` (as [`exp_nonpositive`] of `-0.5 z z`) and
/// [`normal_tail_given_gaussian`]`(z, exp(-z^2 / 2), scaled_from)` of eight lanes with
/// AVX-512: the same operations as the scalar functions ([`erfc`]'s first two branches below
/// `scaled_from`, `scaled_from <= 1.25 sqrt 2`), lane by lane, so the same values bit for bit.
/// Each rational is computed only when some lane needs it.
///
/// # Safety
/// The CPU must have AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub unsafe fn gaussian_and_tail_avx512(z: &[f64; 8], scaled_from: f64) -> ([f64; 8], [f64; 8]) {
    use std::arch::x86_64::*;
    const SQRT_32: f64 = 5.656854249492380195206754896838792314;
    const INV_SQRT_2PI: f64 = 0.398942280401432677939946059934381868;
    let splat = _mm512_set1_pd;
    // SAFETY: the loads and stores are of 8 f64 from and to arrays of 8.
    let z = unsafe { _mm512_loadu_pd(z.as_ptr()) };
    let y = _mm512_abs_pd(z);
    // The Gaussian: exp_nonpositive(-0.5 * z * z).
    let x = _mm512_mul_pd(_mm512_mul_pd(splat(-0.5), z), z);
    let clamped = _mm512_max_pd(x, splat(EXP_UNDERFLOW));
    let shifted = _mm512_fmadd_pd(clamped, splat(std::f64::consts::LOG2_E), splat(SHIFTER));
    let k = _mm512_sub_pd(shifted, splat(SHIFTER));
    let r = _mm512_fnmadd_pd(
        k,
        splat(LN2_LO),
        _mm512_fnmadd_pd(k, splat(LN2_HI), clamped),
    );
    let mut p = splat(INV_FACTORIALS[13]);
    for &c in INV_FACTORIALS[..13].iter().rev() {
        p = _mm512_fmadd_pd(p, r, splat(c));
    }
    let k_int = _mm512_sub_epi64(
        _mm512_castpd_si512(shifted),
        _mm512_castpd_si512(splat(SHIFTER)),
    );
    let half = _mm512_srai_epi64::<1>(k_int);
    let bias = _mm512_set1_epi64(1023);
    let first = _mm512_castsi512_pd(_mm512_slli_epi64::<52>(_mm512_add_epi64(half, bias)));
    let second = _mm512_castsi512_pd(_mm512_slli_epi64::<52>(_mm512_add_epi64(
        _mm512_sub_epi64(k_int, half),
        bias,
    )));
    let value = _mm512_mul_pd(_mm512_mul_pd(p, first), second);
    let underflow = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(x, splat(EXP_UNDERFLOW));
    let gauss = _mm512_mask_blend_pd(underflow, value, _mm512_setzero_pd());
    // normal_tail_scaled(y): Cody's rational, then the asymptotic one where y > sqrt 32.
    let mut num = _mm512_mul_pd(splat(ANORM_C[8]), y);
    let mut den = y;
    for i in 0..7 {
        num = _mm512_mul_pd(_mm512_add_pd(num, splat(ANORM_C[i])), y);
        den = _mm512_mul_pd(_mm512_add_pd(den, splat(ANORM_D[i])), y);
    }
    let mut scaled = _mm512_div_pd(
        _mm512_add_pd(num, splat(ANORM_C[7])),
        _mm512_add_pd(den, splat(ANORM_D[7])),
    );
    let far = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(y, splat(SQRT_32));
    if far != 0 {
        let r = _mm512_div_pd(splat(1.0), _mm512_mul_pd(y, y));
        let mut num = _mm512_mul_pd(splat(ANORM_P[5]), r);
        let mut den = r;
        for i in 0..4 {
            num = _mm512_mul_pd(_mm512_add_pd(num, splat(ANORM_P[i])), r);
            den = _mm512_mul_pd(_mm512_add_pd(den, splat(ANORM_Q[i])), r);
        }
        let t = _mm512_div_pd(
            _mm512_mul_pd(r, _mm512_add_pd(num, splat(ANORM_P[4]))),
            _mm512_add_pd(den, splat(ANORM_Q[4])),
        );
        let asymptotic = _mm512_div_pd(_mm512_sub_pd(splat(INV_SQRT_2PI), t), y);
        scaled = _mm512_mask_blend_pd(far, scaled, asymptotic);
    }
    let mut tail = _mm512_mul_pd(gauss, scaled);
    let near = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(y, splat(scaled_from));
    if near != 0 {
        // SAFETY: this function's own target feature.
        let erfc =
            unsafe { erfc_below_1_25_avx512(_mm512_div_pd(y, splat(std::f64::consts::SQRT_2))) };
        tail = _mm512_mask_blend_pd(near, tail, _mm512_mul_pd(splat(0.5), erfc));
    }
    let (mut g, mut t) = ([0.0; 8], [0.0; 8]);
    // SAFETY: as the load.
    unsafe {
        _mm512_storeu_pd(g.as_mut_ptr(), gauss);
        _mm512_storeu_pd(t.as_mut_ptr(), tail);
    }
    (g, t)
}

/// [`erfc`] of lanes in `[0, 1.25)` (others: unspecified), with its operations: below 2^-56
/// `1 - x`, below 0.84375 the `PP/QQ` rational (two forms either side of 0.25), above the
/// `PA/QA` one about 1.
///
/// # Safety
/// The CPU must have AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn erfc_below_1_25_avx512(x: std::arch::x86_64::__m512d) -> std::arch::x86_64::__m512d {
    use std::arch::x86_64::*;
    let splat = _mm512_set1_pd;
    let one = splat(1.0);
    // poly and poly1 as the scalar's fold (0 z + c is c exactly).
    let rational = |num: &[f64], den: &[f64], v: __m512d| {
        let (mut n, mut d) = (splat(num[num.len() - 1]), splat(den[den.len() - 1]));
        for &c in num[..num.len() - 1].iter().rev() {
            n = _mm512_add_pd(_mm512_mul_pd(n, v), splat(c));
        }
        for &c in den[..den.len() - 1].iter().rev() {
            d = _mm512_add_pd(_mm512_mul_pd(d, v), splat(c));
        }
        _mm512_div_pd(n, _mm512_add_pd(one, _mm512_mul_pd(v, d)))
    };
    let small = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(x, splat(0.84375));
    let mut out = x;
    if small != 0 {
        let r = rational(&PP, &QQ, _mm512_mul_pd(x, x));
        let xr = _mm512_mul_pd(x, r);
        let below_quarter = _mm512_sub_pd(one, _mm512_add_pd(x, xr));
        let above_quarter =
            _mm512_sub_pd(splat(0.5), _mm512_add_pd(_mm512_sub_pd(x, splat(0.5)), xr));
        let quarter = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(x, splat(0.25));
        let tiny = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(x, splat(1.3877787807814457e-17));
        let value = _mm512_mask_blend_pd(quarter, above_quarter, below_quarter);
        let value = _mm512_mask_blend_pd(tiny, value, _mm512_sub_pd(one, x));
        out = _mm512_mask_blend_pd(small, out, value);
    }
    if small != 0xff {
        let r = rational(&PA, &QA, _mm512_sub_pd(x, one));
        out = _mm512_mask_blend_pd(small, _mm512_sub_pd(splat(1.0 - ERX), r), out);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Relative difference, with an absolute floor for values near zero.
    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs().max(1e-300)
    }

    /// The tail's error bound: a few ulps (FreeBSD's and ours) plus the rounding of the
    /// exponent `-x^2 - 0.5625 + R/S` in one `exp`.
    fn tail_bound(x: f64) -> f64 {
        1e-15 + x * x * 2.5e-16
    }

    #[test]
    fn erfc_matches_libm_on_a_dense_grid_to_its_error_bound() {
        let mut x = -8.0;
        while x < 27.0 {
            let (ours, reference) = (erfc(x), libm::erfc(x));
            assert!(
                rel(ours, reference) <= tail_bound(x),
                "erfc({x}) = {ours}, libm {reference}"
            );
            x += 1.0 / 512.0 + 1e-7;
        }
    }

    #[test]
    fn far_scaled_tail_matches_the_three_division_form_and_libm() {
        let mut y: f64 = 5.657;
        while y < 39.0 {
            let (fast, reference) = (normal_tail_scaled_far(y), normal_tail_scaled(y));
            assert!(rel(fast, reference) <= 2e-15, "{y}: {fast} vs {reference}");
            let q = (-0.5 * y * y).exp() * fast;
            let libm_q = 0.5 * libm::erfc(y / std::f64::consts::SQRT_2);
            if libm_q > 0.0 {
                assert!(
                    rel(q, libm_q) <= 2e-15 + 2.5e-16 * y * y,
                    "Q({y}) = {q} vs {libm_q}"
                );
            }
            y += 1.0 / 256.0 + 1e-7;
        }
    }

    #[test]
    fn scaled_normal_tail_times_its_gaussian_matches_libm_erfc() {
        let mut y: f64 = 0.675;
        while y < 38.0 {
            let ours = (-0.5 * y * y).exp() * normal_tail_scaled(y);
            let reference = 0.5 * libm::erfc(y / std::f64::consts::SQRT_2);
            let err = rel(ours, reference);
            assert!(
                err <= 2e-15 + 2.5e-16 * y * y,
                "Q({y}) = {ours}, libm {reference}, relative error {err}"
            );
            y += 1.0 / 256.0 + 1e-7;
        }
    }

    #[test]
    fn exp_nonpositive_is_within_4_ulps_of_exp_and_underflows_as_it() {
        let ulp = |v: f64| f64::from_bits(v.to_bits() + 1) - v;
        let mut x = 0.0;
        while x > -745.2 {
            let (ours, reference) = (exp_nonpositive(x), x.exp());
            let bound = if reference >= f64::MIN_POSITIVE {
                4.0 * ulp(reference)
            } else {
                // Subnormal results: one rounding at the smallest subnormal.
                f64::from_bits(1)
            };
            assert!(
                (ours - reference).abs() <= bound,
                "exp({x}) = {ours}, std {reference}"
            );
            x -= 1.0 / 256.0 + 1e-9;
        }
        for x in [-745.2, -746.0, -800.0, -1e300, f64::NEG_INFINITY] {
            assert_eq!(exp_nonpositive(x), 0.0, "{x}");
        }
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert_eq!(exp_nonpositive(-0.0), 1.0);
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_lanes_are_the_scalar_functions_bit_for_bit() {
        if !std::arch::is_x86_feature_detected!("avx512f") {
            eprintln!("no AVX-512 here: the vector lanes are not exercised");
            return;
        }
        let from = 1.25 * std::f64::consts::SQRT_2;
        let mut z: f64 = -40.0;
        while z < 40.0 {
            // Lanes on both sides of every branch together (0.25 and 0.84375 in erfc's
            // argument, the switch to the scaled tail, sqrt 32, the underflow), and alone.
            let lanes = [z, -z, z + 3.0, z - 3.0, z * 0.1, 5.6568, 38.7, 1e-18 * z];
            for batch in [lanes, [z; 8], [z * 0.05; 8]] {
                // SAFETY: AVX-512F is present (checked above).
                let (g, t) = unsafe { gaussian_and_tail_avx512(&batch, from) };
                for (l, &zl) in batch.iter().enumerate() {
                    let gauss = exp_nonpositive(-0.5 * zl * zl);
                    assert_eq!(g[l].to_bits(), gauss.to_bits(), "{zl}");
                    if zl.abs() < 38.6 {
                        let tail = normal_tail_given_gaussian(zl, gauss, from);
                        assert_eq!(t[l].to_bits(), tail.to_bits(), "{zl}");
                    }
                }
            }
            z += 1.0 / 64.0 + 1e-7;
        }
    }

    #[test]
    fn erf_matches_libm_on_a_dense_grid() {
        let mut x = -8.0;
        while x < 8.0 {
            let (ours, reference) = (erf(x), libm::erf(x));
            assert!(
                (ours - reference).abs() <= 4e-16,
                "erf({x}) = {ours}, libm {reference}"
            );
            x += 1.0 / 512.0 + 1e-7;
        }
    }

    #[test]
    fn hand_values_and_edge_cases() {
        // erfc(1) and erfc(5) to 16 digits (Abramowitz & Stegun, table 7.1 extended).
        assert!(rel(erfc(1.0), 0.157_299_207_050_285_13) < 1e-15);
        assert!(rel(erfc(5.0), 1.537_459_794_428_034_8e-12) < 1e-14);
        assert_eq!(erfc(0.0), 1.0);
        assert_eq!(erf(0.0), 0.0);
        assert_eq!(erfc(f64::INFINITY), 0.0);
        assert_eq!(erfc(f64::NEG_INFINITY), 2.0);
        assert_eq!(erf(f64::NEG_INFINITY), -1.0);
        assert!(erfc(f64::NAN).is_nan() && erf(f64::NAN).is_nan());
        assert_eq!(erfc(40.0), 0.0);
        assert_eq!(erfc(-40.0), 2.0);
    }

    proptest! {
        #[test]
        fn erfc_agrees_with_libm_anywhere(x in -30.0f64..30.0) {
            let (ours, reference) = (erfc(x), libm::erfc(x));
            prop_assert!(rel(ours, reference) <= tail_bound(x) || (ours == 0.0 && reference < 1e-300),
                "erfc({}) = {}, libm {}", x, ours, reference);
        }

        #[test]
        fn erf_is_odd_and_agrees_with_libm(x in -10.0f64..10.0) {
            prop_assert_eq!(erf(-x), -erf(x));
            prop_assert!((erf(x) - libm::erf(x)).abs() <= 4e-16);
        }
    }
}

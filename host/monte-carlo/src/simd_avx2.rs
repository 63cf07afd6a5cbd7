//! The lane vectors of `simd` written with AVX2 intrinsics: `LANES` = 8 f64 as two 256-bit
//! registers.
//!
//! The compiler does not reliably turn the array version into full-width vector code (it stops at
//! pairs), so the photon step is compiled a second time against these types (see
//! `photon_lanes::avx2`). Same API, same IEEE operations, bit-identical results.
//!
//! Soundness: the operations call AVX/AVX2 intrinsics without checking the CPU. Values of these
//! types are only created inside `photon_lanes::avx2`, whose single entry point is a
//! `#[target_feature(enable = "avx2")]` function called after `is_x86_feature_detected!("avx2")`.

use std::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Shl, Shr, Sub};

use super::simd::LANES;

const _: () = assert!(LANES == 8, "two 4-lane AVX registers hold exactly 8 lanes");

/// 8 f64 in two AVX registers.
#[derive(Clone, Copy)]
pub(crate) struct F64s([__m256d; 2]);

/// 8 u64 (or lane masks: all ones / zero) in two AVX registers.
#[derive(Clone, Copy)]
pub(crate) struct U64s([__m256i; 2]);

macro_rules! both {
    ($ty:ident, $f:ident, $a:expr, $b:expr) => {
        // SAFETY: see the module documentation (only reached with AVX2 enabled and detected).
        unsafe { $ty([$f($a.0[0], $b.0[0]), $f($a.0[1], $b.0[1])]) }
    };
}

macro_rules! binary_op {
    ($ty:ident, $trait:ident, $method:ident, $intrinsic:ident) => {
        impl $trait for $ty {
            type Output = $ty;
            #[inline(always)]
            fn $method(self, rhs: $ty) -> $ty {
                both!($ty, $intrinsic, self, rhs)
            }
        }
    };
}

binary_op!(F64s, Add, add, _mm256_add_pd);
binary_op!(F64s, Sub, sub, _mm256_sub_pd);
binary_op!(F64s, Mul, mul, _mm256_mul_pd);
binary_op!(F64s, Div, div, _mm256_div_pd);
binary_op!(U64s, BitAnd, bitand, _mm256_and_si256);
binary_op!(U64s, BitOr, bitor, _mm256_or_si256);
binary_op!(U64s, BitXor, bitxor, _mm256_xor_si256);

const SIGN: u64 = 0x8000_0000_0000_0000;

impl Neg for F64s {
    type Output = F64s;
    #[inline(always)]
    fn neg(self) -> F64s {
        (self.to_bits() ^ U64s::splat(SIGN)).as_f64_bits()
    }
}

impl Not for U64s {
    type Output = U64s;
    #[inline(always)]
    fn not(self) -> U64s {
        self ^ U64s::splat(u64::MAX)
    }
}

impl Shl<u32> for U64s {
    type Output = U64s;
    #[inline(always)]
    fn shl(self, n: u32) -> U64s {
        // SAFETY: see the module documentation.
        unsafe {
            let count = _mm_cvtsi32_si128(n as i32);
            U64s([
                _mm256_sll_epi64(self.0[0], count),
                _mm256_sll_epi64(self.0[1], count),
            ])
        }
    }
}

impl Shr<u32> for U64s {
    type Output = U64s;
    #[inline(always)]
    fn shr(self, n: u32) -> U64s {
        // SAFETY: see the module documentation.
        unsafe {
            let count = _mm_cvtsi32_si128(n as i32);
            U64s([
                _mm256_srl_epi64(self.0[0], count),
                _mm256_srl_epi64(self.0[1], count),
            ])
        }
    }
}

impl F64s {
    #[inline(always)]
    pub(crate) fn splat(x: f64) -> Self {
        // SAFETY: see the module documentation.
        unsafe { Self([_mm256_set1_pd(x); 2]) }
    }

    #[inline(always)]
    pub(crate) fn load(values: [f64; LANES]) -> Self {
        // SAFETY: see the module documentation; the pointers cover 4 + 4 f64 of `values`.
        unsafe {
            Self([
                _mm256_loadu_pd(values.as_ptr()),
                _mm256_loadu_pd(values.as_ptr().add(4)),
            ])
        }
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f64; LANES] {
        let mut out = [0.0; LANES];
        // SAFETY: see the module documentation; the pointers cover 4 + 4 f64 of `out`.
        unsafe {
            _mm256_storeu_pd(out.as_mut_ptr(), self.0[0]);
            _mm256_storeu_pd(out.as_mut_ptr().add(4), self.0[1]);
        }
        out
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        // SAFETY: see the module documentation.
        unsafe { Self([_mm256_sqrt_pd(self.0[0]), _mm256_sqrt_pd(self.0[1])]) }
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        (self.to_bits() & U64s::splat(!SIGN)).as_f64_bits()
    }

    /// Lane-wise `if self > other { self } else { other }` (the array version's NaN behaviour).
    #[inline(always)]
    pub(crate) fn max(self, other: Self) -> Self {
        self.gt(other).select(self, other)
    }

    /// Lane-wise `if self < other { self } else { other }`.
    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        self.lt(other).select(self, other)
    }

    #[inline(always)]
    pub(crate) fn lt(self, other: Self) -> U64s {
        self.compare::<_CMP_LT_OQ>(other)
    }

    #[inline(always)]
    pub(crate) fn gt(self, other: Self) -> U64s {
        self.compare::<_CMP_GT_OQ>(other)
    }

    #[inline(always)]
    pub(crate) fn eq(self, other: Self) -> U64s {
        self.compare::<_CMP_EQ_OQ>(other)
    }

    #[inline(always)]
    fn compare<const PREDICATE: i32>(self, other: Self) -> U64s {
        // SAFETY: see the module documentation.
        unsafe {
            U64s([
                _mm256_castpd_si256(_mm256_cmp_pd::<PREDICATE>(self.0[0], other.0[0])),
                _mm256_castpd_si256(_mm256_cmp_pd::<PREDICATE>(self.0[1], other.0[1])),
            ])
        }
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U64s {
        // SAFETY: see the module documentation.
        unsafe {
            U64s([
                _mm256_castpd_si256(self.0[0]),
                _mm256_castpd_si256(self.0[1]),
            ])
        }
    }
}

impl U64s {
    #[inline(always)]
    pub(crate) fn splat(x: u64) -> Self {
        // SAFETY: see the module documentation.
        unsafe { Self([_mm256_set1_epi64x(x as i64); 2]) }
    }

    #[inline(always)]
    pub(crate) fn load(values: [u64; LANES]) -> Self {
        // SAFETY: see the module documentation; the pointers cover 4 + 4 u64 of `values`.
        unsafe {
            let p = values.as_ptr().cast::<__m256i>();
            Self([_mm256_loadu_si256(p), _mm256_loadu_si256(p.add(1))])
        }
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u64; LANES] {
        let mut out = [0u64; LANES];
        // SAFETY: see the module documentation; the pointers cover 4 + 4 u64 of `out`.
        unsafe {
            let p = out.as_mut_ptr().cast::<__m256i>();
            _mm256_storeu_si256(p, self.0[0]);
            _mm256_storeu_si256(p.add(1), self.0[1]);
        }
        out
    }

    #[inline(always)]
    pub(crate) fn wrapping_add(self, other: Self) -> Self {
        both!(U64s, _mm256_add_epi64, self, other)
    }

    #[inline(always)]
    pub(crate) fn rotate_left(self, n: u32) -> Self {
        (self << n) | (self >> (64 - n))
    }

    #[inline(always)]
    pub(crate) fn as_f64_bits(self) -> F64s {
        // SAFETY: see the module documentation.
        unsafe {
            F64s([
                _mm256_castsi256_pd(self.0[0]),
                _mm256_castsi256_pd(self.0[1]),
            ])
        }
    }

    #[inline(always)]
    pub(crate) fn eq_u64(self, other: Self) -> U64s {
        both!(U64s, _mm256_cmpeq_epi64, self, other)
    }

    /// As a mask: `a` where set, `b` elsewhere (bitwise, so exact for any value).
    #[inline(always)]
    pub(crate) fn select(self, a: F64s, b: F64s) -> F64s {
        ((self & a.to_bits()) | (!self & b.to_bits())).as_f64_bits()
    }

    /// As a mask: one bit per lane, lane 0 in bit 0.
    #[inline(always)]
    pub(crate) fn bitmask(self) -> u32 {
        // SAFETY: see the module documentation.
        unsafe {
            let low = _mm256_movemask_pd(_mm256_castsi256_pd(self.0[0])) as u32;
            let high = _mm256_movemask_pd(_mm256_castsi256_pd(self.0[1])) as u32;
            low | (high << 4)
        }
    }
}

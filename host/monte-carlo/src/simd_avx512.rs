//! The lane vectors of `simd` as one AVX-512 register: `LANES` = 8 f64 in a `__m512d`.
//!
//! Same API and the same IEEE operations as the array and AVX2 versions (bit-identical results);
//! half the instructions of the AVX2 version. Masks are kept as vectors (all ones / zero per lane)
//! like the other versions; the compiler folds the conversions to and from mask registers.
//!
//! Soundness: the operations call AVX-512 intrinsics without checking the CPU. Values of these
//! types are only created inside `photon_lanes::avx512`, whose single entry point is a
//! `#[target_feature(enable = "avx512f")]` function called after `is_x86_feature_detected!`.

use std::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Shl, Shr, Sub};

use super::simd::LANES;

const _: () = assert!(LANES == 8, "one AVX-512 register holds exactly 8 f64");

/// 8 f64 in one AVX-512 register.
#[derive(Clone, Copy)]
pub(crate) struct F64s(__m512d);

/// 8 u64 (or lane masks: all ones / zero) in one AVX-512 register.
#[derive(Clone, Copy)]
pub(crate) struct U64s(__m512i);

macro_rules! binary_op {
    ($ty:ident, $trait:ident, $method:ident, $intrinsic:ident) => {
        impl $trait for $ty {
            type Output = $ty;
            #[inline(always)]
            fn $method(self, rhs: $ty) -> $ty {
                // SAFETY: see the module documentation.
                $ty(unsafe { $intrinsic(self.0, rhs.0) })
            }
        }
    };
}

binary_op!(F64s, Add, add, _mm512_add_pd);
binary_op!(F64s, Sub, sub, _mm512_sub_pd);
binary_op!(F64s, Mul, mul, _mm512_mul_pd);
binary_op!(F64s, Div, div, _mm512_div_pd);
binary_op!(U64s, BitAnd, bitand, _mm512_and_si512);
binary_op!(U64s, BitOr, bitor, _mm512_or_si512);
binary_op!(U64s, BitXor, bitxor, _mm512_xor_si512);

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
        U64s(unsafe { _mm512_sll_epi64(self.0, _mm_cvtsi32_si128(n as i32)) })
    }
}

impl Shr<u32> for U64s {
    type Output = U64s;
    #[inline(always)]
    fn shr(self, n: u32) -> U64s {
        // SAFETY: see the module documentation.
        U64s(unsafe { _mm512_srl_epi64(self.0, _mm_cvtsi32_si128(n as i32)) })
    }
}

impl F64s {
    #[inline(always)]
    pub(crate) fn splat(x: f64) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_set1_pd(x) })
    }

    #[inline(always)]
    pub(crate) fn load(values: [f64; LANES]) -> Self {
        // SAFETY: see the module documentation; the load covers exactly `values`.
        Self(unsafe { _mm512_loadu_pd(values.as_ptr()) })
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f64; LANES] {
        let mut out = [0.0; LANES];
        // SAFETY: see the module documentation; the store covers exactly `out`.
        unsafe { _mm512_storeu_pd(out.as_mut_ptr(), self.0) };
        out
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_sqrt_pd(self.0) })
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        (self.to_bits() & U64s::splat(!SIGN)).as_f64_bits()
    }

    /// Lane-wise `if self > other { self } else { other }` (`vmaxpd`, NaN included).
    #[inline(always)]
    pub(crate) fn max(self, other: Self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_max_pd(self.0, other.0) })
    }

    /// Lane-wise `if self < other { self } else { other }` (`vminpd`).
    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_min_pd(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn lt(self, other: Self) -> U64s {
        // SAFETY: see the module documentation.
        U64s::from_mask(unsafe { _mm512_cmp_pd_mask::<_CMP_LT_OQ>(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn gt(self, other: Self) -> U64s {
        // SAFETY: see the module documentation.
        U64s::from_mask(unsafe { _mm512_cmp_pd_mask::<_CMP_GT_OQ>(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn eq(self, other: Self) -> U64s {
        // SAFETY: see the module documentation.
        U64s::from_mask(unsafe { _mm512_cmp_pd_mask::<_CMP_EQ_OQ>(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U64s {
        // SAFETY: see the module documentation.
        U64s(unsafe { _mm512_castpd_si512(self.0) })
    }
}

impl U64s {
    #[inline(always)]
    pub(crate) fn splat(x: u64) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_set1_epi64(x as i64) })
    }

    #[inline(always)]
    fn from_mask(mask: __mmask8) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_maskz_mov_epi64(mask, _mm512_set1_epi64(-1)) })
    }

    #[inline(always)]
    fn to_mask(self) -> __mmask8 {
        // SAFETY: see the module documentation.
        unsafe { _mm512_test_epi64_mask(self.0, self.0) }
    }

    #[inline(always)]
    pub(crate) fn load(values: [u64; LANES]) -> Self {
        // SAFETY: see the module documentation; the load covers exactly `values`.
        Self(unsafe { _mm512_loadu_si512(values.as_ptr().cast()) })
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u64; LANES] {
        let mut out = [0u64; LANES];
        // SAFETY: see the module documentation; the store covers exactly `out`.
        unsafe { _mm512_storeu_si512(out.as_mut_ptr().cast(), self.0) };
        out
    }

    #[inline(always)]
    pub(crate) fn wrapping_add(self, other: Self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_add_epi64(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn rotate_left(self, n: u32) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_rolv_epi64(self.0, _mm512_set1_epi64(i64::from(n))) })
    }

    #[inline(always)]
    pub(crate) fn as_f64_bits(self) -> F64s {
        // SAFETY: see the module documentation.
        F64s(unsafe { _mm512_castsi512_pd(self.0) })
    }

    #[inline(always)]
    pub(crate) fn eq_u64(self, other: Self) -> U64s {
        // SAFETY: see the module documentation.
        U64s::from_mask(unsafe { _mm512_cmpeq_epi64_mask(self.0, other.0) })
    }

    /// As a mask: `a` where set, `b` elsewhere (masks are all ones or zero per lane).
    #[inline(always)]
    pub(crate) fn select(self, a: F64s, b: F64s) -> F64s {
        // SAFETY: see the module documentation.
        F64s(unsafe { _mm512_mask_blend_pd(self.to_mask(), b.0, a.0) })
    }

    /// As a mask: one bit per lane, lane 0 in bit 0.
    #[inline(always)]
    pub(crate) fn bitmask(self) -> u32 {
        u32::from(self.to_mask())
    }
}

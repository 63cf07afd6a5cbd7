//! The lane vectors of `simd` as one AVX-512 register: `LANES` = 16 f32 in a `__m512`.
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

const _: () = assert!(LANES == 16, "one AVX-512 register holds exactly 16 f32");

/// 16 f32 in one AVX-512 register.
#[derive(Clone, Copy)]
pub(crate) struct F32s(__m512);

/// 16 u32 (or lane masks: all ones / zero) in one AVX-512 register.
#[derive(Clone, Copy)]
pub(crate) struct U32s(__m512i);

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

binary_op!(F32s, Add, add, _mm512_add_ps);
binary_op!(F32s, Sub, sub, _mm512_sub_ps);
binary_op!(F32s, Mul, mul, _mm512_mul_ps);
binary_op!(F32s, Div, div, _mm512_div_ps);
binary_op!(U32s, BitAnd, bitand, _mm512_and_si512);
binary_op!(U32s, BitOr, bitor, _mm512_or_si512);
binary_op!(U32s, BitXor, bitxor, _mm512_xor_si512);

const SIGN: u32 = 0x8000_0000;

impl Neg for F32s {
    type Output = F32s;
    #[inline(always)]
    fn neg(self) -> F32s {
        (self.to_bits() ^ U32s::splat(SIGN)).as_f32_bits()
    }
}

impl Not for U32s {
    type Output = U32s;
    #[inline(always)]
    fn not(self) -> U32s {
        self ^ U32s::splat(u32::MAX)
    }
}

impl Shl<u32> for U32s {
    type Output = U32s;
    #[inline(always)]
    fn shl(self, n: u32) -> U32s {
        // SAFETY: see the module documentation.
        U32s(unsafe { _mm512_sll_epi32(self.0, _mm_cvtsi32_si128(n as i32)) })
    }
}

impl Shr<u32> for U32s {
    type Output = U32s;
    #[inline(always)]
    fn shr(self, n: u32) -> U32s {
        // SAFETY: see the module documentation.
        U32s(unsafe { _mm512_srl_epi32(self.0, _mm_cvtsi32_si128(n as i32)) })
    }
}

impl F32s {
    #[inline(always)]
    pub(crate) fn splat(x: f32) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_set1_ps(x) })
    }

    #[inline(always)]
    pub(crate) fn load(values: [f32; LANES]) -> Self {
        // SAFETY: see the module documentation; the load covers exactly `values`.
        Self(unsafe { _mm512_loadu_ps(values.as_ptr()) })
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f32; LANES] {
        let mut out = [0.0f32; LANES];
        // SAFETY: see the module documentation; the store covers exactly `out`.
        unsafe { _mm512_storeu_ps(out.as_mut_ptr(), self.0) };
        out
    }

    /// `self * a + b` with one rounding.
    #[inline(always)]
    pub(crate) fn mul_add(self, a: Self, b: Self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_fmadd_ps(self.0, a.0, b.0) })
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_sqrt_ps(self.0) })
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        (self.to_bits() & U32s::splat(!SIGN)).as_f32_bits()
    }

    /// Lane-wise `if self < other { self } else { other }` (`vminps`).
    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_min_ps(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn lt(self, other: Self) -> U32s {
        // SAFETY: see the module documentation.
        U32s::from_mask(unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn gt(self, other: Self) -> U32s {
        // SAFETY: see the module documentation.
        U32s::from_mask(unsafe { _mm512_cmp_ps_mask::<_CMP_GT_OQ>(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn eq(self, other: Self) -> U32s {
        // SAFETY: see the module documentation.
        U32s::from_mask(unsafe { _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U32s {
        // SAFETY: see the module documentation.
        U32s(unsafe { _mm512_castps_si512(self.0) })
    }
}

impl U32s {
    #[inline(always)]
    pub(crate) fn splat(x: u32) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_set1_epi32(x as i32) })
    }

    #[inline(always)]
    fn from_mask(mask: __mmask16) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_maskz_mov_epi32(mask, _mm512_set1_epi32(-1)) })
    }

    #[inline(always)]
    fn to_mask(self) -> __mmask16 {
        // SAFETY: see the module documentation.
        unsafe { _mm512_test_epi32_mask(self.0, self.0) }
    }

    #[inline(always)]
    pub(crate) fn load(values: [u32; LANES]) -> Self {
        // SAFETY: see the module documentation; the load covers exactly `values`.
        Self(unsafe { _mm512_loadu_si512(values.as_ptr().cast()) })
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u32; LANES] {
        let mut out = [0u32; LANES];
        // SAFETY: see the module documentation; the store covers exactly `out`.
        unsafe { _mm512_storeu_si512(out.as_mut_ptr().cast(), self.0) };
        out
    }

    #[inline(always)]
    pub(crate) fn wrapping_add(self, other: Self) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_add_epi32(self.0, other.0) })
    }

    #[inline(always)]
    pub(crate) fn rotate_left(self, n: u32) -> Self {
        // SAFETY: see the module documentation.
        Self(unsafe { _mm512_rolv_epi32(self.0, _mm512_set1_epi32(n as i32)) })
    }

    #[inline(always)]
    pub(crate) fn as_f32_bits(self) -> F32s {
        // SAFETY: see the module documentation.
        F32s(unsafe { _mm512_castsi512_ps(self.0) })
    }

    #[inline(always)]
    pub(crate) fn eq_u32(self, other: Self) -> U32s {
        // SAFETY: see the module documentation.
        U32s::from_mask(unsafe { _mm512_cmpeq_epi32_mask(self.0, other.0) })
    }

    /// Each lane read as an i32 and rounded to the nearest f32 (`vcvtdq2ps`).
    #[inline(always)]
    pub(crate) fn signed_to_f32(self) -> F32s {
        // SAFETY: see the module documentation.
        F32s(unsafe { _mm512_cvtepi32_ps(self.0) })
    }

    /// As a mask: `a` where set, `b` elsewhere (masks are all ones or zero per lane).
    #[inline(always)]
    pub(crate) fn select(self, a: F32s, b: F32s) -> F32s {
        // SAFETY: see the module documentation.
        F32s(unsafe { _mm512_mask_blend_ps(self.to_mask(), b.0, a.0) })
    }

    /// As a mask: one bit per lane, lane 0 in bit 0.
    #[inline(always)]
    pub(crate) fn bitmask(self) -> u32 {
        u32::from(self.to_mask())
    }
}

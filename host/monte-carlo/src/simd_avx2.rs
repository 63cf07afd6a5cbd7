//! The lane vectors of `simd` written with AVX2 intrinsics: `LANES` f32 in 256-bit registers.
//!
//! The compiler does not reliably turn the array version into full-width vector code (it stops at
//! pairs), so the photon step is compiled a second time against these types (see
//! `photon_lanes::avx2`). Same API, same IEEE operations, bit-identical results.
//!
//! Soundness: the operations call AVX/AVX2/FMA intrinsics without checking the CPU. Values of these
//! types are only created inside `photon_lanes::avx2`, whose single entry point is a
//! `#[target_feature(enable = "avx2,fma")]` function called after `is_x86_feature_detected!` found both.

use std::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Shl, Shr, Sub};

use super::simd::LANES;

/// AVX registers per lane vector (8 f32 each).
const REGS: usize = LANES / 8;
const _: () = assert!(
    LANES.is_multiple_of(8),
    "the lanes must fill whole 8-lane AVX registers"
);

/// `LANES` f32 in AVX registers.
#[derive(Clone, Copy)]
pub(crate) struct F32s([__m256; REGS]);

/// `LANES` u32 (or lane masks: all ones / zero) in AVX registers.
#[derive(Clone, Copy)]
pub(crate) struct U32s([__m256i; REGS]);

/// Applies an intrinsic register by register. A plain loop, not `array::map` with a closure: a
/// closure defined here would not have AVX2 and the intrinsics would not inline.
macro_rules! per_register {
    ($ty:ident, $f:ident, $($arg:expr),+) => {{
        let mut out = $ty::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation (only reached with AVX2 enabled and detected).
            out.0[r] = unsafe { $f($($arg.0[r]),+) };
        }
        out
    }};
}

macro_rules! binary_op {
    ($ty:ident, $trait:ident, $method:ident, $intrinsic:ident) => {
        impl $trait for $ty {
            type Output = $ty;
            #[inline(always)]
            fn $method(self, rhs: $ty) -> $ty {
                per_register!($ty, $intrinsic, self, rhs)
            }
        }
    };
}

binary_op!(F32s, Add, add, _mm256_add_ps);
binary_op!(F32s, Sub, sub, _mm256_sub_ps);
binary_op!(F32s, Mul, mul, _mm256_mul_ps);
binary_op!(F32s, Div, div, _mm256_div_ps);
binary_op!(U32s, BitAnd, bitand, _mm256_and_si256);
binary_op!(U32s, BitOr, bitor, _mm256_or_si256);
binary_op!(U32s, BitXor, bitxor, _mm256_xor_si256);

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
        let count = unsafe { _mm_cvtsi32_si128(n as i32) };
        let mut out = U32s::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            out.0[r] = unsafe { _mm256_sll_epi32(self.0[r], count) };
        }
        out
    }
}

impl Shr<u32> for U32s {
    type Output = U32s;
    #[inline(always)]
    fn shr(self, n: u32) -> U32s {
        // SAFETY: see the module documentation.
        let count = unsafe { _mm_cvtsi32_si128(n as i32) };
        let mut out = U32s::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            out.0[r] = unsafe { _mm256_srl_epi32(self.0[r], count) };
        }
        out
    }
}

impl F32s {
    #[inline(always)]
    fn zeroed() -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_setzero_ps() }; REGS])
    }

    #[inline(always)]
    pub(crate) fn splat(x: f32) -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_set1_ps(x) }; REGS])
    }

    #[inline(always)]
    pub(crate) fn load(values: [f32; LANES]) -> Self {
        let mut out = Self::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation; 8 r + 8 <= LANES.
            out.0[r] = unsafe { _mm256_loadu_ps(values.as_ptr().add(8 * r)) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f32; LANES] {
        let mut out = [0.0f32; LANES];
        for r in 0..REGS {
            // SAFETY: see the module documentation; 8 r + 8 <= LANES.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(8 * r), self.0[r]) };
        }
        out
    }

    /// `self * a + b` with one rounding (FMA3).
    #[inline(always)]
    pub(crate) fn mul_add(self, a: Self, b: Self) -> Self {
        per_register!(F32s, _mm256_fmadd_ps, self, a, b)
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        per_register!(F32s, _mm256_sqrt_ps, self)
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        (self.to_bits() & U32s::splat(!SIGN)).as_f32_bits()
    }

    /// Lane-wise `if self < other { self } else { other }` (`vminps`).
    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        per_register!(F32s, _mm256_min_ps, self, other)
    }

    #[inline(always)]
    pub(crate) fn lt(self, other: Self) -> U32s {
        self.compare::<_CMP_LT_OQ>(other)
    }

    #[inline(always)]
    pub(crate) fn gt(self, other: Self) -> U32s {
        self.compare::<_CMP_GT_OQ>(other)
    }

    #[inline(always)]
    pub(crate) fn eq(self, other: Self) -> U32s {
        self.compare::<_CMP_EQ_OQ>(other)
    }

    #[inline(always)]
    fn compare<const PREDICATE: i32>(self, other: Self) -> U32s {
        let mut out = U32s::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            out.0[r] =
                unsafe { _mm256_castps_si256(_mm256_cmp_ps::<PREDICATE>(self.0[r], other.0[r])) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U32s {
        per_register!(U32s, _mm256_castps_si256, self)
    }
}

impl U32s {
    #[inline(always)]
    fn zeroed() -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_setzero_si256() }; REGS])
    }

    #[inline(always)]
    pub(crate) fn splat(x: u32) -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_set1_epi32(x as i32) }; REGS])
    }

    #[inline(always)]
    pub(crate) fn load(values: [u32; LANES]) -> Self {
        let mut out = Self::zeroed();
        let p = values.as_ptr().cast::<__m256i>();
        for r in 0..REGS {
            // SAFETY: see the module documentation; register r covers u32 8 r .. 8 r + 8.
            out.0[r] = unsafe { _mm256_loadu_si256(p.add(r)) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u32; LANES] {
        let mut out = [0u32; LANES];
        let p = out.as_mut_ptr().cast::<__m256i>();
        for r in 0..REGS {
            // SAFETY: see the module documentation; register r covers u32 8 r .. 8 r + 8.
            unsafe { _mm256_storeu_si256(p.add(r), self.0[r]) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn wrapping_add(self, other: Self) -> Self {
        per_register!(U32s, _mm256_add_epi32, self, other)
    }

    #[inline(always)]
    pub(crate) fn rotate_left(self, n: u32) -> Self {
        (self << n) | (self >> (32 - n))
    }

    #[inline(always)]
    pub(crate) fn as_f32_bits(self) -> F32s {
        per_register!(F32s, _mm256_castsi256_ps, self)
    }

    #[inline(always)]
    pub(crate) fn eq_u32(self, other: Self) -> U32s {
        per_register!(U32s, _mm256_cmpeq_epi32, self, other)
    }

    /// Each lane read as an i32 and rounded to the nearest f32 (`vcvtdq2ps`).
    #[inline(always)]
    pub(crate) fn signed_to_f32(self) -> F32s {
        per_register!(F32s, _mm256_cvtepi32_ps, self)
    }

    /// As a mask: `a` where set, `b` elsewhere. One `vblendvps` per register; it looks at the
    /// sign bit only, which for an all-ones / zero mask is the same choice.
    #[inline(always)]
    pub(crate) fn select(self, a: F32s, b: F32s) -> F32s {
        let mask = self.as_f32_bits();
        per_register!(F32s, _mm256_blendv_ps, b, a, mask)
    }

    /// As a mask: one bit per lane, lane 0 in bit 0.
    #[inline(always)]
    pub(crate) fn bitmask(self) -> u32 {
        let mut bits = 0;
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            let eight = unsafe { _mm256_movemask_ps(_mm256_castsi256_ps(self.0[r])) } as u32;
            bits |= eight << (8 * r);
        }
        bits
    }
}

//! The lane vectors of `simd` written with AVX2 intrinsics: `LANES` f64 in 256-bit registers.
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

/// AVX registers per lane vector (4 f64 each).
const REGS: usize = LANES / 4;
const _: () = assert!(
    LANES.is_multiple_of(4),
    "the lanes must fill whole 4-lane AVX registers"
);

/// `LANES` f64 in AVX registers.
#[derive(Clone, Copy)]
pub(crate) struct F64s([__m256d; REGS]);

/// `LANES` u64 (or lane masks: all ones / zero) in AVX registers.
#[derive(Clone, Copy)]
pub(crate) struct U64s([__m256i; REGS]);

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
        let count = unsafe { _mm_cvtsi32_si128(n as i32) };
        let mut out = U64s::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            out.0[r] = unsafe { _mm256_sll_epi64(self.0[r], count) };
        }
        out
    }
}

impl Shr<u32> for U64s {
    type Output = U64s;
    #[inline(always)]
    fn shr(self, n: u32) -> U64s {
        // SAFETY: see the module documentation.
        let count = unsafe { _mm_cvtsi32_si128(n as i32) };
        let mut out = U64s::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            out.0[r] = unsafe { _mm256_srl_epi64(self.0[r], count) };
        }
        out
    }
}

impl F64s {
    #[inline(always)]
    fn zeroed() -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_setzero_pd() }; REGS])
    }

    #[inline(always)]
    pub(crate) fn splat(x: f64) -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_set1_pd(x) }; REGS])
    }

    #[inline(always)]
    pub(crate) fn load(values: [f64; LANES]) -> Self {
        let mut out = Self::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation; 4 r + 4 <= LANES.
            out.0[r] = unsafe { _mm256_loadu_pd(values.as_ptr().add(4 * r)) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f64; LANES] {
        let mut out = [0.0; LANES];
        for r in 0..REGS {
            // SAFETY: see the module documentation; 4 r + 4 <= LANES.
            unsafe { _mm256_storeu_pd(out.as_mut_ptr().add(4 * r), self.0[r]) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        per_register!(F64s, _mm256_sqrt_pd, self)
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        (self.to_bits() & U64s::splat(!SIGN)).as_f64_bits()
    }

    /// Lane-wise `if self > other { self } else { other }`: exactly `vmaxpd`'s definition,
    /// NaN included, so the array version agrees.
    #[inline(always)]
    pub(crate) fn max(self, other: Self) -> Self {
        per_register!(F64s, _mm256_max_pd, self, other)
    }

    /// Lane-wise `if self < other { self } else { other }` (`vminpd`).
    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        per_register!(F64s, _mm256_min_pd, self, other)
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
        let mut out = U64s::zeroed();
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            out.0[r] =
                unsafe { _mm256_castpd_si256(_mm256_cmp_pd::<PREDICATE>(self.0[r], other.0[r])) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U64s {
        per_register!(U64s, _mm256_castpd_si256, self)
    }
}

impl U64s {
    #[inline(always)]
    fn zeroed() -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_setzero_si256() }; REGS])
    }

    #[inline(always)]
    pub(crate) fn splat(x: u64) -> Self {
        // SAFETY: see the module documentation.
        Self([unsafe { _mm256_set1_epi64x(x as i64) }; REGS])
    }

    #[inline(always)]
    pub(crate) fn load(values: [u64; LANES]) -> Self {
        let mut out = Self::zeroed();
        let p = values.as_ptr().cast::<__m256i>();
        for r in 0..REGS {
            // SAFETY: see the module documentation; register r covers u64 4 r .. 4 r + 4.
            out.0[r] = unsafe { _mm256_loadu_si256(p.add(r)) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u64; LANES] {
        let mut out = [0u64; LANES];
        let p = out.as_mut_ptr().cast::<__m256i>();
        for r in 0..REGS {
            // SAFETY: see the module documentation; register r covers u64 4 r .. 4 r + 4.
            unsafe { _mm256_storeu_si256(p.add(r), self.0[r]) };
        }
        out
    }

    #[inline(always)]
    pub(crate) fn wrapping_add(self, other: Self) -> Self {
        per_register!(U64s, _mm256_add_epi64, self, other)
    }

    #[inline(always)]
    pub(crate) fn rotate_left(self, n: u32) -> Self {
        (self << n) | (self >> (64 - n))
    }

    #[inline(always)]
    pub(crate) fn as_f64_bits(self) -> F64s {
        per_register!(F64s, _mm256_castsi256_pd, self)
    }

    #[inline(always)]
    pub(crate) fn eq_u64(self, other: Self) -> U64s {
        per_register!(U64s, _mm256_cmpeq_epi64, self, other)
    }

    /// As a mask: `a` where set, `b` elsewhere. One `vblendvpd` per register; it looks at the
    /// sign bit only, which for an all-ones / zero mask is the same choice.
    #[inline(always)]
    pub(crate) fn select(self, a: F64s, b: F64s) -> F64s {
        let mask = self.as_f64_bits();
        per_register!(F64s, _mm256_blendv_pd, b, a, mask)
    }

    /// As a mask: one bit per lane, lane 0 in bit 0.
    #[inline(always)]
    pub(crate) fn bitmask(self) -> u32 {
        let mut bits = 0;
        for r in 0..REGS {
            // SAFETY: see the module documentation.
            let four = unsafe { _mm256_movemask_pd(_mm256_castsi256_pd(self.0[r])) } as u32;
            bits |= four << (4 * r);
        }
        bits
    }
}

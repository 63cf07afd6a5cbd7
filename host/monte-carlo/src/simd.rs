//! A minimal portable SIMD vector on stable Rust: `LANES` f32 or u32 in an array, every operation a
//! one-line loop over the lanes.
//!
//! Each operation is small enough for the compiler to unroll and turn into one vector instruction
//! (per register width of the target features the caller was compiled with: see the dispatch in
//! `photon_lanes`). Writing the photon step as a long scalar body per lane instead leaves a loop too
//! big to unroll that the loop vectoriser refuses, and the code stays scalar; hence this type.
//! Operations are the IEEE ones (the fused multiply-add exactly rounded), so every instruction set
//! gives bit-identical results.

use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Shl, Shr, Sub};

/// Photons in flight per thread: one AVX-512 register of f32 (two AVX2 registers).
pub(crate) const LANES: usize = 16;

/// `LANES` f32 values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct F32s(pub [f32; LANES]);

/// `LANES` u32 values; also the lane masks (all ones for true, zero for false).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct U32s(pub [u32; LANES]);

macro_rules! lanewise {
    ($a:expr, |$x:ident| $body:expr) => {{
        let a = $a;
        let mut out = [Default::default(); LANES];
        for (o, &$x) in out.iter_mut().zip(a.iter()) {
            *o = $body;
        }
        out
    }};
    ($a:expr, $b:expr, |$x:ident, $y:ident| $body:expr) => {{
        let (a, b) = ($a, $b);
        let mut out = [Default::default(); LANES];
        for i in 0..LANES {
            let ($x, $y) = (a[i], b[i]);
            out[i] = $body;
        }
        out
    }};
}

macro_rules! binary_op {
    ($ty:ident, $trait:ident, $method:ident, $op:tt) => {
        impl $trait for $ty {
            type Output = $ty;
            #[inline(always)]
            fn $method(self, rhs: $ty) -> $ty {
                $ty(lanewise!(self.0, rhs.0, |x, y| x $op y))
            }
        }
    };
}

binary_op!(F32s, Add, add, +);
binary_op!(F32s, Sub, sub, -);
binary_op!(F32s, Mul, mul, *);
binary_op!(F32s, Div, div, /);
binary_op!(U32s, BitAnd, bitand, &);
binary_op!(U32s, BitOr, bitor, |);
binary_op!(U32s, BitXor, bitxor, ^);

impl Neg for F32s {
    type Output = F32s;
    #[inline(always)]
    fn neg(self) -> F32s {
        F32s(lanewise!(self.0, |x| -x))
    }
}

impl Not for U32s {
    type Output = U32s;
    #[inline(always)]
    fn not(self) -> U32s {
        U32s(lanewise!(self.0, |x| !x))
    }
}

impl Shl<u32> for U32s {
    type Output = U32s;
    #[inline(always)]
    fn shl(self, n: u32) -> U32s {
        U32s(lanewise!(self.0, |x| x << n))
    }
}

impl Shr<u32> for U32s {
    type Output = U32s;
    #[inline(always)]
    fn shr(self, n: u32) -> U32s {
        U32s(lanewise!(self.0, |x| x >> n))
    }
}

impl F32s {
    #[inline(always)]
    pub(crate) fn splat(x: f32) -> Self {
        Self([x; LANES])
    }

    #[inline(always)]
    pub(crate) fn load(values: [f32; LANES]) -> Self {
        Self(values)
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f32; LANES] {
        self.0
    }

    /// `self * a + b` with one rounding (`f32::mul_add`: the FMA instruction or libm's exact
    /// software version).
    #[inline(always)]
    pub(crate) fn mul_add(self, a: Self, b: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i].mul_add(a.0[i], b.0[i])))
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        Self(lanewise!(self.0, |x| x.sqrt()))
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        Self(lanewise!(self.0, |x| x.abs()))
    }

    /// Lane-wise `if self < other { self } else { other }` (x86's `minps`, NaN included).
    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        Self(lanewise!(self.0, other.0, |x, y| if x < y { x } else { y }))
    }

    #[inline(always)]
    pub(crate) fn lt(self, other: Self) -> U32s {
        U32s(lanewise!(self.0, other.0, |x, y| mask(x < y)))
    }

    #[inline(always)]
    pub(crate) fn gt(self, other: Self) -> U32s {
        U32s(lanewise!(self.0, other.0, |x, y| mask(x > y)))
    }

    #[inline(always)]
    pub(crate) fn eq(self, other: Self) -> U32s {
        U32s(lanewise!(self.0, other.0, |x, y| mask(x == y)))
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U32s {
        U32s(lanewise!(self.0, |x| x.to_bits()))
    }
}

impl U32s {
    #[inline(always)]
    pub(crate) fn splat(x: u32) -> Self {
        Self([x; LANES])
    }

    #[inline(always)]
    pub(crate) fn load(values: [u32; LANES]) -> Self {
        Self(values)
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u32; LANES] {
        self.0
    }

    #[inline(always)]
    pub(crate) fn wrapping_add(self, other: Self) -> Self {
        Self(lanewise!(self.0, other.0, |x, y| x.wrapping_add(y)))
    }

    #[inline(always)]
    pub(crate) fn rotate_left(self, n: u32) -> Self {
        Self(lanewise!(self.0, |x| x.rotate_left(n)))
    }

    #[inline(always)]
    pub(crate) fn as_f32_bits(self) -> F32s {
        F32s(lanewise!(self.0, |x| f32::from_bits(x)))
    }

    /// Each lane read as an i32 and rounded to the nearest f32 (`cvtdq2ps`).
    #[inline(always)]
    pub(crate) fn signed_to_f32(self) -> F32s {
        F32s(lanewise!(self.0, |x| x as i32 as f32))
    }

    #[inline(always)]
    pub(crate) fn eq_u32(self, other: Self) -> U32s {
        U32s(lanewise!(self.0, other.0, |x, y| mask(x == y)))
    }

    /// As a mask: `a` where set, `b` elsewhere (bitwise, so exact for any value).
    #[inline(always)]
    pub(crate) fn select(self, a: F32s, b: F32s) -> F32s {
        ((self & a.to_bits()) | (!self & b.to_bits())).as_f32_bits()
    }

    /// As a mask: one bit per lane, lane 0 in bit 0.
    #[inline(always)]
    pub(crate) fn bitmask(self) -> u32 {
        let mut bits = 0;
        for (i, &m) in self.0.iter().enumerate() {
            bits |= u32::from(m != 0) << i;
        }
        bits
    }
}

#[inline(always)]
fn mask(b: bool) -> u32 {
    if b { u32::MAX } else { 0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn select_and_masks_follow_the_comparisons() {
        let a = F32s(std::array::from_fn(|i| i as f32));
        let b = F32s::splat(3.5);
        let lower = a.lt(b);
        assert_eq!(lower.bitmask(), 0b1111);
        assert_eq!(a.gt(b).bitmask(), 0xffff & !0b1111);
        let picked = lower.select(a, F32s::splat(-1.0));
        assert_eq!(picked.0[..6], [0.0, 1.0, 2.0, 3.0, -1.0, -1.0]);
        assert_eq!((a - b).abs().min(F32s::splat(1.0)).0[0], 1.0);
        assert_eq!(
            U32s::splat(0x7fff_ffff).signed_to_f32().0[3],
            2_147_483_648.0
        );
    }
}

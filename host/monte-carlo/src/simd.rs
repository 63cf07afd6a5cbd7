//! A minimal portable SIMD vector on stable Rust: `LANES` f64 or u64 in an array, every operation a
//! one-line loop over the lanes.
//!
//! Each operation is small enough for the compiler to unroll and turn into one vector instruction
//! (per register width of the target features the caller was compiled with: see the dispatch in
//! `photon_lanes`). Writing the photon step as a long scalar body per lane instead leaves a loop too
//! big to unroll that the loop vectoriser refuses, and the code stays scalar; hence this type.
//! Operations are the IEEE ones (no fused multiply-add), so every instruction set gives
//! bit-identical results.

use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Shl, Shr, Sub};

/// Photons in flight per thread: one AVX-512 register of f64 (two AVX2 registers).
pub(crate) const LANES: usize = 8;

/// `LANES` f64 values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct F64s(pub [f64; LANES]);

/// `LANES` u64 values; also the lane masks (all ones for true, zero for false).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct U64s(pub [u64; LANES]);

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

binary_op!(F64s, Add, add, +);
binary_op!(F64s, Sub, sub, -);
binary_op!(F64s, Mul, mul, *);
binary_op!(F64s, Div, div, /);
binary_op!(U64s, BitAnd, bitand, &);
binary_op!(U64s, BitOr, bitor, |);
binary_op!(U64s, BitXor, bitxor, ^);

impl Neg for F64s {
    type Output = F64s;
    #[inline(always)]
    fn neg(self) -> F64s {
        F64s(lanewise!(self.0, |x| -x))
    }
}

impl Not for U64s {
    type Output = U64s;
    #[inline(always)]
    fn not(self) -> U64s {
        U64s(lanewise!(self.0, |x| !x))
    }
}

impl Shl<u32> for U64s {
    type Output = U64s;
    #[inline(always)]
    fn shl(self, n: u32) -> U64s {
        U64s(lanewise!(self.0, |x| x << n))
    }
}

impl Shr<u32> for U64s {
    type Output = U64s;
    #[inline(always)]
    fn shr(self, n: u32) -> U64s {
        U64s(lanewise!(self.0, |x| x >> n))
    }
}

impl F64s {
    #[inline(always)]
    pub(crate) fn splat(x: f64) -> Self {
        Self([x; LANES])
    }

    #[inline(always)]
    pub(crate) fn load(values: [f64; LANES]) -> Self {
        Self(values)
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [f64; LANES] {
        self.0
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        Self(lanewise!(self.0, |x| x.sqrt()))
    }

    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        Self(lanewise!(self.0, |x| x.abs()))
    }

    /// Lane-wise maximum (`self` when the other is NaN, as x86's max does with this order).
    #[inline(always)]
    pub(crate) fn max(self, other: Self) -> Self {
        Self(lanewise!(self.0, other.0, |x, y| if x > y { x } else { y }))
    }

    #[inline(always)]
    pub(crate) fn min(self, other: Self) -> Self {
        Self(lanewise!(self.0, other.0, |x, y| if x < y { x } else { y }))
    }

    #[inline(always)]
    pub(crate) fn lt(self, other: Self) -> U64s {
        U64s(lanewise!(self.0, other.0, |x, y| mask(x < y)))
    }

    #[inline(always)]
    pub(crate) fn gt(self, other: Self) -> U64s {
        U64s(lanewise!(self.0, other.0, |x, y| mask(x > y)))
    }

    #[inline(always)]
    pub(crate) fn eq(self, other: Self) -> U64s {
        U64s(lanewise!(self.0, other.0, |x, y| mask(x == y)))
    }

    #[inline(always)]
    pub(crate) fn to_bits(self) -> U64s {
        U64s(lanewise!(self.0, |x| x.to_bits()))
    }
}

impl U64s {
    #[inline(always)]
    pub(crate) fn splat(x: u64) -> Self {
        Self([x; LANES])
    }

    #[inline(always)]
    pub(crate) fn load(values: [u64; LANES]) -> Self {
        Self(values)
    }

    #[inline(always)]
    pub(crate) fn store(self) -> [u64; LANES] {
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
    pub(crate) fn as_f64_bits(self) -> F64s {
        F64s(lanewise!(self.0, |x| f64::from_bits(x)))
    }

    #[inline(always)]
    pub(crate) fn eq_u64(self, other: Self) -> U64s {
        U64s(lanewise!(self.0, other.0, |x, y| mask(x == y)))
    }

    /// As a mask: `a` where set, `b` elsewhere (bitwise, so exact for any value).
    #[inline(always)]
    pub(crate) fn select(self, a: F64s, b: F64s) -> F64s {
        ((self & a.to_bits()) | (!self & b.to_bits())).as_f64_bits()
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
fn mask(b: bool) -> u64 {
    if b { u64::MAX } else { 0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn select_and_masks_follow_the_comparisons() {
        let a = F64s([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let b = F64s::splat(3.5);
        let lower = a.lt(b);
        assert_eq!(lower.bitmask(), 0b0000_1111);
        assert_eq!(a.gt(b).bitmask(), 0b1111_0000);
        let picked = lower.select(a, F64s::splat(-1.0));
        assert_eq!(picked.0, [0.0, 1.0, 2.0, 3.0, -1.0, -1.0, -1.0, -1.0]);
        assert_eq!((a - b).abs().min(F64s::splat(1.0)).0[0], 1.0);
        assert_eq!(a.max(b).0[7], 7.0);
    }
}

//! Four `f64` lanes with elementwise IEEE arithmetic, for kernels written once over
//! [`Lanes`] and run on one value (`f64`) or four ([`F64x4`]): every lane of the four
//! computes the bits the one-value path computes for the same input (no fused
//! multiply-add, no reordered sums), so batching never changes a result. The lane loops
//! of [`F64x4`] become vector instructions (in functions compiled for AVX, four lanes per
//! instruction).

use std::ops::{Add, Mul, Sub};

/// One value per lane, with elementwise IEEE arithmetic.
pub(crate) trait Lanes:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self>
{
    const N: usize;
    fn splat(v: f64) -> Self;
    fn div(self, o: Self) -> Self;
    fn sqrt(self) -> Self;
    fn abs(self) -> Self;
    fn lane(&self, l: usize) -> f64;
    fn set_lane(&mut self, l: usize, v: f64);
    /// `self` where `take[l]`, else `other`.
    fn select(self, take: &[bool; 4], other: Self) -> Self;
}

impl Lanes for f64 {
    const N: usize = 1;
    #[inline(always)]
    fn splat(v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        self / o
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    #[inline(always)]
    fn abs(self) -> Self {
        f64::abs(self)
    }
    #[inline(always)]
    fn lane(&self, _: usize) -> f64 {
        *self
    }
    #[inline(always)]
    fn set_lane(&mut self, _: usize, v: f64) {
        *self = v;
    }
    #[inline(always)]
    fn select(self, take: &[bool; 4], other: Self) -> Self {
        if take[0] { self } else { other }
    }
}

/// Four `f64` lanes; the compiler turns the lane loops into vector instructions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct F64x4(pub(crate) [f64; 4]);

macro_rules! lanewise {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for F64x4 {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                F64x4(std::array::from_fn(|l| self.0[l] $op o.0[l]))
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);

impl Lanes for F64x4 {
    const N: usize = 4;
    #[inline(always)]
    fn splat(v: f64) -> Self {
        F64x4([v; 4])
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        F64x4(std::array::from_fn(|l| self.0[l] / o.0[l]))
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        F64x4(self.0.map(f64::sqrt))
    }
    #[inline(always)]
    fn abs(self) -> Self {
        F64x4(self.0.map(f64::abs))
    }
    #[inline(always)]
    fn lane(&self, l: usize) -> f64 {
        self.0[l]
    }
    #[inline(always)]
    fn set_lane(&mut self, l: usize, v: f64) {
        self.0[l] = v;
    }
    #[inline(always)]
    fn select(self, take: &[bool; 4], other: Self) -> Self {
        F64x4(std::array::from_fn(|l| {
            if take[l] { self.0[l] } else { other.0[l] }
        }))
    }
}

//! A Gaussian seen through a box: the density of `s = x + u` with `x ~ N(mu, sigma^2)` and `u`
//! uniform on `[-W/2, W/2]` (the slit width), and the posterior moments of `x` given `s`.
//!
//! The density is `h(s) = (Phi(b) - Phi(a)) / W` with `a = (s - W/2 - mu)/sigma`,
//! `b = (s + W/2 - mu)/sigma`; given `s` the latent `x` is the normal truncated to
//! `[s - W/2, s + W/2]`, whose first two moments are closed form. These two facts make the EM of
//! `em_free` / `em_layered` an exact EM for the box-convolved mixture (not an approximation), so the
//! log-likelihood is monotone up to rounding.
//!
//! Everything is computed in log space with tail-safe normal CDF differences, so a sample a
//! thousand sigmas from a component gives a finite (very negative) log-density, never NaN or -inf.

use std::f64::consts::{LN_2, PI, SQRT_2};

/// `ln(phi(x))`, the log of the standard normal density.
pub fn ln_phi(x: f64) -> f64 {
    -0.5 * x * x - 0.5 * (2.0 * PI).ln()
}

/// `ln(Q(x))` with `Q(x) = 1 - Phi(x)` the upper tail, accurate for every finite `x`.
pub fn ln_upper_tail(x: f64) -> f64 {
    if x < 8.0 {
        // erfc keeps full relative accuracy here (Q(8) ~ 6e-16, far from underflow).
        (0.5 * mlsss_core::special::erfc(x / std::f64::consts::SQRT_2)).ln()
    } else {
        ln_phi(x) + mills_ratio(x).ln()
    }
}

/// Mills ratio `Q(x)/phi(x)` for `x >= 8` by its continued fraction (Lentz would be overkill:
/// 40 backward terms converge to machine precision this far in the tail).
fn mills_ratio(x: f64) -> f64 {
    let mut tail = 0.0;
    for k in (1..=40).rev() {
        tail = k as f64 / (x + tail);
    }
    1.0 / (x + tail)
}

/// Below this many sigmas from the mean the tail probabilities are differenced directly.
const LINEAR_TAIL: f64 = 5.0;

/// `ln(Phi(b) - Phi(a))` for `a <= b`. Returns a finite number for every finite input with
/// `a < b`; `-inf` only when `a == b`.
pub fn ln_cdf_diff(a: f64, b: f64) -> f64 {
    debug_assert!(a <= b);
    let width = b - a;
    if width <= 0.0 {
        return f64::NEG_INFINITY;
    }
    if width < 1e-3 {
        // Midpoint rule with its curvature correction: phi''/phi = m^2 - 1.
        let m = 0.5 * (a + b);
        return ln_phi(m) + width.ln() + ((m * m - 1.0) * width * width / 24.0).ln_1p();
    }
    if a > 0.0 && a < LINEAR_TAIL {
        // Q(a) - Q(b) directly: Q(a) > 1e-7 and the interval is not tiny, so the difference
        // loses at most a few digits of relative accuracy (cheaper than the log-space branch).
        let q =
            0.5 * (mlsss_core::special::erfc(a / SQRT_2) - mlsss_core::special::erfc(b / SQRT_2));
        q.max(f64::MIN_POSITIVE).ln()
    } else if b < 0.0 && b > -LINEAR_TAIL {
        let q =
            0.5 * (mlsss_core::special::erfc(-b / SQRT_2) - mlsss_core::special::erfc(-a / SQRT_2));
        q.max(f64::MIN_POSITIVE).ln()
    } else if a > 0.0 {
        // Both in the upper tail: Q(a) - Q(b).
        ln_diff_of_logs(ln_upper_tail(a), ln_upper_tail(b))
    } else if b < 0.0 {
        // Mirror image in the lower tail.
        ln_diff_of_logs(ln_upper_tail(-b), ln_upper_tail(-a))
    } else {
        // Straddles 0: at least min(Phi(b)-1/2, 1/2-Phi(a)) which is not tiny relative to width.
        let lower = 0.5 * mlsss_core::special::erfc(-a / std::f64::consts::SQRT_2);
        let upper = 0.5 * mlsss_core::special::erfc(b / std::f64::consts::SQRT_2);
        (1.0 - lower - upper).max(f64::MIN_POSITIVE).ln()
    }
}

/// `Phi(b) - Phi(a)` for `a <= b` in linear space, by the same branches as [`ln_cdf_diff`]
/// without its logarithms (for callers that sum densities, e.g. a likelihood scan). Underflows
/// to 0 beyond ~37 sigmas: callers fall back to [`ln_cdf_diff`] when a sum of these is tiny.
pub fn cdf_diff(a: f64, b: f64) -> f64 {
    let width = b - a;
    if width <= 0.0 {
        return 0.0;
    }
    if width < 1e-3 {
        let m = 0.5 * (a + b);
        return ln_phi(m).exp() * width * (1.0 + (m * m - 1.0) * width * width / 24.0);
    }
    let (ta, tb) = (small_tail(a), small_tail(b));
    let q = if a > 0.0 {
        ta - tb
    } else if b < 0.0 {
        tb - ta
    } else {
        1.0 - ta - tb
    };
    q.max(0.0)
}

/// Beyond this `|z|` (`erfc`'s argument `|z| / sqrt 2` at 1.25, where [`erfc`] starts calling
/// `exp`) the normal tail is taken as `exp(-z^2/2)` times Cody's rational
/// ([`normal_tail_scaled`]), so that an [`Edge`] shares the exponential with its density.
/// Below it the tail is `0.5 erfc(|z| / sqrt 2)`, which needs no exponential there.
///
/// [`erfc`]: mlsss_core::special::erfc
/// [`normal_tail_scaled`]: mlsss_core::special::normal_tail_scaled
const SCALED_TAIL_FROM: f64 = 1.25 * SQRT_2;

/// The smaller normal tail beyond `z`, `Q(|z|)`, given `gauss = exp(-z^2/2)` when `|z| >=`
/// [`SCALED_TAIL_FROM`] (ignored below it). Relative error within `2e-15 + 2.5e-16 z^2`
/// ([`normal_tail_scaled`]; `0.5 erfc` to an ulp below the switch). The rule is
/// [`normal_tail_given_gaussian`]'s (the batched edges' too); `gauss` is called only beyond the
/// switch.
///
/// [`normal_tail_scaled`]: mlsss_core::special::normal_tail_scaled
/// [`normal_tail_given_gaussian`]: mlsss_core::special::normal_tail_given_gaussian
#[inline]
fn tail_with(z: f64, gauss: impl FnOnce() -> f64) -> f64 {
    // Below the switch the tail does not read the Gaussian: not computed there.
    let g = if z.abs() < SCALED_TAIL_FROM {
        0.0
    } else {
        gauss()
    };
    mlsss_core::special::normal_tail_given_gaussian(z, g, SCALED_TAIL_FROM)
}

/// `Q(|z|)` ([`tail_with`] computing its own exponential).
#[inline]
fn small_tail(z: f64) -> f64 {
    if z.abs() >= UNDERFLOW_Z {
        return 0.0;
    }
    tail_with(z, || gaussian(z))
}

/// From this `|z|` on, `exp(-z^2/2)` is exactly 0 (its exponent is below -745.14, where `exp`
/// underflows past the subnormals), and so are the tail and the density made from it (0 times
/// Cody's finite rational): [`small_tail`] and [`Edge::new`] return those zeros without the
/// exponential and the rational. Why: the narrow components (the dipole's finest Gaussians, a
/// shallow layer's) put many of the period's box edges beyond it. Bit-identical by
/// construction; the test `edges_beyond_the_underflow_are_the_computed_zeros` checks it.
const UNDERFLOW_Z: f64 = 38.61;

/// `exp(-z^2/2)`, the unnormalised standard normal density: the one expression both the
/// density and the tail of an [`Edge`] use, so masses agree bit for bit however they are made.
#[inline]
fn gaussian(z: f64) -> f64 {
    (-0.5 * z * z).exp()
}

/// A standardised box edge `z` with what a box's mass and posterior need there: the smaller
/// normal tail beyond it, `0.5 erfc(|z| / sqrt 2)`, and (for posteriors) the density `phi(z)`.
///
/// Why: the slit boxes of a profile tile the period (a sweep shifts the slit by its own width),
/// so each box's upper edge is the next box's lower edge. Computing the error function and the
/// exponential once per edge instead of once per box end halves the EM's costliest calls
/// ([`mass_between`] and [`BoxedGaussian::posterior_between`] do the rest).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Edge {
    pub z: f64,
    tail: f64,
    phi: f64,
}

impl Edge {
    /// Tail and density at `z`.
    /// One exponential for both beyond `SCALED_TAIL_FROM` (where most edges of a profile
    /// fall): the tail is the density's Gaussian times Cody's rational.
    #[inline(always)]
    pub fn new(z: f64) -> Self {
        Self::with_density_and_tail(z, |z, g| tail_with(z, || g))
    }

    /// [`Edge::tail_only`] with the far tail's one-division form
    /// ([`normal_tail_scaled_far`](mlsss_core::special::normal_tail_scaled_far)) beyond
    /// `sqrt 32`: a few ulps from [`Edge::tail_only`] there, the same value below. For the
    /// dipole's extinction search, whose narrow Gaussians put most edges that far; the EM keeps
    /// [`Edge::tail_only`] and [`Edge::new`] (its results stay bit for bit).
    #[inline]
    pub fn tail_only_fast(z: f64) -> Self {
        let tail = if z.abs() >= UNDERFLOW_Z {
            0.0
        } else {
            fast_tail(z, || gaussian(z))
        };
        Self {
            z,
            tail,
            phi: f64::NAN,
        }
    }

    /// [`Edge::tail_only_fast`] with the density `phi(z)` as well (one exponential for both;
    /// [`Edge::phi`]): for the dipole's extinction search, which takes the slope of a box's
    /// mass from its edges' densities.
    #[inline]
    pub fn with_density_fast(z: f64) -> Self {
        Self::with_density_and_tail(z, |z, g| fast_tail(z, || g))
    }

    /// The edge at `z` with its density and `tail(z, gaussian(z))` (one exponential for both);
    /// both 0 where the Gaussian underflows.
    #[inline(always)]
    fn with_density_and_tail(z: f64, tail: impl FnOnce(f64, f64) -> f64) -> Self {
        if z.abs() >= UNDERFLOW_Z {
            return Self {
                z,
                tail: 0.0,
                phi: 0.0,
            };
        }
        let g = gaussian(z);
        Self {
            z,
            tail: tail(z, g),
            phi: g * INV_SQRT_2PI,
        }
    }

    /// The edge at `z` given its Gaussian `exp(-z^2/2)` and its tail (as [`tail_with`] takes
    /// it; both ignored beyond [`UNDERFLOW_Z`], where the edge is zeros as [`Edge::new`]'s).
    #[inline(always)]
    fn from_parts(z: f64, gauss: f64, tail: f64) -> Self {
        if z.abs() >= UNDERFLOW_Z {
            return Self {
                z,
                tail: 0.0,
                phi: 0.0,
            };
        }
        Self {
            z,
            tail,
            phi: gauss * INV_SQRT_2PI,
        }
    }

    /// The standard normal density at the edge, `phi(z)` (NaN for an edge made without it).
    #[inline]
    pub fn phi(&self) -> f64 {
        self.phi
    }

    /// The tail at `z` alone (for masses; [`BoxedGaussian::posterior_between`] needs [`Edge::new`]).
    #[inline]
    pub fn tail_only(z: f64) -> Self {
        Self {
            z,
            tail: small_tail(z),
            phi: f64::NAN,
        }
    }
}

/// The tail of [`Edge::tail_only_fast`] below [`UNDERFLOW_Z`], given `gauss = exp(-z^2/2)`:
/// beyond `sqrt 32` the far tail's one-division form
/// ([`normal_tail_scaled_far`](mlsss_core::special::normal_tail_scaled_far)), else [`tail_with`].
#[inline]
fn fast_tail(z: f64, gauss: impl FnOnce() -> f64) -> f64 {
    const SQRT_32: f64 = 5.656_854_249_492_381;
    let y = z.abs();
    if y > SQRT_32 {
        gauss() * mlsss_core::special::normal_tail_scaled_far(y)
    } else {
        tail_with(z, gauss)
    }
}

/// `Phi(b) - Phi(a)` for edges `a <= b`: the same value and branches as [`cdf_diff`] of their
/// `z` (bit for bit: `0.5 (x - y) = 0.5 x - 0.5 y` exactly).
#[inline(always)]
pub fn mass_between(a: &Edge, b: &Edge) -> f64 {
    let width = b.z - a.z;
    if width <= 0.0 {
        return 0.0;
    }
    if width < 1e-3 {
        return cdf_diff(a.z, b.z);
    }
    let q = if a.z > 0.0 {
        a.tail - b.tail
    } else if b.z < 0.0 {
        b.tail - a.tail
    } else {
        1.0 - a.tail - b.tail
    };
    q.max(0.0)
}

/// Two slit boxes whose facing edges (standardised) differ by at most this fraction of the box
/// width share one edge evaluation: a sweep places them edge to edge, and they differ only by
/// the rounding of the sample positions (~1e-13 of the width).
pub(crate) const SHARED_EDGE: f64 = 1e-9;

/// The boxes of one component's slit image at `offset` over the samples at `positions`, walked
/// in the order `order` (by position): calls `visit(j, lower, upper)` with the indices in
/// `edges` of the standardised edges of sample `j`'s box, pushing each edge once where one box
/// ends at the next one's start. Samples `reaches(s)` refuses (too far for this image to
/// matter) are skipped. The edges are evaluated afterwards, all of a profile's walks at once
/// ([`edges_into`]).
pub fn box_edges(
    g: &BoxedGaussian,
    offset: f64,
    order: &[usize],
    positions: impl Fn(usize) -> f64,
    reaches: impl Fn(f64) -> bool,
    edges: &mut Vec<f64>,
    mut visit: impl FnMut(usize, usize, usize),
) {
    // The previous box's upper edge: its `z` and index.
    let mut previous: Option<(f64, usize)> = None;
    for &j in order {
        let s = positions(j);
        if !reaches(s) {
            previous = None;
            continue;
        }
        let (a, b) = g.interval(s - offset);
        let lower = match previous {
            Some((z, i)) if (a - z).abs() <= SHARED_EDGE * (b - a) => i,
            _ => {
                edges.push(a);
                edges.len() - 1
            }
        };
        edges.push(b);
        let upper = edges.len() - 1;
        visit(j, lower, upper);
        previous = Some((b, upper));
    }
}

/// The edges at every `z`, into `out` (emptied first): [`Edge::new`]'s values but for the
/// Gaussian, taken as [`exp_nonpositive`] instead of libm's `exp` (within 4 ulps of it), eight
/// at a time where the CPU has AVX-512 ([`gaussian_and_tail_avx512`]: the Gaussian, Cody's
/// rational and, below `1.25 sqrt 2`, `erfc`'s rationals of eight edges in vector registers).
/// Every instruction set gets the same values bit for bit (the test
/// `batched_edges_are_the_same_on_every_path_and_edge_new_to_the_rounding`).
///
/// Why: the E-step evaluates ~170 million edges at full size. One at a time, inside the walk,
/// each was a call of libm's `exp` and a chain of dependent multiplications ending in a
/// division; walked first and evaluated together, the full-size fit's `fit_em` went from 4.9-5.1
/// to 3.7-3.8 CPU-s (2.47-2.60 to 1.90-1.93 s wall, 3 alternated runs each) with the same mean
/// iterations and components per fit, and to 3.5-3.6 CPU-s with `erfc` in the vector registers
/// too (2 runs each, the model byte-identical).
///
/// [`exp_nonpositive`]: mlsss_core::special::exp_nonpositive
/// [`gaussian_and_tail_avx512`]: mlsss_core::special::gaussian_and_tail_avx512
pub fn edges_into(z: &[f64], out: &mut Vec<Edge>) {
    out.clear();
    out.reserve(z.len());
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked above).
            unsafe { edges_into_avx512(z, out) };
            return;
        }
        if std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has FMA (checked above).
            unsafe { edges_into_fma(z, out) };
            return;
        }
    }
    edges_one_by_one(z, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn edges_into_avx512(z: &[f64], out: &mut Vec<Edge>) {
    let (chunks, rest) = z.as_chunks::<8>();
    for lanes in chunks {
        push_lanes_avx512(lanes, 8, out);
    }
    if !rest.is_empty() {
        // Only the last edges are copied (padded): copying every chunk cost a `memcpy` call each.
        let mut lanes = [0.0; 8];
        lanes[..rest.len()].copy_from_slice(rest);
        push_lanes_avx512(&lanes, rest.len(), out);
    }
}

/// The edges at the first `count` of `lanes` (the others are padding), onto `out`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
fn push_lanes_avx512(lanes: &[f64; 8], count: usize, out: &mut Vec<Edge>) {
    // SAFETY: this function's own target feature.
    let (gauss, tail) =
        unsafe { mlsss_core::special::gaussian_and_tail_avx512(lanes, SCALED_TAIL_FROM) };
    out.extend((0..count).map(|l| Edge::from_parts(lanes[l], gauss[l], tail[l])));
}

/// [`edges_one_by_one`] with the hardware's fused multiply-add (without it, `mul_add` is a call
/// of libm's software `fma`: the same values, several times slower).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "fma")]
unsafe fn edges_into_fma(z: &[f64], out: &mut Vec<Edge>) {
    edges_one_by_one(z, out);
}

/// [`edges_into`] one edge at a time.
#[inline(always)]
fn edges_one_by_one(z: &[f64], out: &mut Vec<Edge>) {
    use mlsss_core::special::{exp_nonpositive, normal_tail_given_gaussian};
    // A plain loop, not `extend` with a closure: the closure would be compiled apart, without
    // the caller's target features, and `mul_add` would be libm's software `fma` (measured:
    // the E-step twice as slow).
    for &z in z {
        let edge = if z.abs() >= UNDERFLOW_Z {
            Edge::from_parts(z, 0.0, 0.0)
        } else {
            let gauss = exp_nonpositive(-0.5 * z * z);
            Edge::from_parts(
                z,
                gauss,
                normal_tail_given_gaussian(z, gauss, SCALED_TAIL_FROM),
            )
        };
        out.push(edge);
    }
}

/// `ln(e^p - e^q)` for `p >= q`.
fn ln_diff_of_logs(p: f64, q: f64) -> f64 {
    let d = q - p;
    if d >= 0.0 {
        return ln_phi(40.0); // equal tails: a vanishing but finite mass
    }
    // ln(1 - e^d), the accurate branch chosen as in Maechler's log1mexp note.
    let ln1m = if d > -LN_2 {
        (-d.exp_m1()).ln()
    } else {
        (-d.exp()).ln_1p()
    };
    p + ln1m
}

/// A component seen through the slit: mean and standard deviation (mm) of the Gaussian, and the
/// slit width `W` (mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxedGaussian {
    pub mean: f64,
    pub sigma: f64,
    pub width: f64,
}

/// Smallest `Phi(b) - Phi(a)` the linear-space forms use: far above the subnormal range, so
/// `phi(a) / Z` keeps full precision and a sum of densities that stays above ~1e-200 loses
/// nothing measurable by dropping the terms below it.
pub const LINEAR_MIN: f64 = 1e-290;

/// `1 / sqrt(2 pi)`.
const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// [`Posterior`] in linear space (see [`BoxedGaussian::posterior_linear`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearPosterior {
    /// `h(s)`, the density of the sample.
    pub density: f64,
    /// `E[x | s]`.
    pub mean: f64,
    /// `Var[x | s]`, clamped to `[0, W^2/12]`.
    pub variance: f64,
}

/// Posterior of the latent (unboxed) position given one observed sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Posterior {
    /// `ln h(s)`, the log-density of the sample.
    pub ln_density: f64,
    /// `E[x | s]`.
    pub mean: f64,
    /// `Var[x | s]`, clamped to its exact bounds `[0, W^2/12]`.
    pub variance: f64,
}

impl BoxedGaussian {
    /// Bounds of the standardised interval for sample `s`.
    #[inline]
    pub fn interval(&self, s: f64) -> (f64, f64) {
        let half = 0.5 * self.width;
        (
            (s - half - self.mean) / self.sigma,
            (s + half - self.mean) / self.sigma,
        )
    }

    /// `h(s)` in linear space (0 where it underflows, ~37 sigmas out; see [`cdf_diff`]).
    pub fn density(&self, s: f64) -> f64 {
        let (a, b) = self.interval(s);
        cdf_diff(a, b) / self.width
    }

    /// `ln h(s)`.
    pub fn ln_density(&self, s: f64) -> f64 {
        let (a, b) = self.interval(s);
        ln_cdf_diff(a, b) - self.width.ln()
    }

    /// Density and the truncated-normal moments of `x` given `s`, in linear space: the same
    /// formulas as [`BoxedGaussian::posterior`] without its logarithms and exponentials of the
    /// normaliser (`phi(a) / Z` directly). `None` when `Z = Phi(b) - Phi(a)` is below
    /// [`LINEAR_MIN`] (~37 sigmas out), where only the log-space form is accurate.
    pub fn posterior_linear(&self, s: f64) -> Option<LinearPosterior> {
        let (a, b) = self.interval(s);
        self.posterior_between(&Edge::new(a), &Edge::new(b))
    }

    /// [`BoxedGaussian::posterior_linear`] of the sample whose standardised interval has the
    /// edges `a` and `b` (made with [`Edge::new`]; neighbouring samples may share one).
    ///
    /// Always inlined (with [`mass_between`] and the moments) into the E-step's loop over
    /// boxes: out of line (a call through the GOT, another codegen unit) it returned its
    /// `Option` through memory, and reloading it stalled on store forwarding, a third of the
    /// box walk's samples in `perf annotate`. Inlined, the full-size fit's `fit_em` went
    /// from 8.8 to 7.8 CPU-s with a byte-identical model (Rust contracts no FMAs, so inlining
    /// changes no result).
    #[inline(always)]
    pub fn posterior_between(&self, a: &Edge, b: &Edge) -> Option<LinearPosterior> {
        let z = mass_between(a, b);
        if z.is_nan() || z < LINEAR_MIN {
            return None;
        }
        let width = b.z - a.z;
        let (m1, var_std) = if width < 1e-3 {
            let m = 0.5 * (a.z + b.z);
            (m - m * width * width / 12.0, width * width / 12.0)
        } else {
            let ra = a.phi / z;
            let rb = b.phi / z;
            let m1 = ra - rb;
            (m1, 1.0 + a.z * ra - b.z * rb - m1 * m1)
        };
        Some(self.moments(z / self.width, a.z, b.z, m1, var_std))
    }

    /// [`BoxedGaussian::density`] of the sample whose standardised interval has the edges `a`
    /// and `b`.
    #[inline]
    pub fn density_between(&self, a: &Edge, b: &Edge) -> f64 {
        mass_between(a, b) / self.width
    }

    /// The posterior mean and variance (clamped to their exact bounds) from the standardised
    /// moments, with `density` as given.
    #[inline(always)]
    fn moments(&self, density: f64, a: f64, b: f64, m1: f64, var_std: f64) -> LinearPosterior {
        let max_var = self.width * self.width / 12.0;
        let variance = (self.sigma * self.sigma * var_std).clamp(0.0, max_var);
        LinearPosterior {
            density,
            mean: self.mean + self.sigma * m1.clamp(a, b),
            variance: if variance.is_finite() { variance } else { 0.0 },
        }
    }

    /// Log-density and the truncated-normal moments of `x` given `s`.
    pub fn posterior(&self, s: f64) -> Posterior {
        let (a, b) = self.interval(s);
        let ln_z = ln_cdf_diff(a, b);
        // phi(a)/Z and phi(b)/Z stay finite in log space even when Z underflows.
        let ra = (ln_phi(a) - ln_z).exp();
        let rb = (ln_phi(b) - ln_z).exp();
        let m1 = ra - rb;
        let (m1, var_std) = if (b - a) < 1e-3 {
            // Nearly a point: the posterior is the box itself, tilted by the Gaussian slope.
            let m = 0.5 * (a + b);
            let w = b - a;
            (m - m * w * w / 12.0, w * w / 12.0)
        } else {
            let second = 1.0 + a * ra - b * rb;
            (m1, second - m1 * m1)
        };
        let moments = self.moments(0.0, a, b, m1, var_std);
        Posterior {
            ln_density: ln_z - self.width.ln(),
            mean: moments.mean,
            variance: moments.variance,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shortcut beyond [`UNDERFLOW_Z`] gives the bits the full computation gives, at the
    /// threshold, just past it, far out and at infinity, on both sides (and the computation
    /// really is zero there: `exp` underflows).
    #[test]
    fn edges_beyond_the_underflow_are_the_computed_zeros() {
        let full = |z: f64| {
            let g = gaussian(z);
            (tail_with(z, || g), g * INV_SQRT_2PI)
        };
        let mut zs = vec![UNDERFLOW_Z, 40.0, 1e3, 1e150, f64::MAX, f64::INFINITY];
        zs.extend((0..2000).map(|i| UNDERFLOW_Z + i as f64 * 1e-3));
        for z in zs.iter().flat_map(|&z| [z, -z]) {
            let (tail, phi) = full(z);
            assert_eq!(tail.to_bits(), 0.0f64.to_bits(), "tail at {z}");
            assert_eq!(phi.to_bits(), 0.0f64.to_bits(), "density at {z}");
            let edge = Edge::new(z);
            assert_eq!(edge.tail.to_bits(), tail.to_bits(), "{z}");
            assert_eq!(edge.phi.to_bits(), phi.to_bits(), "{z}");
            assert_eq!(Edge::tail_only(z).tail.to_bits(), tail.to_bits(), "{z}");
        }
        // Just inside the threshold the Gaussian is still computed (and is 0 or subnormal).
        let inside = UNDERFLOW_Z - 1e-9;
        assert_eq!(Edge::new(inside).tail, full(inside).0);
        // Where the exponential stops being exactly 0: -745.13 in the exponent, z ~ 38.604.
        assert!(gaussian(38.60) > 0.0);
    }

    /// [`edges_into`] gives the same bits on every path (AVX-512 where this CPU has it, with
    /// a remainder of fewer than eight edges, against one at a time) and [`Edge::new`]'s values
    /// to its exponential's rounding: the same where no exponential enters (the tails below
    /// [`SCALED_TAIL_FROM`], the zeros beyond [`UNDERFLOW_Z`]).
    #[test]
    fn batched_edges_are_the_same_on_every_path_and_edge_new_to_the_rounding() {
        let mut zs: Vec<f64> = (0..20_001)
            .map(|i| -45.0 + i as f64 * 0.0045 + 1e-7)
            .collect();
        zs.extend([
            0.0,
            -0.0,
            SCALED_TAIL_FROM,
            -SCALED_TAIL_FROM,
            UNDERFLOW_Z,
            -UNDERFLOW_Z,
        ]);
        zs.extend([
            5.656_854_249_492_381,
            38.6,
            -38.6,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ]);
        let mut batched = Vec::new();
        edges_into(&zs, &mut batched);
        let mut one_by_one = Vec::new();
        edges_one_by_one(&zs, &mut one_by_one);
        assert_eq!((batched.len(), one_by_one.len()), (zs.len(), zs.len()));
        let bits = |e: &Edge| (e.z.to_bits(), e.tail.to_bits(), e.phi.to_bits());
        let close = |ours: f64, libm: f64| (ours - libm).abs() <= 1e-15 * libm.abs() + 1e-320;
        for ((b, o), &z) in batched.iter().zip(&one_by_one).zip(&zs) {
            assert_eq!(bits(b), bits(o), "{z}");
            let reference = Edge::new(z);
            assert!(
                close(b.phi, reference.phi),
                "phi({z}): {} vs {}",
                b.phi,
                reference.phi
            );
            assert!(
                close(b.tail, reference.tail),
                "tail({z}): {} vs {}",
                b.tail,
                reference.tail
            );
            if z.abs() < SCALED_TAIL_FROM || z.abs() >= UNDERFLOW_Z {
                assert_eq!(b.tail.to_bits(), reference.tail.to_bits(), "{z}");
            }
        }
        edges_into(&[], &mut batched);
        assert!(batched.is_empty());
    }

    /// [`box_edges`] pushes one edge where a box ends at the next one's start, two after a
    /// gap (a sample the image does not reach), and each box's edges are its interval.
    #[test]
    fn box_edges_share_the_edges_of_adjacent_boxes() {
        let g = BoxedGaussian {
            mean: 0.3,
            sigma: 0.7,
            width: 0.5,
        };
        // Boxes edge to edge (a sweep shifts the slit by its width), sample 3 out of reach.
        let positions: Vec<f64> = (0..6).map(|k| -1.0 + 0.5 * k as f64).collect();
        let order: Vec<usize> = (0..6).collect();
        let mut edges = Vec::new();
        let mut boxes = Vec::new();
        box_edges(
            &g,
            0.0,
            &order,
            |j| positions[j],
            |s| s != positions[3],
            &mut edges,
            |j, lower, upper| boxes.push((j, lower, upper)),
        );
        assert_eq!(boxes.len(), 5);
        // 0, 1, 2 share: 4 edges; 4, 5 after the gap: 3 more.
        assert_eq!(edges.len(), 7);
        for w in boxes.windows(2) {
            let adjacent = w[1].0 == w[0].0 + 1;
            assert_eq!(w[1].1 == w[0].2, adjacent, "{w:?}");
        }
        for &(j, lower, upper) in &boxes {
            let (a, b) = g.interval(positions[j]);
            assert!(
                (edges[lower] - a).abs() <= 1e-12 && edges[upper] == b,
                "sample {j}"
            );
        }
    }

    fn phi_cdf(x: f64) -> f64 {
        0.5 * libm::erfc(-x / std::f64::consts::SQRT_2)
    }

    #[test]
    fn cdf_difference_matches_direct_formula_where_that_is_accurate() {
        for &(a, b) in &[
            (-1.0, 0.5),
            (0.2, 1.7),
            (-3.0, -2.0),
            (2.0, 2.5),
            (-0.5, 0.5),
        ] {
            let direct = (phi_cdf(b) - phi_cdf(a)).ln();
            assert!((ln_cdf_diff(a, b) - direct).abs() < 1e-12, "{a} {b}");
        }
    }

    #[test]
    fn far_tails_are_finite_and_match_the_asymptotic_expansion() {
        // Q(a) - Q(b) for a = 1000, b = 1000.5: ~ phi(a)/a, since Q(b) << Q(a).
        let v = ln_cdf_diff(1000.0, 1000.5);
        let asym = ln_phi(1000.0) - 1000f64.ln() + (1.0f64 - 1.0 / 1e6).ln();
        assert!(v.is_finite());
        assert!((v - asym).abs() < 1e-6, "{v} vs {asym}");
        // Mirror symmetry.
        assert!((ln_cdf_diff(-1000.5, -1000.0) - v).abs() < 1e-12);
    }

    #[test]
    fn narrow_interval_uses_the_midpoint_rule_continuously() {
        // Just above and just below the switch give the same value.
        let a = 0.7;
        let below = ln_cdf_diff(a, a + 0.999e-3);
        let above = ln_cdf_diff(a, a + 1.001e-3);
        assert!((above - below - (1.001f64 / 0.999).ln()).abs() < 1e-6);
    }

    #[test]
    fn masses_and_posteriors_from_edges_are_those_from_the_interval_bit_for_bit() {
        let g = BoxedGaussian {
            mean: 0.3,
            sigma: 0.4,
            width: 0.75,
        };
        for j in -400..400 {
            let s = f64::from(j) * 0.0137;
            let (a, b) = g.interval(s);
            let (ea, eb) = (Edge::new(a), Edge::new(b));
            assert_eq!(
                mass_between(&ea, &eb).to_bits(),
                cdf_diff(a, b).to_bits(),
                "{s}"
            );
            let tail = mass_between(&Edge::tail_only(a), &Edge::tail_only(b));
            assert_eq!(tail.to_bits(), cdf_diff(a, b).to_bits());
            assert_eq!(g.density_between(&ea, &eb), g.density(s));
            // The linear-space posterior against the log-space one (an independent form).
            let lin = g.posterior_between(&ea, &eb).unwrap();
            let log = g.posterior(s);
            assert!((lin.density.ln() - log.ln_density).abs() < 1e-9, "{s}");
            assert!((lin.mean - log.mean).abs() < 1e-9, "{s}");
            assert!(
                (lin.variance - log.variance).abs() < 1e-6 * g.width * g.width,
                "{s}"
            );
        }
        // Nearly empty boxes take the midpoint rule, as cdf_diff does.
        let (a, b) = (Edge::new(0.7), Edge::new(0.7 + 1e-4));
        assert_eq!(mass_between(&a, &b), cdf_diff(0.7, 0.7 + 1e-4));
    }

    #[test]
    fn boxed_density_integrates_to_one() {
        let g = BoxedGaussian {
            mean: 0.3,
            sigma: 0.4,
            width: 0.75,
        };
        let step = 1e-3;
        let total: f64 = (-8000..8000)
            .map(|i| g.ln_density(i as f64 * step).exp() * step)
            .sum();
        assert!((total - 1.0).abs() < 1e-6, "{total}");
    }

    #[test]
    fn posterior_moments_match_numerical_integration() {
        let g = BoxedGaussian {
            mean: -0.2,
            sigma: 0.5,
            width: 0.6,
        };
        for &s in &[-0.2, 0.4, 1.5, -2.0] {
            let p = g.posterior(s);
            // Integrate x * N(x) over [s - W/2, s + W/2].
            let n = 20000;
            let (lo, hi) = (s - 0.3, s + 0.3);
            let dx = (hi - lo) / n as f64;
            let (mut z, mut m1, mut m2) = (0.0, 0.0, 0.0);
            for i in 0..n {
                let x = lo + (i as f64 + 0.5) * dx;
                let w = (-0.5 * ((x - g.mean) / g.sigma).powi(2)).exp();
                z += w;
                m1 += w * x;
                m2 += w * x * x;
            }
            let mean = m1 / z;
            let var = m2 / z - mean * mean;
            assert!((p.mean - mean).abs() < 1e-7, "s={s}: {} vs {mean}", p.mean);
            assert!(
                (p.variance - var).abs() < 1e-7,
                "s={s}: {} vs {var}",
                p.variance
            );
        }
    }

    #[test]
    fn posterior_far_in_the_tail_sits_at_the_near_edge_of_the_slit() {
        let g = BoxedGaussian {
            mean: 0.0,
            sigma: 0.01,
            width: 0.5,
        };
        let p = g.posterior(50.0);
        assert!(p.ln_density.is_finite());
        assert!(p.mean > 49.75 && p.mean < 49.76, "{}", p.mean);
        assert!(p.variance >= 0.0 && p.variance < 1e-6);
    }

    #[test]
    fn linear_posterior_matches_the_log_space_one_wherever_it_is_defined() {
        let mut compared = 0;
        for sigma in [0.01, 0.3, 2.0, 15.0] {
            for width in [1e-4, 0.05, 0.6, 3.0] {
                let g = BoxedGaussian {
                    mean: 0.25,
                    sigma,
                    width,
                };
                for i in -200..=200 {
                    let s = 0.25 + f64::from(i) * 0.37 * sigma.max(width);
                    let log = g.posterior(s);
                    match g.posterior_linear(s) {
                        Some(lin) => {
                            compared += 1;
                            let rel = (lin.density / log.ln_density.exp() - 1.0).abs();
                            assert!(rel < 1e-9, "s={s} sigma={sigma} W={width}: {rel}");
                            let scale = sigma.max(width);
                            assert!((lin.mean - log.mean).abs() < 1e-9 * scale, "s={s}");
                            // The variance is a difference of terms ~ d^2 (d sigmas out) in
                            // both forms: it carries their normalisers' rounding times d^2.
                            let d = (s - g.mean) / sigma;
                            let tol = 1e-9 * scale * scale + 1e-11 * (1.0 + d * d) * sigma * sigma;
                            assert!(
                                (lin.variance - log.variance).abs() < tol,
                                "s={s} sigma={sigma} W={width}: {} vs {}",
                                lin.variance,
                                log.variance
                            );
                        }
                        // Only where the density is beyond the linear range.
                        None => assert!(log.ln_density + width.ln() < LINEAR_MIN.ln() + 1e-6),
                    }
                }
            }
        }
        assert!(compared > 1000, "{compared}");
    }

    #[test]
    fn linear_cdf_difference_matches_the_log_space_one_until_it_underflows() {
        let mut worst = 0.0f64;
        for i in 0..400 {
            let a = -40.0 + 0.2 * f64::from(i);
            for width in [1e-5, 5e-4, 2e-3, 0.05, 0.7, 3.0, 25.0] {
                let b = a + width;
                let linear = cdf_diff(a, b);
                let reference = ln_cdf_diff(a, b).exp();
                if reference > 1e-280 {
                    let rel = (linear / reference - 1.0).abs();
                    worst = worst.max(rel);
                    assert!(rel < 1e-9, "a={a} w={width}: {linear} vs {reference}");
                } else {
                    assert!(linear <= 1e-270, "a={a} w={width}: {linear}");
                }
            }
        }
        assert!(worst > 0.0, "the comparison ran");
    }
}

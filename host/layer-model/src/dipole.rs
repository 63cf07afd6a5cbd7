//! Baseline: a per-pixel isotropic diffusion profile, the classical dipole (Jensen et al. 2001).
//!
//! `R_d(r) = a'/(4 pi) [z_r (1 + s_tr d_r) e^(-s_tr d_r) / d_r^3 + z_v (1 + s_tr d_v) e^(-s_tr d_v) / d_v^3]`
//! with `s_t' = s_a + s_s'`, `a' = s_s'/s_t'`, `s_tr = sqrt(3 s_a s_t')`, `z_r = 1/s_t'`,
//! `z_v = z_r (1 + 4A/3)`, `A = (1 + F_dr)/(1 - F_dr)`, and the total diffuse reflectance
//! `R = a'/2 (1 + e^(-4/3 A sqrt(3(1 - a')))) e^(-sqrt(3(1 - a')))`.
//!
//! Fitting per pixel (Jensen's recipe): `a'` from the measured total diffuse reflectance
//! (`sum_p F_p / sum_p E_p W_p`, the same quantity that scales the layer weights), then the scale
//! `s_t'` by maximising the profiles' likelihood (a coarse log grid then Brent's method, or
//! Newton's method from the neighbouring tile's optimum, with a walk and a parabola's vertex
//! where Newton's method cannot settle). Rendering: the profile in units
//! of `1/s_t'` is represented once per `a'` as a sum of Gaussians (non-negative least squares on
//! fixed widths), so the dipole renders through the same splatter as MLSSS, centred (depth 0): the
//! line integral of a 2-D Gaussian is the 1-D Gaussian of the same sigma, which also makes the
//! profile likelihood exact through the slit box.

use std::f64::consts::PI;

use super::boxed_gaussian::{BoxedGaussian, Edge, SHARED_EDGE, mass_between};
#[cfg(test)]
use super::em_free::{self, Component};
use super::mixture::{NEGLIGIBLE_SIGMAS, by_position, image_reaches};
use super::mixture::{Profile, relative_information};
use super::render::{ShapeLayer, SplatLayer};

/// Widths (units of `1/s_t'`) of the Gaussians representing the dipole.
const WIDTHS: [f64; 10] = [0.08, 0.16, 0.32, 0.6, 1.1, 2.0, 3.6, 6.5, 12.0, 22.0];

/// Diffuse Fresnel reflectance (Egan & Hilgeman fit used by Jensen 2001).
pub fn fresnel_diffuse(eta: f64) -> f64 {
    -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta
}

fn boundary_a(eta: f64) -> f64 {
    let f = fresnel_diffuse(eta);
    (1.0 + f) / (1.0 - f)
}

/// `R_d(r)` (1/mm^2) for reduced albedo `albedo` and `s_t' = 1` (lengths in mean free paths).
pub fn profile_unit(r: f64, albedo: f64, eta: f64) -> f64 {
    let sigma_a = 1.0 - albedo;
    let s_tr = (3.0 * sigma_a).sqrt();
    let z_r = 1.0;
    let z_v = z_r * (1.0 + 4.0 / 3.0 * boundary_a(eta));
    let term = |z: f64| {
        let d = (r * r + z * z).sqrt();
        z * (1.0 + s_tr * d) * (-s_tr * d).exp() / (d * d * d)
    };
    albedo / (4.0 * PI) * (term(z_r) + term(z_v))
}

/// Total diffuse reflectance of the dipole.
pub fn total_reflectance(albedo: f64, eta: f64) -> f64 {
    let root = (3.0 * (1.0 - albedo)).sqrt();
    albedo / 2.0 * (1.0 + (-4.0 / 3.0 * boundary_a(eta) * root).exp()) * (-root).exp()
}

/// Reduced albedo giving total diffuse reflectance `r` (bisection; clamped to the reachable range).
pub fn albedo_for_reflectance(r: f64, eta: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, 1.0);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if total_reflectance(mid, eta) < r {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Non-negative least squares (Lawson-Hanson) for the small systems here.
fn nnls(a: &[Vec<f64>], b: &[f64]) -> Vec<f64> {
    let n = a[0].len();
    let mut x = vec![0.0; n];
    let mut passive = vec![false; n];
    for _ in 0..(3 * n) {
        let resid: Vec<f64> = (0..b.len())
            .map(|i| b[i] - (0..n).map(|j| a[i][j] * x[j]).sum::<f64>())
            .collect();
        let grad: Vec<f64> = (0..n)
            .map(|j| (0..b.len()).map(|i| a[i][j] * resid[i]).sum())
            .collect();
        let Some((j, &g)) = grad
            .iter()
            .enumerate()
            .filter(|(j, _)| !passive[*j])
            .max_by(|a, b| a.1.total_cmp(b.1))
        else {
            break;
        };
        if g <= 1e-14 {
            break;
        }
        passive[j] = true;
        loop {
            let idx: Vec<usize> = (0..n).filter(|&j| passive[j]).collect();
            let z = least_squares(a, b, &idx);
            if z.iter().all(|&v| v > 0.0) {
                for (k, &j) in idx.iter().enumerate() {
                    x[j] = z[k];
                }
                break;
            }
            // Step back towards the feasible region and drop the variables that hit zero.
            let mut alpha = 1.0f64;
            for (k, &j) in idx.iter().enumerate() {
                if z[k] <= 0.0 {
                    alpha = alpha.min(x[j] / (x[j] - z[k]));
                }
            }
            for (k, &j) in idx.iter().enumerate() {
                x[j] += alpha * (z[k] - x[j]);
                if x[j] <= 1e-15 {
                    x[j] = 0.0;
                    passive[j] = false;
                }
            }
        }
    }
    x
}

fn least_squares(a: &[Vec<f64>], b: &[f64], idx: &[usize]) -> Vec<f64> {
    let m = idx.len();
    let ata = nalgebra::DMatrix::from_fn(m, m, |p, q| {
        a.iter().map(|row| row[idx[p]] * row[idx[q]]).sum::<f64>()
    });
    let atb = nalgebra::DVector::from_fn(m, |p, _| {
        a.iter()
            .zip(b)
            .map(|(row, bi)| row[idx[p]] * bi)
            .sum::<f64>()
    });
    ata.cholesky()
        .map(|c| c.solve(&atb).iter().copied().collect())
        .unwrap_or_else(|| vec![0.0; m])
}

/// Weights of the Gaussians (2-D, unit mass each, widths `WIDTHS`) summing to the unit-scale
/// dipole profile, fitted on log-spaced radii with relative weighting (tails matter for skin).
pub fn gaussian_representation(albedo: f64, eta: f64) -> Vec<f64> {
    // Radii out to where the profile has fallen to `PROFILE_FLOOR` of its value at the first:
    // beyond, the relative rows' scales (1/target) reach 1e20 and more for a low albedo (dark
    // skin: the profile falls fast) and the least squares returned all-zero weights, an empty
    // dipole for every pixel-channel below reflectance ~0.14.
    const PROFILE_FLOOR: f64 = 1e-9;
    let peak = profile_unit(0.01, albedo, eta);
    let radii: Vec<f64> = (0..60)
        .map(|i| 0.01 * 1.15f64.powi(i))
        .filter(|&r| profile_unit(r, albedo, eta) >= PROFILE_FLOOR * peak)
        .collect();
    let g2 = |r: f64, s: f64| (-0.5 * (r / s).powi(2)).exp() / (2.0 * PI * s * s);
    // Relative least squares: rows scaled by 1/target; each row also weighted by r (area).
    let rows: Vec<(Vec<f64>, f64)> = radii
        .iter()
        .map(|&r| {
            let t = profile_unit(r, albedo, eta).max(1e-300);
            let scale = r.sqrt() / t;
            (
                WIDTHS.iter().map(|&s| g2(r, s) * scale).collect(),
                t * scale,
            )
        })
        .collect();
    let a: Vec<Vec<f64>> = rows.iter().map(|r| r.0.clone()).collect();
    let b: Vec<f64> = rows.iter().map(|r| r.1).collect();
    nnls(&a, &b)
}

/// A fitted dipole for one pixel and channel.
#[derive(Debug, Clone, PartialEq)]
pub struct DipoleFit {
    /// Reduced albedo of the table row used: the one nearest the albedo whose total diffuse
    /// reflectance is `reflectance`.
    pub albedo: f64,
    /// Reduced extinction `s_t'` (1/mm).
    pub extinction: f64,
    /// Total diffuse reflectance the weights are scaled to.
    pub reflectance: f64,
    /// Layers for the renderer (all at depth 0).
    pub layers: Vec<SplatLayer>,
}

/// Range of the reduced extinction `s_t'` searched (1/mm).
const EXTINCTION_RANGE: (f64, f64) = (0.1, 50.0);
/// Relative resolution of Brent's method in the extinction search (the global search, and a
/// walk from a hint that meets a range end; see [`maximise_in_log_near`]).
const EXTINCTION_RESOLUTION: f64 = 1.02;

/// Maximum `(f(x), x)` of `f` over `[range.0, range.1]` in log `x`: a log grid of `grid` points
/// (global: the score may have shallow side maxima), then Brent's method inside the grid cells
/// around the best point, to a ratio `resolution` between the bracket ends. The likelihood is
/// smooth and unimodal within one grid cell, so ~`grid + 4` evaluations replace a fine grid.
fn maximise_in_log(
    mut f: impl FnMut(f64) -> f64,
    range: (f64, f64),
    grid: usize,
    resolution: f64,
) -> (f64, f64) {
    let (lo, hi) = (range.0.ln(), range.1.ln());
    let step = (hi - lo) / (grid.max(2) - 1) as f64;
    let xs: Vec<f64> = (0..grid.max(2)).map(|i| lo + step * i as f64).collect();
    let values: Vec<f64> = xs.iter().map(|&x| f(x.exp())).collect();
    let best = (0..xs.len())
        .max_by(|&a, &b| values[a].total_cmp(&values[b]))
        .unwrap_or(0);
    let (left, right) = (best.saturating_sub(1), (best + 1).min(xs.len() - 1));
    brent(
        f,
        (xs[left], xs[right]),
        [
            (values[best], xs[best]),
            (values[left], xs[left]),
            (values[right], xs[right]),
        ],
        resolution,
    )
}

/// Step (in log `x`) of the local bracket search of [`maximise_in_log_near`].
const NEAR_STEP: f64 = 0.2;

/// Maximum `(f(x), x)` of `f` over `[range.0, range.1]` in log `x`, starting from `hint` (e.g. a
/// neighbour's optimum; the fit's fallback where [`newton_in_log`] gives up): walks uphill in steps of [`NEAR_STEP`] until the maximum is bracketed,
/// then [`refined_vertex`] of the bracket's three points (Brent's method when the bracket meets
/// a range end). About 4 evaluations when the hint is close, against ~12 for the global
/// [`maximise_in_log`]; finds the maximum of the hint's basin only.
///
/// Why not Brent's method down to `resolution`: its ~3 more evaluations per pixel-channel (7.2
/// in all on the full-size head, 4.34 now) were 40 % of the dipole baseline's CPU time, and the
/// held-out error can hardly see the difference: on the full-size head (projector 3 held out)
/// the dipole's global relative error moved from 0.097048 to 0.097057 (+0.01 %). The vertex of
/// the walked bracket alone (3.35 evaluations) moved it by +0.07 % there, but by +0.44 % (and
/// its back-scatter errors by +0.6 %) on a quick head (skin III, seed 4817).
fn maximise_in_log_near(
    mut f: impl FnMut(f64) -> f64,
    hint: f64,
    range: (f64, f64),
    resolution: f64,
) -> (f64, f64) {
    let (lo, hi) = (range.0.ln(), range.1.ln());
    let mut m = hint.ln().clamp(lo, hi);
    let mut fm = f(m.exp());
    let (mut l, mut r) = ((m - NEAR_STEP).max(lo), (m + NEAR_STEP).min(hi));
    let (mut fl, mut fr) = (f(l.exp()), f(r.exp()));
    // Each move shifts the bracket one step uphill; the range bounds the walk.
    for _ in 0..((hi - lo) / NEAR_STEP).ceil() as usize {
        if fl > fm && l > lo {
            (r, fr, m, fm) = (m, fm, l, fl);
            l = (m - NEAR_STEP).max(lo);
            fl = f(l.exp());
        } else if fr > fm && r < hi {
            (l, fl, m, fm) = (m, fm, r, fr);
            r = (m + NEAR_STEP).min(hi);
            fr = f(r.exp());
        } else {
            break;
        }
    }
    // After the walk `m` is the best of the three (or a range end). Inside the range the three
    // are a step apart: the log-likelihood is close to a parabola over a bracket this narrow.
    let finite = fm.is_finite() && fl.is_finite() && fr.is_finite();
    if l > lo && r < hi && finite && fm >= fl && fm >= fr {
        return refined_vertex(f, [(l, fl), (m, fm), (r, fr)]);
    }
    let mut points = [(fm, m), (fl, l), (fr, r)];
    points.sort_by(|a, b| b.0.total_cmp(&a.0));
    brent(f, (l, r), points, resolution)
}

/// Largest move (in log `x`) of one step of [`newton_in_log`]: about the walk's bracket
/// ([`NEAR_STEP`]), so that a step from a far or poorly modelled point stays local.
const NEWTON_MAX_STEP: f64 = 0.3;

/// [`newton_in_log`] stops once a step is shorter than this (in log `x`): Newton's method
/// converges quadratically, so the unscored point it returns is then within ~`1e-3` of the
/// maximum, as the walk's refined vertex was (Brent's method to [`EXTINCTION_RESOLUTION`]:
/// `0.005`). Why not tighter: at `0.01` the full-size head's fits took 1.94 scores instead of
/// 1.69 (1.59 against 1.43 CPU-s on one thread) and its held-out figures moved by at most
/// 0.005 % (the dipole's global relative error 0.0970451 against 0.0970444).
const NEWTON_TOLERANCE: f64 = 0.03;

/// Scores [`newton_in_log`] may take before it gives up.
const NEWTON_SCORES: usize = 5;

/// The maximum `(f(x), x)` of `f` over `range` in log `x` by Newton's method from `hint`
/// (e.g. a neighbour's optimum): `f(x)` gives the function and its first two derivatives in
/// `ln x`. Stops when a step is below [`NEWTON_TOLERANCE`] and returns the point it leads to
/// (not scored; the value is the last one scored). `None` (the caller searches otherwise)
/// where `f` gives none, the function is not concave at a scored point, a step would leave
/// the range, or [`NEWTON_SCORES`] scores did not settle.
///
/// Why: the walk of [`maximise_in_log_near`] needs at least four scores (the bracket and its
/// vertex): 242 619 for the full-size head's 55 893 pixel-channels. From the neighbour's
/// optimum (55 380 of them) Newton's method took 1.69 scores with derivatives on average
/// (93 494; plain scores, of the rows' first tiles' grid searches and of the walk where
/// Newton's method gave up, 7 023): the dipole baseline 2.68 / 2.57 -> 1.44 / 1.41 CPU-s on
/// one thread. It also lands a little closer to the maximum than the walk's vertex: the
/// dipole's held-out global relative error 0.0970573 -> 0.0970444 there (Brent's method to
/// 2 %: 0.097048).
fn newton_in_log(
    mut f: impl FnMut(f64) -> Option<[f64; 3]>,
    hint: f64,
    range: (f64, f64),
) -> Option<(f64, f64)> {
    let (lo, hi) = (range.0.ln(), range.1.ln());
    let inside = |u: f64| u > lo && u < hi;
    let mut u = hint.ln();
    if !inside(u) {
        return None;
    }
    for _ in 0..NEWTON_SCORES {
        let [value, slope, curvature] = f(u.exp())?;
        if curvature.is_nan() || curvature >= 0.0 {
            return None;
        }
        let step = -slope / curvature;
        let next = u + step.clamp(-NEWTON_MAX_STEP, NEWTON_MAX_STEP);
        if !inside(next) {
            return None;
        }
        if step.abs() < NEWTON_TOLERANCE {
            return Some((value, next.exp()));
        }
        u = next;
    }
    None
}

/// The maximum `(value, exp x)` of `f(exp x)` near a bracket `[(l, f(l)), (m, f(m)), (r, f(r))]`
/// (by position, the middle one the best): `f` scored once at the vertex of the parabola
/// through the three, then the vertex of the parabola through the best of the four points and
/// its neighbours on either side (not scored). The value is the best scored one.
fn refined_vertex(mut f: impl FnMut(f64) -> f64, bracket: [(f64, f64); 3]) -> (f64, f64) {
    let [(l, fl), (m, fm), (r, fr)] = bracket;
    let u = parabola_vertex((l, fl), (m, fm), (r, fr)).clamp(l, r);
    let fu = f(u.exp());
    if !fu.is_finite() {
        return (fm, m.exp());
    }
    let mut points = [(l, fl), (m, fm), (r, fr), (u, fu)];
    points.sort_by(|a, b| a.0.total_cmp(&b.0));
    // The best inner point (an end point is never better than the middle of the bracket).
    let best = (0..4)
        .max_by(|&a, &b| points[a].1.total_cmp(&points[b].1))
        .unwrap_or(1)
        .clamp(1, 2);
    let (a, b, c) = (points[best - 1], points[best], points[best + 1]);
    let v = parabola_vertex(a, b, c).clamp(a.0, c.0);
    let v = if v.is_finite() { v } else { b.0 };
    (b.1.max(fm), v.exp())
}

/// The `x` of the vertex of the parabola through three points `(x, f)` (`b.0` when they are on
/// a line).
fn parabola_vertex(a: (f64, f64), b: (f64, f64), c: (f64, f64)) -> f64 {
    let (p, q) = ((b.0 - a.0) * (b.1 - c.1), (b.0 - c.0) * (b.1 - a.1));
    let den = p - q;
    if den == 0.0 || !den.is_finite() {
        return b.0;
    }
    b.0 - 0.5 * ((b.0 - a.0) * p - (b.0 - c.0) * q) / den
}

/// Brent's method (parabolic interpolation, golden-section steps when a parabola is not
/// trusted; Numerical Recipes' `brent`) for the maximum of `f(exp x)` over `x` in `bracket`,
/// down to a bracket of about `ln resolution`. `points` are evaluated points inside the bracket,
/// best first (`(value, x)`); the first step is the vertex of the parabola through them, so a
/// smooth maximum takes a few evaluations (golden section alone needs ~7 more for a 0.4 bracket).
/// Returns the best point evaluated, as `(value, exp x)`.
fn brent(
    mut f: impl FnMut(f64) -> f64,
    bracket: (f64, f64),
    points: [(f64, f64); 3],
    resolution: f64,
) -> (f64, f64) {
    const GOLDEN: f64 = 0.381_966_011_250_105;
    // Minimise g = -f; NaN values count as worst.
    let g = |v: f64| if v.is_nan() { f64::INFINITY } else { -v };
    let (mut a, mut b) = bracket;
    let [(vx, mut x), (vw, mut w), (vv, mut v)] = points;
    let (mut fx, mut fw, mut fv) = (g(vx), g(vw), g(vv));
    let tol = 0.25 * resolution.ln();
    // A large previous step lets the first step be parabolic.
    let (mut d, mut e) = (0.0f64, b - a);
    for _ in 0..100 {
        let xm = 0.5 * (a + b);
        if (x - xm).abs() <= 2.0 * tol - 0.5 * (b - a) {
            break;
        }
        let mut golden = true;
        if e.abs() > tol {
            let r = (x - w) * (fx - fv);
            let mut q = (x - v) * (fx - fw);
            let mut p = (x - v) * q - (x - w) * r;
            q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            }
            q = q.abs();
            let previous = e;
            e = d;
            if p.abs() < (0.5 * q * previous).abs() && p > q * (a - x) && p < q * (b - x) {
                d = p / q;
                let u = x + d;
                if u - a < 2.0 * tol || b - u < 2.0 * tol {
                    d = tol.copysign(xm - x);
                }
                golden = false;
            }
        }
        if golden {
            e = if x >= xm { a - x } else { b - x };
            d = GOLDEN * e;
        }
        let u = if d.abs() >= tol {
            x + d
        } else {
            x + tol.copysign(d)
        };
        let fu = g(f(u.exp()));
        if fu <= fx {
            if u >= x {
                a = x;
            } else {
                b = x;
            }
            (v, fv, w, fw, x, fx) = (w, fw, x, fx, u, fu);
        } else {
            if u < x {
                a = u;
            } else {
                b = u;
            }
            if fu <= fw || w == x {
                (v, fv, w, fw) = (w, fw, u, fu);
            } else if fu <= fv || v == x || v == w {
                (v, fv) = (u, fu);
            }
        }
    }
    (-fx, x.exp())
}

/// A pixel-channel's profiles prepared once for the extinction search: each profile's samples
/// with their weights normalised to its relative information, as the EM's likelihood
/// (`em_free::log_likelihood`) weighs them, and the same profiles left out. The score of an
/// extinction is then computed without allocating and with densities summed in linear space
/// (the EM's log-space sum needs a logarithm and an exponential per term); a sample whose
/// density underflows is summed in log space instead. Equal to the EM's likelihood summed over
/// the profiles to ~1e-12 relative.
struct PreparedProfiles<'a> {
    profiles: Vec<PreparedProfile<'a>>,
}

/// One usable profile of [`PreparedProfiles`].
struct PreparedProfile<'a> {
    profile: &'a Profile,
    /// Normalised weight of each sample.
    weights: Vec<f64>,
    /// The slit images (one, or three with a period), their boxes in order of position.
    images: Vec<PreparedImage>,
}

/// The boxes of the samples with weight seen from one slit image.
struct PreparedImage {
    offset: f64,
    boxes: Vec<PreparedBox>,
}

/// A sample's slit box relative to an image's centre, in mm: what `BoxedGaussian::interval`
/// and `image_reaches` computed from the position at every score, made once per fit. Why: the
/// score (~7 per pixel-channel, ~600 boxes each at full size) spent most of its time in the
/// two divisions by sigma per box and the one by the slit width per density; with the edges in
/// mm a component standardises them by one multiplication (`ext / width`), and its weight
/// takes the slit width's division once.
#[derive(Debug, Clone, Copy)]
struct PreparedBox {
    sample: usize,
    /// `s - offset - W/2` and `s - offset + W/2`.
    lower: f64,
    upper: f64,
    /// `|s - offset| - W/2`: how far the box is from the image's centre (the reach test).
    distance: f64,
    /// The lower edge is the previous box's upper edge (a sweep puts slits edge to edge; the
    /// criterion of [`box_edges`](crate::boxed_gaussian::box_edges)): it is computed once.
    shares_lower: bool,
}

impl PreparedImage {
    /// The boxes of the samples `order` (by position) of `prof` seen from the image at `offset`.
    fn new(prof: &Profile, order: &[usize], offset: f64) -> Self {
        let half = 0.5 * prof.slit_width;
        let mut previous_upper = f64::NAN;
        let boxes = order
            .iter()
            .map(|&j| {
                let x = prof.samples[j].s - offset;
                let (lower, upper) = (x - half, x + half);
                let shares_lower = (lower - previous_upper).abs() <= SHARED_EDGE * (upper - lower);
                previous_upper = upper;
                PreparedBox {
                    sample: j,
                    lower,
                    upper,
                    distance: x.abs() - half,
                    shares_lower,
                }
            })
            .collect();
        Self { offset, boxes }
    }

    /// Calls `add(sample, lower, upper)` for each box with its edges made by `edge` at the
    /// box's bounds times `scale`, skipping the boxes of a side image further than
    /// [`NEGLIGIBLE_SIGMAS`] sigmas (as `image_reaches`); shared edges are made once.
    #[inline(always)]
    fn for_each_box<E: Copy>(
        &self,
        scale: f64,
        edge: impl Fn(f64) -> E,
        mut add: impl FnMut(usize, &E, &E),
    ) {
        let reach = NEGLIGIBLE_SIGMAS / scale;
        let central = self.offset == 0.0;
        let mut previous: Option<E> = None;
        for b in &self.boxes {
            if !central && b.distance > reach {
                previous = None;
                continue;
            }
            let lower = match previous {
                Some(e) if b.shares_lower => e,
                _ => edge(b.lower * scale),
            };
            let upper = edge(b.upper * scale);
            add(b.sample, &lower, &upper);
            previous = Some(upper);
        }
    }

    /// Adds `weight` times the mass of the centred Gaussian of standard deviation `1 / scale`
    /// in each box (`scale`: `ext / width`) to `densities` ([`PreparedImage::for_each_box`]).
    fn add_masses(&self, scale: f64, weight: f64, densities: &mut [f64]) {
        self.for_each_box(scale, Edge::tail_only_fast, |sample, lower, upper| {
            densities[sample] += weight * mass_between(lower, upper);
        });
    }

    /// [`PreparedImage::add_masses`] with the mass's first two derivatives in `ln ext`
    /// (`sums[j]`: mass, slope, curvature). A box edge `z` scales with the extinction, so
    /// `d Phi(z) / d ln ext = z phi(z)` and its derivative `z phi(z) (1 - z^2)`: each edge's
    /// density gives both, one exponential per edge as for the mass.
    fn add_masses_and_slopes(&self, scale: f64, weight: f64, sums: &mut [[f64; 3]]) {
        self.for_each_box(scale, SlopedEdge::new, |sample, lower, upper| {
            let sum = &mut sums[sample];
            sum[0] += weight * mass_between(&lower.edge, &upper.edge);
            sum[1] += weight * (upper.slope - lower.slope);
            sum[2] += weight * (upper.curvature - lower.curvature);
        });
    }
}

/// A box edge with the derivatives of `Phi(z)` in `ln ext` ([`PreparedImage::add_masses_and_slopes`]).
#[derive(Debug, Clone, Copy)]
struct SlopedEdge {
    edge: Edge,
    /// `z phi(z)`.
    slope: f64,
    /// `z phi(z) (1 - z^2)`.
    curvature: f64,
}

impl SlopedEdge {
    #[inline]
    fn new(z: f64) -> Self {
        let edge = Edge::with_density_fast(z);
        let slope = z * edge.phi();
        Self {
            edge,
            slope,
            curvature: slope * (1.0 - z * z),
        }
    }
}

/// Below this a sample's summed density is recomputed in log space.
const LINEAR_DENSITY_FLOOR: f64 = 1e-250;

impl<'a> PreparedProfiles<'a> {
    /// Profiles the EM's likelihood refuses (no signal, bad slit width, non-finite samples) are
    /// left out, as the score's `filter_map` over `log_likelihood` left them out.
    fn new(profiles: &'a [Profile]) -> Self {
        let usable = |p: &Profile| {
            p.slit_width > 0.0
                && p.slit_width.is_finite()
                && p.samples.iter().all(|s| s.s.is_finite() && s.y.is_finite())
        };
        let usable: Vec<&Profile> = profiles.iter().filter(|p| usable(p)).collect();
        let trust = relative_information(usable.iter().copied());
        Self {
            profiles: usable
                .into_iter()
                .zip(trust)
                .filter_map(|(p, trust)| {
                    let total = p.total();
                    (total > 0.0).then(|| PreparedProfile::new(p, trust, total))
                })
                .collect(),
        }
    }

    /// Sum over the profiles of the mean log-density per unit weight of the centred mixture
    /// `components` (`(weight, width in units of 1/s_t')`) at reduced extinction `ext`, each
    /// Gaussian boxed by the slit and wrapped over one period either side (images further than
    /// `NEGLIGIBLE_SIGMAS` left out, as the EM leaves them out).
    fn log_likelihood(&self, components: &[(f64, f64)], ext: f64) -> f64 {
        let mut densities = Vec::new();
        self.profiles
            .iter()
            .map(|p| p.log_likelihood(components, ext, &mut densities))
            .sum()
    }

    /// [`PreparedProfiles::log_likelihood`] and its first two derivatives in `ln ext`, the
    /// value bit for bit the same; `None` where a sample's density is below
    /// [`LINEAR_DENSITY_FLOOR`] (its log-space sum has no derivatives here) or a sum is not
    /// finite.
    fn log_likelihood_and_slopes(&self, components: &[(f64, f64)], ext: f64) -> Option<[f64; 3]> {
        let mut sums = Vec::new();
        let mut total = [0.0; 3];
        for p in &self.profiles {
            let terms = p.log_likelihood_and_slopes(components, ext, &mut sums)?;
            for (t, x) in total.iter_mut().zip(terms) {
                *t += x;
            }
        }
        total.iter().all(|v| v.is_finite()).then_some(total)
    }
}

impl<'a> PreparedProfile<'a> {
    /// `trust`: the profile's relative information; `total`: its total signal (positive).
    fn new(profile: &'a Profile, trust: f64, total: f64) -> Self {
        let weights: Vec<f64> = profile
            .samples
            .iter()
            .map(|s| trust * s.y.max(0.0) / total)
            .collect();
        let order = by_position(profile, &weights);
        let images = Self::offsets(profile)
            .into_iter()
            .filter(|o| o.is_finite())
            .map(|o| PreparedImage::new(profile, &order, o))
            .collect();
        Self {
            profile,
            weights,
            images,
        }
    }

    /// The images' offsets, NaN for none.
    fn offsets(profile: &Profile) -> [f64; 3] {
        match profile.period {
            Some(t) => [-t, 0.0, t],
            None => [0.0, f64::NAN, f64::NAN],
        }
    }

    /// This profile's term of [`PreparedProfiles::log_likelihood`]; `densities` is scratch.
    fn log_likelihood(&self, components: &[(f64, f64)], ext: f64, densities: &mut Vec<f64>) -> f64 {
        let prof = self.profile;
        densities.clear();
        densities.resize(prof.samples.len(), 0.0);
        let per_width = 1.0 / prof.slit_width;
        for &(weight, width) in components.iter().filter(|c| c.0 > 0.0) {
            let scale = ext / width;
            for image in &self.images {
                image.add_masses(scale, weight * per_width, densities);
            }
        }
        let mut ll = 0.0;
        for (j, (sample, &y)) in prof.samples.iter().zip(&self.weights).enumerate() {
            if y <= 0.0 {
                continue;
            }
            let density = densities[j];
            let ln_density = if density > LINEAR_DENSITY_FLOOR {
                density.ln()
            } else {
                self.ln_density_far(components, ext, sample.s)
            };
            ll += y * ln_density;
        }
        ll
    }

    /// This profile's term of [`PreparedProfiles::log_likelihood_and_slopes`]; `sums` is
    /// scratch. The log-likelihood `sum y ln D` has the slope `sum y D' / D` and the curvature
    /// `sum y (D'' / D - (D' / D)^2)`.
    fn log_likelihood_and_slopes(
        &self,
        components: &[(f64, f64)],
        ext: f64,
        sums: &mut Vec<[f64; 3]>,
    ) -> Option<[f64; 3]> {
        sums.clear();
        sums.resize(self.profile.samples.len(), [0.0; 3]);
        let per_width = 1.0 / self.profile.slit_width;
        for &(weight, width) in components.iter().filter(|c| c.0 > 0.0) {
            let scale = ext / width;
            for image in &self.images {
                image.add_masses_and_slopes(scale, weight * per_width, sums);
            }
        }
        let mut out = [0.0; 3];
        for (&[density, slope, curvature], &y) in sums.iter().zip(&self.weights) {
            if y <= 0.0 {
                continue;
            }
            if density <= LINEAR_DENSITY_FLOOR {
                return None;
            }
            let relative_slope = slope / density;
            out[0] += y * density.ln();
            out[1] += y * relative_slope;
            out[2] += y * (curvature / density - relative_slope * relative_slope);
        }
        Some(out)
    }

    /// The log-density at `s` summed in log space, for a sample whose linear density
    /// underflows.
    fn ln_density_far(&self, components: &[(f64, f64)], ext: f64, s: f64) -> f64 {
        let prof = self.profile;
        let offsets = Self::offsets(prof);
        let ln: Vec<f64> = components
            .iter()
            .filter(|c| c.0 > 0.0)
            .flat_map(|&(weight, width)| {
                let g = BoxedGaussian {
                    mean: 0.0,
                    sigma: width / ext,
                    width: prof.slit_width,
                };
                offsets
                    .into_iter()
                    .filter(move |&o| image_reaches(&g, o, s))
                    .map(move |o| weight.ln() + g.ln_density(s - o))
            })
            .collect();
        let max = ln.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        max + ln.iter().map(|t| (t - max).exp()).sum::<f64>().ln()
    }
}

/// Table of Gaussian representations over the reduced albedo, built once.
#[derive(Debug, Clone)]
pub struct DipoleTable {
    albedos: Vec<f64>,
    /// The rows' weights as fitted (the tests compare them; the fits use `components`).
    #[cfg(test)]
    weights: Vec<Vec<f64>>,
    /// Total diffuse reflectance at the midpoint between consecutive `albedos` (increasing, as
    /// the reflectance is in the albedo): the row nearest in albedo to a measured reflectance
    /// is found by a binary search here instead of inverting the reflectance per pixel (60
    /// bisection steps of two exponentials, for ~4 million pixel-channels at full size).
    midpoint_reflectances: Vec<f64>,
    /// Per row, its Gaussians with weight as `(weight / row total, width)`, in order of width;
    /// `None` for a row whose total is not positive. Made once here: every fit and both
    /// passes of the model's construction (~4 million pixel-channels each at full size)
    /// summed and normalised the row again.
    components: Vec<Option<Vec<(f64, f64)>>>,
}

/// `(weight / total, width)` of the Gaussians with weight of one table row, `None` when the
/// row's total is not positive (no representation).
fn row_components(weights: &[f64]) -> Option<Vec<(f64, f64)>> {
    let total: f64 = weights.iter().sum();
    if total <= 0.0 {
        return None;
    }
    Some(
        WIDTHS
            .iter()
            .zip(weights)
            .filter(|(_, w)| **w > 0.0)
            .map(|(&s, &w)| (w / total, s))
            .collect(),
    )
}

impl DipoleTable {
    pub fn new(eta: f64) -> Self {
        let albedos: Vec<f64> = (0..24).map(|i| 1.0 - 0.6 * 0.75f64.powi(i)).collect();
        let weights: Vec<Vec<f64>> = albedos
            .iter()
            .map(|&a| gaussian_representation(a, eta))
            .collect();
        let midpoint_reflectances = albedos
            .windows(2)
            .map(|a| total_reflectance(0.5 * (a[0] + a[1]), eta))
            .collect();
        let components = weights.iter().map(|w| row_components(w)).collect();
        Self {
            albedos,
            #[cfg(test)]
            weights,
            midpoint_reflectances,
            components,
        }
    }

    /// The row nearest in albedo to the albedo of total diffuse reflectance `reflectance`.
    fn row_for_reflectance(&self, reflectance: f64) -> usize {
        self.midpoint_reflectances
            .partition_point(|&r| r < reflectance)
    }

    #[cfg(test)]
    fn nearest(&self, albedo: f64) -> &[f64] {
        let k = self
            .albedos
            .iter()
            .enumerate()
            .min_by(|a, b| (a.1 - albedo).abs().total_cmp(&(b.1 - albedo).abs()))
            .map_or(0, |(k, _)| k);
        &self.weights[k]
    }

    /// Fits one pixel-channel: `reflectance` = measured total diffuse reflectance, `profiles` the
    /// pixel's slit profiles (shifts ignored: the dipole is centred). `hint`: an extinction to
    /// search around (a neighbour's), else the whole range is searched. `None` without light.
    pub fn fit(
        &self,
        profiles: &[Profile],
        reflectance: f64,
        hint: Option<f64>,
    ) -> Option<DipoleFit> {
        if reflectance.is_nan() || reflectance <= 0.0 {
            return None;
        }
        let components = self.components[self.row_for_reflectance(reflectance)].as_deref()?;
        let prepared = PreparedProfiles::new(profiles);
        let score = |ext: f64| prepared.log_likelihood(components, ext);
        let sloped = |ext: f64| prepared.log_likelihood_and_slopes(components, ext);
        let best = match hint {
            Some(h) if h.is_finite() && h > 0.0 => newton_in_log(sloped, h, EXTINCTION_RANGE)
                .unwrap_or_else(|| {
                    maximise_in_log_near(score, h, EXTINCTION_RANGE, EXTINCTION_RESOLUTION)
                }),
            _ => maximise_in_log(score, EXTINCTION_RANGE, 8, EXTINCTION_RESOLUTION),
        };
        if !best.0.is_finite() {
            return None;
        }
        self.with_extinction(reflectance, best.1)
    }

    /// The dipole of a pixel-channel with total diffuse reflectance `reflectance` and a given
    /// reduced extinction (e.g. fitted on a neighbour: the profile's shape, its own amplitude).
    /// `None` without light.
    pub fn with_extinction(&self, reflectance: f64, extinction: f64) -> Option<DipoleFit> {
        let layers = self.splat_layers(reflectance, extinction)?.collect();
        Some(DipoleFit {
            albedo: self.albedos[self.row_for_reflectance(reflectance)],
            extinction,
            reflectance,
            layers,
        })
    }

    /// The layers of [`DipoleTable::with_extinction`] alone, without allocating (a full-size
    /// model asks for millions): the shape of [`DipoleTable::shape_row`] scaled by the
    /// reflectance.
    pub fn splat_layers(
        &self,
        reflectance: f64,
        extinction: f64,
    ) -> Option<impl Iterator<Item = SplatLayer> + '_> {
        let row = self.shape_row(reflectance, extinction)?;
        Some(
            self.shape_layers(row, extinction)
                .map(move |s| s.scaled(reflectance)),
        )
    }

    /// The table row whose shape gives the layers of a pixel-channel with this reflectance and
    /// extinction; `None` where [`DipoleTable::splat_layers`] gives none.
    pub fn shape_row(&self, reflectance: f64, extinction: f64) -> Option<usize> {
        if reflectance.is_nan() || reflectance <= 0.0 || extinction.is_nan() || extinction <= 0.0 {
            return None;
        }
        let row = self.row_for_reflectance(reflectance);
        self.components[row].as_ref().map(|_| row)
    }

    /// The layers of table row `row` at `extinction` per unit reflectance (weights as the
    /// table holds them, in `f64`, so a pixel's scaled weight is rounded once).
    pub fn shape_layers(
        &self,
        row: usize,
        extinction: f64,
    ) -> impl Iterator<Item = ShapeLayer> + '_ {
        self.components
            .get(row)
            .and_then(|c| c.as_deref())
            .into_iter()
            .flatten()
            .enumerate()
            .map(move |(j, &(w, s))| ShapeLayer {
                index: j as u16,
                weight: w,
                sigma_mm: (s / extinction) as f32,
                depth_mm: 0.0,
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mixture::Sample;

    #[test]
    fn total_reflectance_is_the_integral_of_the_profile_and_inverts() {
        for &albedo in &[0.5, 0.9, 0.99] {
            // Integral of R_d over the plane: sum of 2 pi r R_d(r) dr on a fine log grid.
            let mut total = 0.0;
            let mut r = 1e-5;
            while r < 2000.0 {
                let dr = r * 0.002;
                total += 2.0 * PI * r * profile_unit(r + dr / 2.0, albedo, 1.3) * dr;
                r += dr;
            }
            let closed = total_reflectance(albedo, 1.3);
            assert!(
                (total / closed - 1.0).abs() < 0.01,
                "{albedo}: {total} vs {closed}"
            );
            assert!((albedo_for_reflectance(closed, 1.3) - albedo).abs() < 1e-9);
        }
    }

    #[test]
    fn table_row_from_reflectance_is_the_row_nearest_the_inverted_albedo() {
        // Regression guard for the binary search that replaced the per-pixel inversion.
        let table = DipoleTable::new(1.4);
        for j in 1..2000 {
            let r = 0.6 * f64::from(j) / 2000.0;
            let by_albedo = table.nearest(albedo_for_reflectance(r, 1.4));
            let row = table.row_for_reflectance(r);
            assert_eq!(table.weights[row], by_albedo, "reflectance {r}");
        }
    }

    #[test]
    fn gaussian_sum_follows_the_dipole_within_ten_percent_over_the_range_that_matters() {
        let albedo = 0.95;
        let w = gaussian_representation(albedo, 1.4);
        assert_follows_the_dipole(albedo, &w, &[0.05, 0.2, 0.5, 1.0, 2.0, 4.0, 8.0]);
    }

    #[test]
    fn every_row_of_the_table_represents_its_dipole_down_to_the_lowest_albedo() {
        // Dark skin's low reflectance picks the lowest albedos; their rows were all zero
        // (an empty dipole baseline on types IV-VI). Radii out to 2 mean free paths: the
        // profile of albedo 0.4 has fallen to 1e-3 of its peak there.
        let table = DipoleTable::new(1.4);
        for (albedo, w) in table.albedos.iter().zip(&table.weights) {
            assert!(w.iter().sum::<f64>() > 0.0, "albedo {albedo}: {w:?}");
            assert_follows_the_dipole(*albedo, w, &[0.05, 0.2, 0.5, 1.0, 2.0]);
        }
        // A narrow profile of a dark pixel-channel (reflectance 0.01) now gets a dipole of
        // that reflectance.
        let profile = slit_profile(|s| (-(s * s) / 0.02).exp() + 0.001);
        let fit = table.fit(std::slice::from_ref(&profile), 0.01, None);
        let sum: f32 = fit.map_or(0.0, |f| f.layers.iter().map(|l| l.weight).sum());
        assert!((sum - 0.01).abs() < 1e-6, "{sum}");
    }

    const SLIT_WIDTH: f64 = 0.25;
    const SLIT_PERIOD: f64 = 7.5;

    /// A slit profile of 30 samples across one period, of the slit width and period above, with
    /// `y(s)` at each sample.
    fn slit_profile(y: impl Fn(f64) -> f64) -> Profile {
        let samples = (0..30)
            .map(|i| {
                let s = -SLIT_PERIOD / 2.0 + (i as f64 + 0.5) * SLIT_WIDTH;
                Sample { s, y: y(s) }
            })
            .collect();
        Profile {
            noise: None,
            samples,
            slit_width: SLIT_WIDTH,
            period: Some(SLIT_PERIOD),
            shift_per_depth: 0.0,
        }
    }

    fn assert_follows_the_dipole(albedo: f64, w: &[f64], radii: &[f64]) {
        for &r in radii {
            let approx: f64 = WIDTHS
                .iter()
                .zip(w)
                .map(|(&s, &w)| w * (-0.5 * (r / s).powi(2)).exp() / (2.0 * PI * s * s))
                .sum();
            let exact = profile_unit(r, albedo, 1.4);
            assert!(
                (approx / exact - 1.0).abs() < 0.1,
                "r={r}: {approx} vs {exact}"
            );
        }
    }

    #[test]
    fn log_search_finds_the_maximum_between_grid_points_and_at_the_range_ends() {
        for want in [0.1, 0.37, 3.7, 21.0, 50.0] {
            let f = |x: f64| -(x.ln() - f64::ln(want)).powi(2);
            let (value, at) = maximise_in_log(f, EXTINCTION_RANGE, 8, 1.02);
            assert!((at / want - 1.0).abs() < 0.02, "{want}: found {at}");
            assert!(value <= 0.0 && value > -1e-3);
        }
        for (want, hint) in [(0.37, 0.1), (3.7, 3.0), (3.7, 40.0), (50.0, 20.0)] {
            let f = |x: f64| -(x.ln() - f64::ln(want)).powi(2);
            let (_, at) = maximise_in_log_near(f, hint, EXTINCTION_RANGE, 1.02);
            assert!(
                (at / want - 1.0).abs() < 0.02,
                "{want} from {hint}: found {at}"
            );
        }
        // A narrow global maximum next to a broad side maximum is found by the grid.
        let f = |x: f64| {
            (-(x.ln() - 0.3f64.ln()).powi(2)).exp() + 2.0 * (-(x - 20.0).powi(2) / 8.0).exp()
        };
        let (_, at) = maximise_in_log(f, EXTINCTION_RANGE, 8, 1.02);
        assert!((at / 20.0 - 1.0).abs() < 0.02, "found {at}");
    }

    #[test]
    fn newton_search_finds_a_known_maximum_and_refuses_what_it_cannot_climb() {
        // f(u) = -(u - c)^2 + 0.3 (u - c)^3 in u = ln x: maximum at u = c, derivatives by hand.
        let cubic = |c: f64| {
            move |x: f64| {
                let d = x.ln() - c;
                Some([
                    -d * d + 0.3 * d.powi(3),
                    -2.0 * d + 0.9 * d * d,
                    -2.0 + 1.8 * d,
                ])
            }
        };
        for (want, hint) in [(3.7, 2.9f64), (3.7, 4.6), (0.37, 0.3), (21.0, 30.0)] {
            let (_, at) = newton_in_log(cubic(f64::ln(want)), hint, EXTINCTION_RANGE)
                .unwrap_or_else(|| panic!("{want} from {hint}: no maximum"));
            // Newton's error after a last step `d` is `f''' / (2 f'') d^2`, here 0.45 d^2.
            let bound = 0.45 * NEWTON_TOLERANCE * NEWTON_TOLERANCE;
            assert!((at / want).ln().abs() < bound, "{want} from {hint}: {at}");
        }
        // Convex at the hint (a minimum), the maximum beyond the range, no scores.
        let convex = |x: f64| Some([x.ln().powi(2), 2.0 * x.ln(), 2.0]);
        assert_eq!(newton_in_log(convex, 3.0, EXTINCTION_RANGE), None);
        assert_eq!(
            newton_in_log(cubic(f64::ln(60.0)), 45.0, EXTINCTION_RANGE),
            None
        );
        assert_eq!(newton_in_log(|_| None, 3.0, EXTINCTION_RANGE), None);
    }

    #[test]
    fn score_slopes_are_the_derivatives_of_the_score() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(19);
        let table = DipoleTable::new(1.4);
        let mut compared = 0;
        for case in 0..30 {
            let period: f64 = rng.gen_range(2.0..12.0);
            let profiles: Vec<Profile> = (0..rng.gen_range(1..7))
                .map(|_| {
                    let width: f64 = rng.gen_range(0.05..0.6);
                    let phase = rng.gen_range(0.0..width);
                    let n = (period / width).floor() as usize;
                    Profile {
                        noise: None,
                        // A sweep: slit boxes edge to edge over one period (shared edges).
                        samples: (0..n)
                            .map(|j| Sample {
                                s: -0.5 * period + phase + j as f64 * width,
                                y: rng.gen_range(-0.05..1.0),
                            })
                            .collect(),
                        slit_width: width,
                        period: Some(period),
                        shift_per_depth: 0.0,
                    }
                })
                .collect();
            let Some(components) = table.components[rng.gen_range(0..24)].as_deref() else {
                continue;
            };
            let prepared = PreparedProfiles::new(&profiles);
            for ext in [0.3, 1.7, 6.0, 25.0] {
                let Some([value, slope, curvature]) =
                    prepared.log_likelihood_and_slopes(components, ext)
                else {
                    continue;
                };
                compared += 1;
                // The value is the score's, bit for bit; the derivatives by central
                // differences of the score in ln ext.
                let score = |u: f64| prepared.log_likelihood(components, u.exp());
                assert_eq!(
                    value,
                    prepared.log_likelihood(components, ext),
                    "case {case}, ext {ext}"
                );
                let h = 1e-4;
                let (up, down) = (score(ext.ln() + h), score(ext.ln() - h));
                let numeric_slope = (up - down) / (2.0 * h);
                let numeric_curvature = (up - 2.0 * score(ext.ln()) + down) / (h * h);
                assert!(
                    (slope - numeric_slope).abs() <= 1e-6 * (1.0 + slope.abs()),
                    "case {case}, ext {ext}: slope {slope} vs {numeric_slope}"
                );
                assert!(
                    (curvature - numeric_curvature).abs() <= 1e-3 * (1.0 + curvature.abs()),
                    "case {case}, ext {ext}: curvature {curvature} vs {numeric_curvature}"
                );
            }
        }
        assert!(compared >= 40, "only {compared} scores compared");
    }

    #[test]
    fn fit_recovers_the_extinction_of_a_dipole_profile() {
        // Profile of a dipole with s_t' = 2 /mm seen through a 0.25 mm slit, period 7.5 mm.
        let (eta, albedo, ext) = (1.4, 0.95, 2.0);
        let table = DipoleTable::new(eta);
        let weights = table.nearest(albedo).to_vec();
        let total: f64 = weights.iter().sum();
        let comps: Vec<Component> = WIDTHS
            .iter()
            .zip(&weights)
            .filter(|(_, w)| **w > 0.0)
            .map(|(&s, &w)| Component {
                weight: w / total,
                mean: 0.0,
                sigma: s / ext,
            })
            .collect();
        let (w, t) = (SLIT_WIDTH, SLIT_PERIOD);
        let profile = slit_profile(|s| {
            comps
                .iter()
                .map(|c| {
                    let g = crate::boxed_gaussian::BoxedGaussian {
                        mean: 0.0,
                        sigma: c.sigma,
                        width: w,
                    };
                    c.weight
                        * [-t, 0.0, t]
                            .iter()
                            .map(|o| g.ln_density(s - o).exp())
                            .sum::<f64>()
                })
                .sum()
        });
        let reflectance = total_reflectance(albedo, eta);
        let fit = table
            .fit(std::slice::from_ref(&profile), reflectance, None)
            .unwrap();
        assert!(
            (fit.extinction / ext - 1.0).abs() < 0.05,
            "{}",
            fit.extinction
        );
        let sum: f32 = fit.layers.iter().map(|l| l.weight).sum();
        assert!((f64::from(sum) - reflectance).abs() < 1e-5);
        // Searching from a neighbour's extinction, near or far, finds the same maximum.
        for hint in [0.3, 1.7, 2.4, 15.0] {
            let near = table
                .fit(std::slice::from_ref(&profile), reflectance, Some(hint))
                .unwrap();
            assert!(
                (near.extinction / fit.extinction - 1.0).abs() < 0.02,
                "hint {hint}: {} vs {}",
                near.extinction,
                fit.extinction
            );
        }
    }

    #[test]
    fn prepared_score_equals_the_em_likelihood() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let table = DipoleTable::new(1.4);
        let mut compared = 0;
        for case in 0..40 {
            let period = if case % 5 == 4 {
                None
            } else {
                Some(rng.gen_range(2.0..12.0))
            };
            let profiles: Vec<Profile> = (0..rng.gen_range(1..7))
                .map(|p| Profile {
                    noise: None,
                    samples: (0..10)
                        .map(|j| Sample {
                            s: rng.gen_range(-6.0..6.0),
                            // Some all-zero profiles and negative (noisy) samples.
                            y: if p == 2 && case % 3 == 0 {
                                0.0
                            } else {
                                rng.gen_range(-0.05..1.0) * f64::from(j % 4 + 1)
                            },
                        })
                        .collect(),
                    slit_width: rng.gen_range(0.05..0.6),
                    period,
                    shift_per_depth: 0.0,
                })
                .collect();
            let weights = table.nearest(rng.gen_range(0.75..0.999));
            let total: f64 = weights.iter().sum();
            let components: Vec<(f64, f64)> = WIDTHS
                .iter()
                .zip(weights)
                .filter(|(_, w)| **w > 0.0)
                .map(|(&s, &w)| (w / total, s))
                .collect();
            // Albedos below ~0.7 have no representation (all weights 0): `fit` refuses them
            // before scoring.
            if components.is_empty() {
                continue;
            }
            compared += 1;
            let prepared = PreparedProfiles::new(&profiles);
            for ext in [0.1, 0.7, 3.3, 18.0, 50.0, 400.0] {
                let comps: Vec<Component> = components
                    .iter()
                    .map(|&(weight, s)| Component {
                        weight,
                        mean: 0.0,
                        sigma: s / ext,
                    })
                    .collect();
                let reference: f64 = profiles
                    .iter()
                    .filter_map(|p| em_free::log_likelihood(p, &comps, 1).ok())
                    .sum();
                let fast = prepared.log_likelihood(&components, ext);

                assert!(
                    (fast - reference).abs() <= 1e-10 * (1.0 + reference.abs()),
                    "case {case}, ext {ext}: {fast} vs {reference}"
                );
            }
        }
        assert!(compared >= 20, "only {compared} cases scored");
    }

    #[test]
    fn fast_search_finds_the_extinction_of_a_dense_grid_of_the_em_likelihood() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let (eta, t) = (1.4, 7.5);
        let table = DipoleTable::new(eta);
        let mut fitted = 0;
        for case in 0..12 {
            let ext: f64 = [0.5, 2.0, 8.0][case % 3];
            let albedo = rng.gen_range(0.75..0.99);
            let weights = table.nearest(albedo).to_vec();
            let total: f64 = weights.iter().sum();
            if total <= 0.0 {
                continue;
            }
            fitted += 1;
            let comps = |ext: f64| -> Vec<Component> {
                WIDTHS
                    .iter()
                    .zip(&weights)
                    .filter(|(_, w)| **w > 0.0)
                    .map(|(&s, &w)| Component {
                        weight: w / total,
                        mean: 0.0,
                        sigma: s / ext,
                    })
                    .collect()
            };
            // Two axes, 10 slit positions each, 5 % noise: the profiles of one pixel.
            let profiles: Vec<Profile> = (0..2)
                .map(|_| {
                    let w = rng.gen_range(0.15..0.4);
                    let phase = rng.gen_range(0.0..t / 10.0);
                    let samples = (0..10)
                        .map(|i| {
                            let s = -t / 2.0 + phase + i as f64 * t / 10.0;
                            let y: f64 = comps(ext)
                                .iter()
                                .map(|c| {
                                    let g = BoxedGaussian {
                                        mean: 0.0,
                                        sigma: c.sigma,
                                        width: w,
                                    };
                                    c.weight
                                        * [-t, 0.0, t].iter().map(|o| g.density(s - o)).sum::<f64>()
                                })
                                .sum();
                            Sample {
                                s,
                                y: y * (1.0 + 0.05 * rng.gen_range(-1.0..1.0)),
                            }
                        })
                        .collect();
                    Profile {
                        noise: None,
                        samples,
                        slit_width: w,
                        period: Some(t),
                        shift_per_depth: 0.0,
                    }
                })
                .collect();
            let reference_score = |e: f64| -> f64 {
                profiles
                    .iter()
                    .filter_map(|p| em_free::log_likelihood(p, &comps(e), 1).ok())
                    .sum()
            };
            // Naive reference: the best of 600 log-spaced extinctions.
            let (lo, hi) = (EXTINCTION_RANGE.0.ln(), EXTINCTION_RANGE.1.ln());
            let grid: Vec<f64> = (0..600)
                .map(|i| (lo + (hi - lo) * f64::from(i) / 599.0).exp())
                .collect();
            let best = grid
                .iter()
                .map(|&e| (reference_score(e), e))
                .max_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap()
                .1;
            let reflectance = total_reflectance(albedo, eta);
            let step = (hi - lo) / 599.0;
            for hint in [None, Some(best * 1.5), Some(best / 1.3)] {
                let fit = table.fit(&profiles, reflectance, hint).unwrap();
                assert!(
                    (fit.extinction / best).ln().abs() < EXTINCTION_RESOLUTION.ln() + step,
                    "case {case}, hint {hint:?}: {} vs grid {best}",
                    fit.extinction
                );
            }
        }
        assert!(fitted >= 6, "only {fitted} cases fitted");
    }
}

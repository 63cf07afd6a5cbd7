//! Robust local planes through neighbouring codes (outlier checks and the sub-pixel fit).

use super::DecodeParams;

/// Reusable buffers of [`robust_plane_at_centre`], so that a pixel's fit allocates nothing.
#[derive(Debug, Default)]
pub(super) struct FitScratch {
    values: Vec<f64>,
    inliers: Vec<(f64, f64, f64)>,
}

/// Value at (0, 0) of a plane `c = a + b dx + e dy` fitted to `samples` (dx, dy, c), robustly:
/// samples far from the median are dropped, then the plane is refitted without its worst outliers.
/// Falls back to the inliers' mean when they do not span a plane.
pub(super) fn robust_plane_at_centre(
    samples: &[(f64, f64, f64)],
    params: &DecodeParams,
    scratch: &mut FitScratch,
) -> Option<f64> {
    let values = &mut scratch.values;
    values.clear();
    values.extend(samples.iter().map(|s| s.2));
    if values.is_empty() {
        return None;
    }
    // The element a full sort would put in the middle, found without sorting.
    let middle = values.len() / 2;
    let median = *values.select_nth_unstable_by(middle, f64::total_cmp).1;
    let limit = jump_limit(params);
    let inliers = &mut scratch.inliers;
    inliers.clear();
    inliers.extend(
        samples
            .iter()
            .copied()
            .filter(|s| (s.2 - median).abs() <= limit),
    );
    for _ in 0..2 {
        let plane = fit_plane(inliers)?;
        let before = inliers.len();
        inliers.retain(|s| (plane.eval(s.0, s.1) - s.2).abs() <= 1.5);
        if inliers.len() == before {
            return Some(plane.a);
        }
        if inliers.len() < 3 {
            return None;
        }
    }
    fit_plane(inliers).map(|p| p.a)
}

#[derive(Debug, Clone, Copy)]
struct Plane {
    a: f64,
    b: f64,
    c: f64,
}

impl Plane {
    fn eval(&self, dx: f64, dy: f64) -> f64 {
        self.a + self.b * dx + self.c * dy
    }
}

/// Least-squares plane through `(dx, dy, value)` samples; the mean when they are collinear.
fn fit_plane(samples: &[(f64, f64, f64)]) -> Option<Plane> {
    let n = samples.len() as f64;
    if samples.is_empty() {
        return None;
    }
    let (mut sx, mut sy, mut sv, mut sxx, mut syy, mut sxy, mut sxv, mut syv) =
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for &(x, y, v) in samples {
        sx += x;
        sy += y;
        sv += v;
        sxx += x * x;
        syy += y * y;
        sxy += x * y;
        sxv += x * v;
        syv += y * v;
    }
    let m = nalgebra::Matrix3::new(n, sx, sy, sx, sxx, sxy, sy, sxy, syy);
    let rhs = nalgebra::Vector3::new(sv, sxv, syv);
    // Samples on a line leave the plane undetermined (determinant ~0 relative to n^3).
    let well_posed = samples.len() >= 3 && m.determinant().abs() > 1e-6 * n * n * n;
    match m.lu().solve(&rhs) {
        Some(p) if well_posed && p.iter().all(|x| x.is_finite()) => Some(Plane {
            a: p[0],
            b: p[1],
            c: p[2],
        }),
        _ => Some(Plane {
            a: sv / n,
            b: 0.0,
            c: 0.0,
        }),
    }
}

/// Largest code difference to a neighbour that can still be on the same smooth surface.
pub(super) fn jump_limit(params: &DecodeParams) -> f64 {
    // Up to ~2 projector pixels per camera pixel on steep surfaces, plus the repair tolerance.
    2.0 * params.window_radius as f64 + 2.0 + params.repair_tolerance_px as f64
}

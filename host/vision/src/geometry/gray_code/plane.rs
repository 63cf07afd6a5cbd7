//! Robust local planes through neighbouring codes (outlier checks and the sub-pixel fit).

use super::DecodeParams;

/// A neighbour's offset from the pixel and its integer code. Why integers: every sum of the plane
/// fit is then exact in integer arithmetic and equal to the f64 sums it replaces (all terms are
/// integers far below 2^53), the median is an integer selection, and a sample is 12 bytes
/// instead of 24; the fits are bit for bit those of f64 samples (test).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Sample {
    pub(super) dx: i32,
    pub(super) dy: i32,
    pub(super) code: i32,
}

/// Largest distance of an inlier from the fitted plane, projector pixels.
const INLIER_PX: f64 = 1.5;

/// Reusable buffers of [`robust_plane_at_centre`], so that a pixel's fit allocates nothing.
#[derive(Debug, Default)]
pub(super) struct FitScratch {
    values: Vec<i32>,
    inliers: Vec<Sample>,
}

/// Value at (0, 0) of a plane `c = a + b dx + e dy` fitted to `samples` (dx, dy, c), robustly:
/// samples far from the median are dropped, then the plane is refitted without its worst outliers.
/// Falls back to the inliers' mean when they do not span a plane.
pub(super) fn robust_plane_at_centre(
    samples: &[Sample],
    params: &DecodeParams,
    scratch: &mut FitScratch,
) -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, the one feature `robust_plane_avx2` is compiled for.
        return unsafe { robust_plane_avx2(samples, params, scratch) };
    }
    robust_plane_portable(samples, params, scratch)
}

/// [`robust_plane_portable`] compiled with AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn robust_plane_avx2(
    samples: &[Sample],
    params: &DecodeParams,
    scratch: &mut FitScratch,
) -> Option<f64> {
    robust_plane_portable(samples, params, scratch)
}

/// The body of [`robust_plane_at_centre`] (inlined, with the functions it calls, into each
/// instruction-set variant).
#[inline(always)]
fn robust_plane_portable(
    samples: &[Sample],
    params: &DecodeParams,
    scratch: &mut FitScratch,
) -> Option<f64> {
    let (min, max) = code_range(samples)?;
    let limit = jump_limit(params);
    let inliers = &mut scratch.inliers;
    inliers.clear();
    inliers.extend_from_slice(samples);
    // The median lies within the codes' range: when the range is within the limit, no sample
    // is far from the median and neither it nor the filter is needed (most windows of a smooth
    // surface; the median and the filter were a third of the fit).
    if f64::from(max.abs_diff(min)) > limit {
        let median = median_code(samples, &mut scratch.values)?;
        keep_where(inliers, |s| f64::from(s.code.abs_diff(median)) <= limit);
    }
    for _ in 0..2 {
        let plane = fit_plane(inliers)?;
        let before = inliers.len();
        keep_where(inliers, |s| plane.is_inlier(s.dx, s.dy, s.code));
        if inliers.len() == before {
            return Some(plane.a);
        }
        if inliers.len() < 3 {
            return None;
        }
    }
    fit_plane(inliers).map(|p| p.a)
}

/// `retain`, branch-free: every sample is copied down and the count advances only for those
/// kept (in order). Why: whether a neighbour is an inlier is data-dependent, and `retain`'s
/// mispredicted branches were a visible share of the fits.
#[inline(always)]
fn keep_where(samples: &mut Vec<Sample>, keep: impl Fn(&Sample) -> bool) {
    let mut kept = 0;
    for j in 0..samples.len() {
        let s = samples[j];
        samples[kept] = s;
        kept += usize::from(keep(&s));
    }
    samples.truncate(kept);
}

/// The smallest and largest code of the samples; `None` without samples.
#[inline(always)]
fn code_range(samples: &[Sample]) -> Option<(i32, i32)> {
    let first = samples.first()?.code;
    Some(samples.iter().fold((first, first), |(lo, hi), s| {
        (lo.min(s.code), hi.max(s.code))
    }))
}

/// Codes spanning fewer values than this are ranked by counting.
const COUNTED_SPAN: usize = 64;

/// The code a full sort of the samples' codes would put at index `len / 2`; `None` without
/// samples. Why counting: the codes of a window on a smooth surface span a few tens of values,
/// and counting them into a small histogram and walking it to the middle rank is exact and took
/// a fraction of the time of `select_nth_unstable` (a twelfth of the decode, perf); wider spans
/// (a depth edge, an outlier) fall back to the selection, in `values`.
#[inline(always)]
fn median_code(samples: &[Sample], values: &mut Vec<i32>) -> Option<i32> {
    let (min, max) = code_range(samples)?;
    let middle = samples.len() / 2;
    if i64::from(max) - i64::from(min) < COUNTED_SPAN as i64 {
        let mut counts = [0u32; COUNTED_SPAN];
        for s in samples {
            counts[(s.code - min) as usize] += 1;
        }
        // The first value whose cumulative count passes the middle rank.
        let mut below = 0usize;
        for (offset, &count) in counts.iter().enumerate() {
            below += count as usize;
            if below > middle {
                return Some(min + offset as i32);
            }
        }
    }
    values.clear();
    values.extend(samples.iter().map(|s| s.code));
    Some(*values.select_nth_unstable(middle).1)
}

/// `c = a + b dx + e dy`: `a` is the value at the pixel, `b` and `c` the slopes.
#[derive(Debug, Clone, Copy)]
pub(super) struct Plane {
    pub(super) a: f64,
    b: f64,
    c: f64,
}

impl Plane {
    #[inline(always)]
    pub(super) fn eval(&self, dx: i32, dy: i32) -> f64 {
        self.a + self.b * f64::from(dx) + self.c * f64::from(dy)
    }

    /// Whether the sample `(dx, dy, code)` lies within [`INLIER_PX`] of the plane.
    #[inline(always)]
    pub(super) fn is_inlier(&self, dx: i32, dy: i32, code: i32) -> bool {
        (self.eval(dx, dy) - f64::from(code)).abs() <= INLIER_PX
    }
}

/// Least-squares plane through the samples; the mean when they are collinear. The sums are
/// exact integers (i64), converted once.
#[inline(always)]
fn fit_plane(samples: &[Sample]) -> Option<Plane> {
    if samples.is_empty() {
        return None;
    }
    let (mut sx, mut sy, mut sv, mut sxx, mut syy, mut sxy, mut sxv, mut syv) =
        (0i64, 0i64, 0i64, 0i64, 0i64, 0i64, 0i64, 0i64);
    for s in samples {
        let (x, y, v) = (i64::from(s.dx), i64::from(s.dy), i64::from(s.code));
        sx += x;
        sy += y;
        sv += v;
        sxx += x * x;
        syy += y * y;
        sxy += x * y;
        sxv += x * v;
        syv += y * v;
    }
    let sums = [sx, sy, sv, sxx, syy, sxy, sxv, syv].map(|v| v as f64);
    Some(plane_from_sums(samples.len(), sums))
}

/// The least-squares plane of `count` samples from their sums `[x, y, v, xx, yy, xy, xv, yv]`;
/// the mean when the samples are collinear.
#[inline(always)]
pub(super) fn plane_from_sums(
    count: usize,
    [sx, sy, sv, sxx, syy, sxy, sxv, syv]: [f64; 8],
) -> Plane {
    let n = count as f64;
    let m = [[n, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]];
    let mean = Plane {
        a: sv / n,
        b: 0.0,
        c: 0.0,
    };
    // Samples on a line leave the plane undetermined (determinant ~0 relative to n^3); the mean
    // is then the answer whatever the solve gives, so the solve is skipped.
    let well_posed = count >= 3 && determinant3(&m).abs() > 1e-6 * n * n * n;
    if !well_posed {
        return mean;
    }
    match lu_solve3(m, [sv, sxv, syv]) {
        Some(p) if p.iter().all(|x| x.is_finite()) => Plane {
            a: p[0],
            b: p[1],
            c: p[2],
        },
        _ => mean,
    }
}

/// The determinant of a 3 x 3 matrix (rows), by the cofactor formula of nalgebra's
/// `Matrix3::determinant`, operation for operation (hence the same bits).
#[inline(always)]
fn determinant3(m: &[[f64; 3]; 3]) -> f64 {
    let minor_12_23 = m[1][1] * m[2][2] - m[2][1] * m[1][2];
    let minor_11_23 = m[1][0] * m[2][2] - m[2][0] * m[1][2];
    let minor_11_22 = m[1][0] * m[2][1] - m[2][0] * m[1][1];
    m[0][0] * minor_12_23 - m[0][1] * minor_11_23 + m[0][2] * minor_11_22
}

/// Solves `m x = rhs` by LU decomposition with partial pivoting, `None` when a pivot is zero.
/// Why by hand: nalgebra's generic `LU::new` and `solve` on a `Matrix3` (a per-pixel call, up to
/// six per decoded pixel) were a tenth of the decode (perf: `LU::new` 5 %, `solve` 3 %, beside
/// the determinant); this is the same algorithm with the same floating-point operations in the
/// same order (pivot = first largest |entry| of the column, the column scaled by the pivot's
/// reciprocal, the rank-one update `y - p x`, unit-lower then upper substitution), unrolled for
/// 3 x 3, so it returns nalgebra's bits (test). The index loops keep nalgebra's loop order
/// readable beside its source.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn lu_solve3(mut m: [[f64; 3]; 3], mut b: [f64; 3]) -> Option<[f64; 3]> {
    let mut swaps = [(0usize, 0usize); 3];
    let mut nswaps = 0;
    for i in 0..3 {
        let mut piv = i;
        let mut largest = m[i][i].abs();
        for (r, row) in m.iter().enumerate().skip(i + 1) {
            if row[i].abs() > largest {
                largest = row[i].abs();
                piv = r;
            }
        }
        let diag = m[piv][i];
        if diag == 0.0 {
            continue;
        }
        if piv != i {
            swaps[nswaps] = (i, piv);
            nswaps += 1;
            m.swap(i, piv);
        }
        let inv_diag = 1.0 / diag;
        for r in i + 1..3 {
            m[r][i] *= inv_diag;
        }
        for k in i + 1..3 {
            for r in i + 1..3 {
                m[r][k] += -m[i][k] * m[r][i];
            }
        }
    }
    for &(i, j) in &swaps[..nswaps] {
        b.swap(i, j);
    }
    for i in 0..2 {
        let coeff = b[i];
        for r in i + 1..3 {
            b[r] += -coeff * m[r][i];
        }
    }
    for i in (0..3).rev() {
        let diag = m[i][i];
        if diag == 0.0 {
            return None;
        }
        let coeff = b[i] / diag;
        b[i] = coeff;
        for r in 0..i {
            b[r] += -coeff * m[r][i];
        }
    }
    Some(b)
}

/// Largest code difference to a neighbour that can still be on the same smooth surface.
pub(super) fn jump_limit(params: &DecodeParams) -> f64 {
    // Up to ~2 projector pixels per camera pixel on steep surfaces, plus the repair tolerance.
    2.0 * params.window_radius as f64 + 2.0 + params.repair_tolerance_px as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    /// The fit as it was on f64 `(dx, dy, code)` samples: the reference the integer fit must
    /// equal bit for bit.
    fn robust_plane_f64(samples: &[(f64, f64, f64)], params: &DecodeParams) -> Option<f64> {
        let mut values: Vec<f64> = samples.iter().map(|s| s.2).collect();
        if values.is_empty() {
            return None;
        }
        let middle = values.len() / 2;
        let median = *values.select_nth_unstable_by(middle, f64::total_cmp).1;
        let limit = jump_limit(params);
        let mut inliers: Vec<(f64, f64, f64)> = samples
            .iter()
            .copied()
            .filter(|s| (s.2 - median).abs() <= limit)
            .collect();
        for _ in 0..2 {
            let plane = fit_plane_f64(&inliers)?;
            let before = inliers.len();
            inliers.retain(|s| (plane.a + plane.b * s.0 + plane.c * s.1 - s.2).abs() <= 1.5);
            if inliers.len() == before {
                return Some(plane.a);
            }
            if inliers.len() < 3 {
                return None;
            }
        }
        fit_plane_f64(&inliers).map(|p| p.a)
    }

    fn fit_plane_f64(samples: &[(f64, f64, f64)]) -> Option<Plane> {
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
        Some(plane_from_sums(
            samples.len(),
            [sx, sy, sv, sxx, syy, sxy, sxv, syv],
        ))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// The unrolled LU solve and determinant return nalgebra's bits: on the normal matrices
        /// of windows (integer sums, symmetric), on general matrices, and with zero columns and
        /// singular ones (where both give up together).
        #[test]
        #[allow(clippy::needless_range_loop)]
        fn unrolled_solve_equals_nalgebra(seed in 0u64..1_000_000, kind in 0usize..4) {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let entry = |rng: &mut rand_pcg::Pcg64| -> f64 {
                match kind {
                    0 => f64::from(rng.gen_range(-200i32..200)),
                    1 => rng.gen_range(-1e3..1e3),
                    2 => if rng.gen_bool(0.4) { 0.0 } else { f64::from(rng.gen_range(-3i32..4)) },
                    _ => rng.gen_range(-1.0..1.0) * 10f64.powi(rng.gen_range(-8..8)),
                }
            };
            let mut m = [[0.0f64; 3]; 3];
            for r in 0..3 {
                for c in 0..3 {
                    m[r][c] = entry(&mut rng);
                }
            }
            if kind == 0 {
                // Symmetric, as the normal equations are.
                for r in 0..3 {
                    for c in 0..r {
                        m[r][c] = m[c][r];
                    }
                }
            }
            let b = [entry(&mut rng), entry(&mut rng), entry(&mut rng)];
            let na = nalgebra::Matrix3::new(
                m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
            );
            let reference = na
                .lu()
                .solve(&nalgebra::Vector3::new(b[0], b[1], b[2]))
                .map(|x| [x[0].to_bits(), x[1].to_bits(), x[2].to_bits()]);
            let fast = lu_solve3(m, b).map(|x| x.map(f64::to_bits));
            prop_assert_eq!(fast, reference);
            prop_assert_eq!(determinant3(&m).to_bits(), na.determinant().to_bits());
        }

        /// The counted median is the middle element of the sorted codes, for narrow spans (the
        /// counting path), wide ones (the selection) and at the span's boundary.
        #[test]
        fn counted_median_is_the_sorted_middle(
            seed in 0u64..1_000_000,
            len in 1usize..120,
            span in 1i32..200,
        ) {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let base = rng.gen_range(0..70_000);
            let samples: Vec<Sample> = (0..len)
                .map(|k| Sample { dx: k as i32, dy: 0, code: base + rng.gen_range(0..span) })
                .collect();
            let mut sorted: Vec<i32> = samples.iter().map(|s| s.code).collect();
            sorted.sort_unstable();
            prop_assert_eq!(median_code(&samples, &mut Vec::new()), Some(sorted[len / 2]));
        }

        /// Windows of up to 9 x 9 neighbours on a tilted plane of codes, with holes, staircase
        /// rounding, jumps (another surface) and wild outliers: the integer fit returns exactly
        /// the f64 fit's value (or both none).
        #[test]
        fn integer_fit_equals_the_f64_fit(seed in 0u64..1_000_000, radius in 1i32..5) {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let (base, gx, gy) = (rng.gen_range(0.0..60_000.0), rng.gen_range(-2.5..2.5), rng.gen_range(-2.5..2.5));
            let keep = rng.gen_range(0.05..1.0);
            let mut samples = Vec::new();
            for dy in -radius..=radius {
                for dx in -radius..=radius {
                    if (dx, dy) == (0, 0) || !rng.gen_bool(keep) {
                        continue;
                    }
                    let mut code = (base + gx * f64::from(dx) + gy * f64::from(dy)).round() as i32;
                    match rng.gen_range(0..20) {
                        0 => code += rng.gen_range(-3000..3000),
                        1 | 2 => code += 9,
                        _ => {}
                    }
                    samples.push(Sample { dx, dy, code: code.max(0) });
                }
            }
            let params = DecodeParams { window_radius: radius as u32, ..DecodeParams::default() };
            let reference: Vec<(f64, f64, f64)> = samples
                .iter()
                .map(|s| (f64::from(s.dx), f64::from(s.dy), f64::from(s.code)))
                .collect();
            let fast = robust_plane_at_centre(&samples, &params, &mut FitScratch::default());
            let slow = robust_plane_f64(&reference, &params);
            prop_assert_eq!(fast.map(f64::to_bits), slow.map(f64::to_bits));
        }
    }
}

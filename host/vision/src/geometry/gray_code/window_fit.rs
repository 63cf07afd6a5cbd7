//! The first plane of a window's robust fit from its sums: the fast path of the repair's
//! prediction and of the consistency check (steps 3 and 4).
//!
//! Why: on the real 8-bit captures (procam capture_0) the repair reads 529 000 windows of
//! 9 x 9 and the check 208 000 of 5 x 5 that are not complete and smooth. Each went through
//! passes over its samples for the statistics, for each side, for the range, a copy, and the
//! sums of each plane fit; 83 % of the repair's fits and 80 % of the check's end at their first
//! plane (no median filter, every sample an inlier). [`WindowSums`] holds the statistics,
//! sides, range and that plane's exact integer sums, and [`WindowSums::first_fit_if_final`]
//! checks that the robust fit would stop there; any other window goes the general way. The
//! check takes the sums from its gathered samples in one pass ([`WindowSums::of_samples`];
//! decoding capture_0 0.476 -> 0.443 CPU-s, mean of 5, 2 alternated pairs), the repair from its
//! row's column sums (`window_columns`, which tests the inliers on the window itself).

use super::DecodeParams;
use super::axis::Grid;
use super::plane::{Plane, Sample, jump_limit, plane_from_sums};

/// The valid codes of the window of `radius` around a pixel, the pixel itself excluded: their
/// count and range, the sums of their least-squares plane (offsets from the pixel), and which
/// sides of the pixel they reach.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct WindowSums {
    /// Valid neighbours.
    pub(super) count: usize,
    /// Pixels of the window inside the image (excluding the centre).
    pub(super) size: usize,
    /// Smallest and largest valid code (`i32::MAX`, `i32::MIN` without any).
    pub(super) min: i32,
    pub(super) max: i32,
    /// `[dx, dy, v, dx^2, dy^2, dx dy, dx v, dy v]` summed over the valid neighbours: the sums
    /// of `plane::fit_plane`, exact integers (so the same whatever the order of the samples).
    pub(super) sums: [i64; 8],
    /// Some valid neighbour left of, right of, above and below the pixel.
    pub(super) sides: [bool; 4],
}

impl WindowSums {
    /// The sums of the gathered valid neighbours `samples` ([`Grid::gather_valid`]) of the
    /// window of `radius` around pixel `i`, in one pass over them.
    pub(super) fn of_samples(grid: Grid, i: usize, radius: usize, samples: &[Sample]) -> Self {
        let (x, y) = (i % grid.width, i / grid.width);
        let ((x0, x1), (y0, y1)) = grid.window_bounds(x, y, radius);
        let (mut min, mut max) = (i32::MAX, i32::MIN);
        // The offsets' sums in i32 (exact: |dx|, |dy| <= 2 MAX_WINDOW_RADIUS, so a sum of
        // squares over a whole window stays below 2^31), the code sums in i64.
        let [mut sx, mut sy, mut sxx, mut syy, mut sxy] = [0i32; 5];
        let [mut sv, mut sxv, mut syv] = [0i64; 3];
        let (mut min_dx, mut max_dx, mut min_dy, mut max_dy) = (0, 0, 0, 0);
        for &Sample { dx, dy, code } in samples {
            sx += dx;
            sy += dy;
            sxx += dx * dx;
            syy += dy * dy;
            sxy += dx * dy;
            let v = i64::from(code);
            sv += v;
            sxv += i64::from(dx) * v;
            syv += i64::from(dy) * v;
            min = min.min(code);
            max = max.max(code);
            (min_dx, max_dx) = (min_dx.min(dx), max_dx.max(dx));
            (min_dy, max_dy) = (min_dy.min(dy), max_dy.max(dy));
        }
        let sums = [
            i64::from(sx),
            i64::from(sy),
            sv,
            i64::from(sxx),
            i64::from(syy),
            i64::from(sxy),
            sxv,
            syv,
        ];
        let sides = [min_dx < 0, max_dx > 0, min_dy < 0, max_dy > 0];
        Self {
            count: samples.len(),
            size: (x1 - x0 + 1) * (y1 - y0 + 1) - 1,
            min,
            max,
            sums,
            sides,
        }
    }

    /// The sum of the valid codes, as `f64` (exact).
    pub(super) fn code_sum(&self) -> f64 {
        self.sums[2] as f64
    }

    /// Valid neighbours on every side of the pixel (left, right, above and below).
    pub(super) fn surrounded(&self) -> bool {
        self.sides.iter().all(|&s| s)
    }

    /// `plane::robust_plane_at_centre` of `samples`, the valid neighbours these sums were taken
    /// from (with `centre`, of them and of the pixel itself with that code, as the consistency
    /// check's sub-pixel fit gathers them), when that fit ends at its first plane: the codes
    /// span no more than the jump limit (no median filter), none is dropped by the jump limit
    /// around `centre`, and every sample is an inlier of the plane (no refit). `None` when the fit would go on
    /// (the caller then runs it): every `Some` is the robust fit's own value, bit for bit (test).
    pub(super) fn first_fit_if_final(
        &self,
        samples: &[Sample],
        params: &DecodeParams,
        centre: Option<i32>,
    ) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let with_centre = match centre {
            None => *self,
            Some(code) => self.with_centre(code, params)?,
        };
        let plane = with_centre.first_plane_if_narrow(params)?;
        // Non-short-circuit `&`: no branch per sample.
        let all_inliers = samples.iter().fold(
            centre.is_none_or(|code| plane.is_inlier(0, 0, code)),
            |all, s| all & plane.is_inlier(s.dx, s.dy, s.code),
        );
        all_inliers.then_some(plane.a)
    }

    /// These sums with the centre's `code` added (its offsets are 0, so it adds its code and
    /// nothing else); `None` when the jump limit around `code` would drop a neighbour.
    fn with_centre(&self, code: i32, params: &DecodeParams) -> Option<Self> {
        let limit = jump_limit(params);
        let kept = |c: i32| f64::from(c.abs_diff(code)) <= limit;
        if !(kept(self.min) && kept(self.max)) {
            return None;
        }
        let mut sums = *self;
        sums.count += 1;
        sums.sums[2] += i64::from(code);
        (sums.min, sums.max) = (self.min.min(code), self.max.max(code));
        Some(sums)
    }

    /// The least-squares plane of these sums when the robust fit would take it as its first
    /// plane: some samples, spanning no more than the jump limit (no median filter).
    pub(super) fn first_plane_if_narrow(&self, params: &DecodeParams) -> Option<Plane> {
        let narrow = f64::from(self.max.abs_diff(self.min)) <= jump_limit(params);
        (self.count > 0 && narrow).then(|| plane_from_sums(self.count, self.sums.map(|s| s as f64)))
    }
}

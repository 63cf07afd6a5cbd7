//! Fresnel reflection and Snell refraction of unpolarised light at a planar interface.

/// Cosine of the refracted angle for light going from index `n_i` to `n_t` with incidence cosine
/// `cos_i` (in [0, 1]), or `None` under total internal reflection.
pub fn refracted_cos(n_i: f64, n_t: f64, cos_i: f64) -> Option<f64> {
    let ratio = n_i / n_t;
    let sin_t_sq = ratio * ratio * (1.0 - cos_i * cos_i);
    if sin_t_sq >= 1.0 {
        None
    } else {
        Some((1.0 - sin_t_sq).sqrt())
    }
}

/// Reflectance of unpolarised light (mean of the s and p reflectances) going from index `n_i` to
/// `n_t` at incidence cosine `cos_i`; 1 under total internal reflection.
pub fn fresnel_reflectance(n_i: f64, n_t: f64, cos_i: f64) -> f64 {
    match refracted_cos(n_i, n_t, cos_i) {
        None => 1.0,
        Some(cos_t) => reflectance_with_cos_t(n_i, n_t, cos_i, cos_t),
    }
}

/// Unpolarised Fresnel reflectance when the refracted cosine is already known (hot path).
#[inline]
pub(crate) fn reflectance_with_cos_t(n_i: f64, n_t: f64, cos_i: f64, cos_t: f64) -> f64 {
    if n_i == n_t {
        return 0.0;
    }
    let rs = (n_i * cos_i - n_t * cos_t) / (n_i * cos_i + n_t * cos_t);
    let rp = (n_i * cos_t - n_t * cos_i) / (n_i * cos_t + n_t * cos_i);
    0.5 * (rs * rs + rp * rp)
}

/// Cosine bins of a `ReflectanceBound`.
const BOUND_BINS: usize = 64;

/// An upper bound of the Fresnel reflectance at one interface (from `n_i` into `n_t`) per bin of
/// the incidence cosine, so that the random choice between reflection and refraction (reflect when
/// a uniform u < R) is settled for most photons by one table look-up: u >= bound means refraction,
/// and only the few draws below the bound need R itself. The outcome of every choice is the same
/// as computing R each time (the bound is above R, the exact comparison decides below it); the
/// gain is that the decision no longer waits on a square root and a division.
///
/// Unpolarised R only grows with the angle of incidence (falls with its cosine, checked by the
/// test below over indices 1-2.5), so its largest value over a bin is at the bin's lower edge; the
/// bound adds 1e-9 there against rounding. It is 1 on every bin that reaches below the critical
/// cosine, where R is 1 (total reflection) or close to it.
#[derive(Debug, Clone)]
pub(crate) struct ReflectanceBound {
    /// n_i / n_t, as `refracted_cos` computes it.
    ratio: f64,
    bound: [f64; BOUND_BINS],
}

impl ReflectanceBound {
    pub(crate) fn new(n_i: f64, n_t: f64) -> Self {
        let bound = std::array::from_fn(|bin| {
            let lower_edge = bin as f64 / BOUND_BINS as f64;
            (fresnel_reflectance(n_i, n_t, lower_edge) + 1e-9).min(1.0)
        });
        Self {
            ratio: n_i / n_t,
            bound,
        }
    }

    /// A value >= R at incidence cosine `cos_i` in [0, 1]; below 1 only where the light is not
    /// totally reflected.
    #[inline(always)]
    pub(crate) fn at(&self, cos_i: f64) -> f64 {
        // `as` saturates, and cos_i = 1 falls in the last bin.
        self.bound[((cos_i * BOUND_BINS as f64) as usize).min(BOUND_BINS - 1)]
    }

    /// `refracted_cos(n_i, n_t, cos_i)` (the same operations, so the same value) where `at(cos_i)`
    /// is below 1, i.e. the light is not totally reflected.
    #[inline(always)]
    pub(crate) fn refracted_cos(&self, cos_i: f64) -> f64 {
        let sin_t_sq = self.ratio * self.ratio * (1.0 - cos_i * cos_i);
        (1.0 - sin_t_sq).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bound is above R at every cosine (dense sweep, both directions of several interfaces,
    /// skin's included), reaches 1 under total reflection, and the refracted cosine it gives is
    /// `refracted_cos`'s to the bit.
    #[test]
    fn reflectance_bound_is_above_the_reflectance_everywhere() {
        let indices = [1.0, 1.33, 1.34, 1.39, 1.4, 1.44, 1.53, 2.5];
        for &n_i in &indices {
            for &n_t in &indices {
                let bound = ReflectanceBound::new(n_i, n_t);
                for k in 0..=200_000 {
                    let cos_i = f64::from(k) / 200_000.0;
                    let r = fresnel_reflectance(n_i, n_t, cos_i);
                    let b = bound.at(cos_i);
                    assert!(b >= r, "{n_i} -> {n_t} at {cos_i}: bound {b} < R {r}");
                    match refracted_cos(n_i, n_t, cos_i) {
                        None => assert_eq!(b, 1.0),
                        Some(cos_t) if b < 1.0 => assert_eq!(bound.refracted_cos(cos_i), cos_t),
                        Some(_) => {}
                    }
                }
            }
        }
    }

    /// What the bound relies on: R falls (never rises) as the incidence cosine grows.
    #[test]
    fn reflectance_falls_with_the_incidence_cosine() {
        for i in 0..=30 {
            for t in 0..=30 {
                let (n_i, n_t) = (1.0 + 0.05 * f64::from(i), 1.0 + 0.05 * f64::from(t));
                let mut last = fresnel_reflectance(n_i, n_t, 0.0);
                for k in 1..=20_000 {
                    let r = fresnel_reflectance(n_i, n_t, f64::from(k) / 20_000.0);
                    assert!(
                        r <= last + 1e-15,
                        "{n_i} -> {n_t} at step {k}: {r} > {last}"
                    );
                    last = r;
                }
            }
        }
    }

    #[test]
    fn normal_incidence_matches_the_closed_form() {
        // ((n1 - n2) / (n1 + n2))^2 at normal incidence.
        let r = fresnel_reflectance(1.0, 1.4, 1.0);
        assert!((r - (0.4f64 / 2.4).powi(2)).abs() < 1e-15);
        // Symmetric in the direction of travel at normal incidence.
        assert!((fresnel_reflectance(1.4, 1.0, 1.0) - r).abs() < 1e-15);
    }

    #[test]
    fn matched_indices_do_not_reflect() {
        assert_eq!(fresnel_reflectance(1.37, 1.37, 0.3), 0.0);
    }

    #[test]
    fn beyond_the_critical_angle_reflects_totally() {
        // Critical angle for 1.4 -> 1.0: sin = 1/1.4, cos = 0.6999.
        assert_eq!(fresnel_reflectance(1.4, 1.0, 0.69), 1.0);
        assert!(fresnel_reflectance(1.4, 1.0, 0.71) < 1.0);
        assert!(refracted_cos(1.4, 1.0, 0.69).is_none());
    }

    #[test]
    fn brewster_angle_has_no_p_reflection() {
        // At Brewster's angle tan(theta) = n2/n1 only s-polarised light reflects.
        let theta = (1.5f64).atan();
        let cos_i = theta.cos();
        let cos_t = refracted_cos(1.0, 1.5, cos_i).unwrap();
        let rs = (cos_i - 1.5 * cos_t) / (cos_i + 1.5 * cos_t);
        let r = fresnel_reflectance(1.0, 1.5, cos_i);
        assert!((r - 0.5 * rs * rs).abs() < 1e-14);
    }

    #[test]
    fn grazing_incidence_reflects_everything() {
        assert!((fresnel_reflectance(1.0, 1.4, 0.0) - 1.0).abs() < 1e-12);
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;

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

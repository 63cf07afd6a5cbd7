//! Light reflected at the surface itself (the direct component): a rough dielectric specular lobe
//! for skin, and a Lambertian reflector for the printed calibration target.
//!
//! The specular lobe is the Torrance-Sparrow microfacet model with the GGX (Trowbridge-Reitz)
//! distribution and Smith's separable shadowing (Walter et al. 2007, "Microfacet models for
//! refraction through rough surfaces"), weighted by the unpolarised Fresnel reflectance of the skin
//! surface. Its roughness follows Weyrich et al. 2006 ("Analysis of human faces using a
//! measurement-based skin reflectance model"), who fitted Torrance-Sparrow roughness of about
//! 0.3-0.45 across face regions.
//!
//! Conventions: all vectors are unit, world frame; `n` is the outward normal, `l` points to the
//! light, `v` to the camera. BRDFs are in 1/sr.

use std::f64::consts::PI;

use nalgebra::Vector3;

/// Microfacet roughness (GGX alpha) of skin.
pub const SKIN_ROUGHNESS: f64 = 0.35;

/// Unpolarised Fresnel reflectance from air into a medium of index `eta` at incidence cosine
/// `cos_i`.
pub fn fresnel_dielectric(cos_i: f64, eta: f64) -> f64 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin_t2 = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin_t2 >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin_t2).sqrt();
    let rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    let rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    0.5 * (rs * rs + rp * rp)
}

/// GGX microfacet distribution for the half-vector cosine `cos_h`.
fn ggx_distribution(cos_h: f64, alpha: f64) -> f64 {
    let a2 = alpha * alpha;
    let c2 = cos_h * cos_h;
    let d = c2 * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

/// Smith's GGX masking for one direction with cosine `cos` to the normal.
fn smith_g1(cos: f64, alpha: f64) -> f64 {
    let c2 = cos * cos;
    let tan2 = (1.0 - c2) / c2;
    2.0 / (1.0 + (1.0 + alpha * alpha * tan2).sqrt())
}

/// Specular BRDF of a rough dielectric surface of index `eta`.
pub fn specular_brdf(
    n: &Vector3<f64>,
    l: &Vector3<f64>,
    v: &Vector3<f64>,
    eta: f64,
    alpha: f64,
) -> f64 {
    let cos_l = n.dot(l);
    let cos_v = n.dot(v);
    if cos_l <= 0.0 || cos_v <= 0.0 {
        return 0.0;
    }
    let h = (l + v).normalize();
    let cos_h = n.dot(&h);
    let fresnel = fresnel_dielectric(l.dot(&h), eta);
    let d = ggx_distribution(cos_h, alpha);
    let g = smith_g1(cos_l, alpha) * smith_g1(cos_v, alpha);
    fresnel * d * g / (4.0 * cos_l * cos_v)
}

/// Lambertian BRDF of albedo `albedo`.
pub fn lambert_brdf(albedo: f64) -> f64 {
    albedo / PI
}

/// Normalised angular distribution of the radiance that diffuse subsurface light leaves the
/// surface with: the light inside is close to isotropic near the surface, so the radiance outside
/// goes as the Fresnel transmittance `1 - F(theta_o)`. Returns the factor `T(theta_o) / C` with
/// `C = integral of T cos over the hemisphere`, so that exitance M gives radiance `M * factor`.
#[derive(Debug, Clone, Copy)]
pub struct DiffuseExit {
    eta: f64,
    norm: f64,
}

impl DiffuseExit {
    pub fn new(eta: f64) -> Self {
        // C = 2 pi int_0^{pi/2} T(theta) cos sin dtheta = pi int_0^1 T(sqrt(s)) ds with s = cos^2.
        let steps = 2000;
        let integral: f64 = (0..steps)
            .map(|i| {
                let s = (i as f64 + 0.5) / steps as f64;
                1.0 - fresnel_dielectric(s.sqrt(), eta)
            })
            .sum::<f64>()
            / steps as f64;
        Self {
            eta,
            norm: PI * integral,
        }
    }

    /// Radiance per unit exitance towards a direction at cosine `cos_o` from the normal, 1/sr.
    pub fn factor(&self, cos_o: f64) -> f64 {
        if cos_o <= 0.0 {
            return 0.0;
        }
        (1.0 - fresnel_dielectric(cos_o, self.eta)) / self.norm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fresnel_at_normal_incidence_is_the_closed_form() {
        let f = fresnel_dielectric(1.0, 1.4);
        assert!((f - (0.4f64 / 2.4).powi(2)).abs() < 1e-12);
        assert!((fresnel_dielectric(0.0, 1.4) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn specular_lobe_reflects_at_most_the_light_it_receives() {
        // Directional albedo: integral of BRDF cos_v over the hemisphere, for a light at 30 deg.
        let n = Vector3::z();
        let l = Vector3::new(0.5, 0.0, 0.75f64.sqrt());
        let (nt, np) = (400, 400);
        let mut albedo = 0.0;
        for i in 0..nt {
            let theta = (i as f64 + 0.5) / nt as f64 * PI / 2.0;
            for j in 0..np {
                let phi = (j as f64 + 0.5) / np as f64 * 2.0 * PI;
                let v = Vector3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                );
                let dw = theta.sin() * (PI / 2.0 / nt as f64) * (2.0 * PI / np as f64);
                albedo += specular_brdf(&n, &l, &v, 1.4, SKIN_ROUGHNESS) * theta.cos() * dw;
            }
        }
        // Close to the Fresnel reflectance at 30 degrees (~0.03), never above it by much.
        let f = fresnel_dielectric(l.z, 1.4);
        assert!(albedo > 0.7 * f && albedo < 1.05 * f, "{albedo} vs {f}");
    }

    #[test]
    fn diffuse_exit_distribution_integrates_to_one() {
        let exit = DiffuseExit::new(1.4);
        let steps = 4000;
        let total: f64 = (0..steps)
            .map(|i| {
                let theta = (i as f64 + 0.5) / steps as f64 * PI / 2.0;
                exit.factor(theta.cos())
                    * theta.cos()
                    * theta.sin()
                    * 2.0
                    * PI
                    * (PI / 2.0 / steps as f64)
            })
            .sum();
        assert!((total - 1.0).abs() < 1e-3, "{total}");
    }
}

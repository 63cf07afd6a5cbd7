//! The planar multi-layer medium: layers stacked from the surface down, between two ambient media.

use super::McError;

/// Largest absorption or scattering coefficient a layer may have, 1/mm (a mean free path of
/// 1 nm; skin's are 0.01-100/mm). Beyond it a step is below the precision of a position in mm
/// and photons never leave the medium.
pub const MAX_COEFFICIENT_PER_MM: f64 = 1e6;

/// One homogeneous layer.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Layer {
    /// Thickness in mm; `f64::INFINITY` makes the layer semi-infinite (only the last layer may be).
    pub thickness_mm: f64,
    /// Absorption coefficient, 1/mm.
    pub mu_a: f64,
    /// Scattering coefficient, 1/mm (not the reduced one: mu_s' = mu_s (1 - g)).
    pub mu_s: f64,
    /// Henyey-Greenstein anisotropy, mean cosine of the scattering angle, in (-1, 1).
    pub g: f64,
    /// Refractive index.
    pub n: f64,
}

impl Layer {
    /// A slab given by its optical properties with mu_t = 1/mm, so lengths are in mean free paths:
    /// `tau` is the optical thickness (infinite for a semi-infinite medium).
    pub fn from_albedo(albedo: f64, tau: f64, g: f64, n: f64) -> Self {
        Self {
            thickness_mm: tau,
            mu_a: 1.0 - albedo,
            mu_s: albedo,
            g,
            n,
        }
    }

    /// Total attenuation coefficient mu_a + mu_s, 1/mm.
    ///
    /// See [`MAX_COEFFICIENT_PER_MM`] for the largest coefficient a layer may have.
    pub fn mu_t(&self) -> f64 {
        self.mu_a + self.mu_s
    }

    fn validate(&self, index: usize, last: bool) -> Result<(), McError> {
        let invalid = |field, value, reason| McError::InvalidLayer {
            index,
            field,
            value,
            reason,
        };
        let t = self.thickness_mm;
        if t.is_nan() || t <= 0.0 {
            return Err(invalid(
                "thickness_mm",
                t,
                "must be positive (inf for semi-infinite)",
            ));
        }
        if t.is_infinite() && !last {
            return Err(invalid(
                "thickness_mm",
                t,
                "only the last layer may be semi-infinite",
            ));
        }
        if !(self.mu_a.is_finite() && (0.0..=MAX_COEFFICIENT_PER_MM).contains(&self.mu_a)) {
            return Err(invalid(
                "mu_a",
                self.mu_a,
                "must be in [0, 1e6] (1/mm; skin is ~0.01-10)",
            ));
        }
        if !(self.mu_s.is_finite() && (0.0..=MAX_COEFFICIENT_PER_MM).contains(&self.mu_s)) {
            return Err(invalid(
                "mu_s",
                self.mu_s,
                "must be in [0, 1e6] (1/mm; skin is ~1-100)",
            ));
        }
        if !(self.g > -1.0 && self.g < 1.0) {
            return Err(invalid("g", self.g, "must be in (-1, 1)"));
        }
        if !(self.n.is_finite() && self.n >= 1.0) {
            return Err(invalid("n", self.n, "must be finite and >= 1"));
        }
        if t.is_infinite() && self.mu_t() == 0.0 {
            return Err(invalid(
                "mu_a",
                self.mu_a,
                "a semi-infinite layer must absorb or scatter (mu_a + mu_s > 0)",
            ));
        }
        Ok(())
    }
}

/// Layers from the surface down, with the refractive indices of the media above and below.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Medium {
    /// Top layer first.
    pub layers: Vec<Layer>,
    /// Refractive index of the ambient medium the beam comes from (1.0 for air).
    pub n_above: f64,
    /// Refractive index below the last layer (unused when it is semi-infinite).
    pub n_below: f64,
}

impl Medium {
    /// A single homogeneous slab between two ambient media.
    pub fn slab(layer: Layer, n_above: f64, n_below: f64) -> Self {
        Self {
            layers: vec![layer],
            n_above,
            n_below,
        }
    }

    /// Checks every layer and ambient index; the first problem found is returned.
    pub fn validate(&self) -> Result<(), McError> {
        if self.layers.is_empty() {
            return Err(McError::NoLayers);
        }
        let last = self.layers.len() - 1;
        for (index, layer) in self.layers.iter().enumerate() {
            layer.validate(index, index == last)?;
        }
        for (field, value) in [("n_above", self.n_above), ("n_below", self.n_below)] {
            if !(value.is_finite() && value >= 1.0) {
                return Err(McError::InvalidMedium {
                    field,
                    value,
                    reason: "refractive index must be finite and >= 1",
                });
            }
        }
        Ok(())
    }

    /// Depth of the bottom of the last layer, mm (infinite for a semi-infinite medium).
    pub fn depth_mm(&self) -> f64 {
        self.layers.iter().map(|l| l.thickness_mm).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn skin() -> Layer {
        Layer {
            thickness_mm: 1.0,
            mu_a: 0.1,
            mu_s: 10.0,
            g: 0.8,
            n: 1.4,
        }
    }

    #[test]
    fn rejects_semi_infinite_layer_above_another() {
        let top = Layer {
            thickness_mm: f64::INFINITY,
            ..skin()
        };
        let medium = Medium {
            layers: vec![top, skin()],
            n_above: 1.0,
            n_below: 1.0,
        };
        let err = medium.validate().unwrap_err();
        assert!(matches!(
            err,
            McError::InvalidLayer {
                index: 0,
                field: "thickness_mm",
                ..
            }
        ));
    }

    #[test]
    fn rejects_out_of_range_parameters() {
        for (layer, field) in [
            (Layer { g: 1.0, ..skin() }, "g"),
            (
                Layer {
                    mu_a: -1.0,
                    ..skin()
                },
                "mu_a",
            ),
            (
                Layer {
                    mu_s: f64::NAN,
                    ..skin()
                },
                "mu_s",
            ),
            (Layer { n: 0.9, ..skin() }, "n"),
            (
                Layer {
                    thickness_mm: 0.0,
                    ..skin()
                },
                "thickness_mm",
            ),
        ] {
            let err = Medium::slab(layer, 1.0, 1.0).validate().unwrap_err();
            match err {
                McError::InvalidLayer { field: f, .. } => assert_eq!(f, field),
                other => panic!("expected InvalidLayer for {field}, got {other}"),
            }
        }
        assert!(Medium::slab(skin(), 0.5, 1.0).validate().is_err());
        assert!(
            Medium {
                layers: vec![],
                n_above: 1.0,
                n_below: 1.0
            }
            .validate()
            .is_err()
        );
    }

    #[test]
    fn albedo_slab_has_unit_attenuation() {
        let layer = Layer::from_albedo(0.9, 2.0, 0.5, 1.4);
        assert!((layer.mu_t() - 1.0).abs() < 1e-15);
        assert!((layer.mu_s / layer.mu_t() - 0.9).abs() < 1e-15);
    }
}

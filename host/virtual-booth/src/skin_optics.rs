//! Optical properties of layered skin from the literature, per camera colour channel.
//!
//! Conventions
//! - Units: coefficients in 1/mm, thicknesses in mm; wavelengths in nm.
//! - Channels are represented by one wavelength each (R 630 nm, G 540 nm, B 470 nm), the centres
//!   of typical camera colour filters.
//! - Layers are listed from the surface down; the last layer is semi-infinite.
//!
//! Sources (the formulas are evaluated in code so the numbers can be traced):
//! - Jacques S.L., "Skin optics", Oregon Medical Laser Center News, Jan 1998 (also summarised in
//!   Jacques 2013, "Optical properties of biological tissues: a review", Phys. Med. Biol. 58 R37):
//!   melanosome absorption `mu_a.mel = 6.6e11 * lambda^-3.33` 1/cm; bloodless tissue baseline
//!   `mu_a.skinbaseline = 0.244 + 85.3 exp(-(lambda - 154) / 66.2)` 1/cm; dermal reduced
//!   scattering (Mie + Rayleigh) `mu_s' = 2e5 lambda^-1.5 + 2e12 lambda^-4` 1/cm, which the
//!   epidermis shares; melanin volume fraction of the epidermis 1.3-6.3 % (light), 11-16 %
//!   (moderately pigmented), 18-43 % (darkly pigmented).
//! - Prahl S., "Optical absorption of hemoglobin", OMLC 1999 (tabulated from Gratzer and Kollias):
//!   molar extinction of HbO2 / Hb in cm^-1/M at 470 nm 33209.2 / 16156.4, 540 nm 53236 / 46592,
//!   630 nm 610 / 5148.8; whole blood 150 g/L haemoglobin (64 500 g/mol):
//!   `mu_a = 2.303 * e * 150 / 64500` 1/cm.
//! - van Gemert M.J.C. et al. 1989, "Skin optics", IEEE TBME 36:1146: dermal anisotropy
//!   `g = 0.62 + 0.29e-3 * lambda`.
//! - Meglinski I.V. & Matcher S.J. 2002, Physiol. Meas. 23:741: layer thicknesses (epidermis
//!   ~0.1 mm, papillary dermis ~0.15 mm, upper blood net plexus ~0.08 mm) and refractive index of
//!   the dermis ~1.4.

use serde::Serialize;

/// Wavelength representing each camera channel (R, G, B), nm.
pub const CHANNEL_WAVELENGTHS_NM: [f64; 3] = [630.0, 540.0, 470.0];

/// Molar extinction of oxy-/deoxy-haemoglobin at the channel wavelengths (Prahl 1999), cm^-1/M.
const HBO2_EXTINCTION: [f64; 3] = [610.0, 53236.0, 33209.2];
const HB_EXTINCTION: [f64; 3] = [5148.8, 46592.0, 16156.4];
/// Haemoglobin concentration of whole blood, g/L, and its molar mass, g/mol.
const BLOOD_HB_G_PER_L: f64 = 150.0;
const HB_MOLAR_MASS: f64 = 64_500.0;
/// Oxygen saturation of the dermal blood (mixed arterial/venous).
const BLOOD_OXYGEN_SATURATION: f64 = 0.75;
/// Refractive index of epidermis and dermis (Meglinski & Matcher 2002; DESIGN default eta).
pub const SKIN_INDEX: f64 = 1.4;

/// Absorption of melanosomes (Jacques 1998), 1/mm.
pub fn melanin_mu_a(lambda_nm: f64) -> f64 {
    6.6e11 * lambda_nm.powf(-3.33) / 10.0
}

/// Absorption of bloodless skin (Jacques 1998), 1/mm.
pub fn baseline_mu_a(lambda_nm: f64) -> f64 {
    (0.244 + 85.3 * (-(lambda_nm - 154.0) / 66.2).exp()) / 10.0
}

/// Absorption of whole blood at channel `c` (Prahl 1999), 1/mm.
pub fn blood_mu_a(c: usize) -> f64 {
    let s = BLOOD_OXYGEN_SATURATION;
    let extinction = s * HBO2_EXTINCTION[c] + (1.0 - s) * HB_EXTINCTION[c];
    2.303 * extinction * BLOOD_HB_G_PER_L / HB_MOLAR_MASS / 10.0
}

/// Reduced scattering of dermis and epidermis (Jacques 1998), 1/mm.
pub fn reduced_scattering(lambda_nm: f64) -> f64 {
    (2e5 * lambda_nm.powf(-1.5) + 2e12 * lambda_nm.powi(-4)) / 10.0
}

/// Henyey-Greenstein anisotropy of dermis (van Gemert et al. 1989).
pub fn anisotropy(lambda_nm: f64) -> f64 {
    0.62 + 0.29e-3 * lambda_nm
}

/// One layer's optics in the three channels.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LayerOptics {
    pub name: String,
    /// mm; infinite for the last (semi-infinite) layer.
    #[serde(serialize_with = "serialize_thickness")]
    pub thickness_mm: f64,
    /// Absorption per channel (R, G, B), 1/mm.
    pub mu_a: [f64; 3],
    /// Scattering per channel (not reduced), 1/mm.
    pub mu_s: [f64; 3],
    /// Henyey-Greenstein anisotropy per channel.
    pub g: [f64; 3],
    pub n: f64,
}

fn serialize_thickness<S: serde::Serializer>(t: &f64, s: S) -> Result<S::Ok, S::Error> {
    if t.is_finite() {
        s.serialize_f64(*t)
    } else {
        s.serialize_str("inf")
    }
}

/// A layered material: the skin at one kind of spot (base skin, freckle, vessel, stubble).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Material {
    pub name: String,
    /// Top layer first.
    pub layers: Vec<LayerOptics>,
}

/// Composition of a skin layer, from which its optics follow.
#[derive(Debug, Clone, Copy)]
struct Composition {
    /// Volume fraction of melanosomes.
    melanin: f64,
    /// Volume fraction of whole blood.
    blood: f64,
    /// Volume fraction of pigmented hair shafts (beard stubble), absorbing like melanosomes.
    hair: f64,
}

fn layer(name: &str, thickness_mm: f64, comp: Composition) -> LayerOptics {
    let mut mu_a = [0.0; 3];
    let mut mu_s = [0.0; 3];
    let mut g = [0.0; 3];
    for c in 0..3 {
        let lambda = CHANNEL_WAVELENGTHS_NM[c];
        let pigment = comp.melanin + comp.hair;
        mu_a[c] = pigment * melanin_mu_a(lambda)
            + comp.blood * blood_mu_a(c)
            + (1.0 - pigment - comp.blood) * baseline_mu_a(lambda);
        g[c] = anisotropy(lambda);
        mu_s[c] = reduced_scattering(lambda) / (1.0 - g[c]);
    }
    LayerOptics {
        name: name.into(),
        thickness_mm,
        mu_a,
        mu_s,
        g,
        n: SKIN_INDEX,
    }
}

/// A skin type: composition of the base skin and of its spatial variations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum SkinPreset {
    /// Lightly pigmented skin: epidermal melanin 2 % (Jacques 1998: 1.3-6.3 %).
    Light,
    /// Darkly pigmented skin: epidermal melanin 25 % (Jacques 1998: 18-43 %).
    Dark,
}

/// Thickness of the epidermis, mm (Meglinski & Matcher 2002: stratum corneum + living epidermis).
const EPIDERMIS_MM: f64 = 0.1;
/// Papillary dermis above the upper blood net plexus, mm (Meglinski & Matcher 2002).
const PAPILLARY_MM: f64 = 0.15;
/// Upper blood net plexus, mm (Meglinski & Matcher 2002 give 0.08 mm; a visible vessel is thicker).
const PLEXUS_MM: f64 = 0.2;
/// Dermal blood volume fraction (Jacques 1998: 0.2-7 %; 2 % typical).
const DERMAL_BLOOD: f64 = 0.02;
/// Blood fraction inside a superficial vessel / telangiectasia layer.
const VESSEL_BLOOD: f64 = 0.2;
/// Volume fraction of pigmented hair shafts through the stubble layers, and the melanin content
/// of a dark hair shaft relative to a melanosome.
const STUBBLE_HAIR_FRACTION: f64 = 0.08;
const HAIR_MELANIN_RELATIVE: f64 = 0.5;

/// Indices of the basis materials the maps blend (order of [`SkinPreset::materials`]).
pub const BASE: usize = 0;
pub const MELANIN_RICH: usize = 1;
pub const BLOOD_RICH: usize = 2;
pub const STUBBLE: usize = 3;
/// Number of basis materials.
pub const MATERIAL_COUNT: usize = 4;

impl SkinPreset {
    /// Epidermal melanin volume fraction of the base skin.
    pub fn melanin(self) -> f64 {
        match self {
            SkinPreset::Light => 0.02,
            SkinPreset::Dark => 0.25,
        }
    }

    /// Melanin of a mole (weight 1 in the melanin map); freckles use partial weights.
    fn mole_melanin(self) -> f64 {
        match self {
            SkinPreset::Light => 0.3,
            SkinPreset::Dark => 0.45,
        }
    }

    /// The basis materials, indexed by [`BASE`], [`MELANIN_RICH`], [`BLOOD_RICH`], [`STUBBLE`].
    pub fn materials(self) -> Vec<Material> {
        let dermis = Composition {
            melanin: 0.0,
            blood: DERMAL_BLOOD,
            hair: 0.0,
        };
        let epidermis = |melanin| Composition {
            melanin,
            blood: 0.0,
            hair: 0.0,
        };
        let with_hair = |c: Composition| Composition {
            hair: STUBBLE_HAIR_FRACTION * HAIR_MELANIN_RELATIVE,
            ..c
        };
        let m = self.melanin();
        vec![
            Material {
                name: "base".into(),
                layers: vec![
                    layer("epidermis", EPIDERMIS_MM, epidermis(m)),
                    layer("dermis", f64::INFINITY, dermis),
                ],
            },
            Material {
                name: "melanin-rich (mole)".into(),
                layers: vec![
                    layer("epidermis", EPIDERMIS_MM, epidermis(self.mole_melanin())),
                    layer("dermis", f64::INFINITY, dermis),
                ],
            },
            Material {
                name: "blood-rich (vessel plexus)".into(),
                layers: vec![
                    layer("epidermis", EPIDERMIS_MM, epidermis(m)),
                    layer("papillary dermis", PAPILLARY_MM, dermis),
                    layer(
                        "vessel plexus",
                        PLEXUS_MM,
                        Composition {
                            blood: VESSEL_BLOOD,
                            ..dermis
                        },
                    ),
                    layer("dermis", f64::INFINITY, dermis),
                ],
            },
            Material {
                name: "stubble".into(),
                layers: vec![
                    layer("epidermis + hair", EPIDERMIS_MM, with_hair(epidermis(m))),
                    layer("dermis + hair", 1.0, with_hair(dermis)),
                    layer("dermis", f64::INFINITY, dermis),
                ],
            },
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn literature_formulas_give_the_published_magnitudes() {
        // Jacques 1998: melanosome mu_a ~ 300/cm at 630 nm; dermis mu_s' ~ 25/cm at 630 nm.
        assert!(
            (melanin_mu_a(630.0) - 31.5).abs() < 0.5,
            "{}",
            melanin_mu_a(630.0)
        );
        assert!((reduced_scattering(630.0) - 2.5).abs() < 0.1);
        // Blood absorbs green far more than red (the haemoglobin Q bands).
        assert!(blood_mu_a(1) > 20.0 * blood_mu_a(0));
        assert!((blood_mu_a(0) - 0.934).abs() < 0.01, "{}", blood_mu_a(0));
    }

    #[test]
    fn dark_skin_absorbs_more_blue_in_the_epidermis_than_light_skin() {
        let light = &SkinPreset::Light.materials()[BASE].layers[0];
        let dark = &SkinPreset::Dark.materials()[BASE].layers[0];
        assert!(dark.mu_a[2] > 5.0 * light.mu_a[2]);
        // Both share the scattering of the dermis and the skin index.
        assert_eq!(dark.mu_s, light.mu_s);
        assert_eq!(dark.n, SKIN_INDEX);
    }
}

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

/// A skin type (Fitzpatrick I-VI): composition of the base skin and of its spatial variations.
///
/// The types differ only in epidermal melanin (blood and thicknesses as in the constants below).
/// Melanosome volume fractions of the epidermis from Jacques 1998 ("Skin optics"): lightly
/// pigmented adults 1.3-6.3 %, moderately pigmented 11-16 %, darkly pigmented 18-43 %, read as
/// types I-II, III-IV and V-VI. `light` and `dark` are the presets the project used before the
/// six types (types II and V), kept as aliases so earlier figures reproduce.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, clap::ValueEnum)]
pub enum SkinPreset {
    /// Type I (very light): epidermal melanin 1.3 % (Jacques 1998: lower end of 1.3-6.3 %).
    #[value(name = "I", alias = "i")]
    #[serde(rename = "I")]
    TypeI,
    /// Type II (light; alias `light`): epidermal melanin 2 % (Jacques 1998: 1.3-6.3 %).
    #[value(name = "II", alias = "ii", alias = "light")]
    #[serde(rename = "II")]
    TypeII,
    /// Type III (light brown): epidermal melanin 6.3 % (Jacques 1998: upper end of 1.3-6.3 %).
    #[value(name = "III", alias = "iii")]
    #[serde(rename = "III")]
    TypeIII,
    /// Type IV (moderate brown): epidermal melanin 13 % (Jacques 1998: 11-16 %).
    #[value(name = "IV", alias = "iv")]
    #[serde(rename = "IV")]
    TypeIV,
    /// Type V (dark brown; alias `dark`): epidermal melanin 25 % (Jacques 1998: 18-43 %).
    #[value(name = "V", alias = "v", alias = "dark")]
    #[serde(rename = "V")]
    TypeV,
    /// Type VI (very dark): epidermal melanin 40 % (Jacques 1998: upper end of 18-43 %).
    #[value(name = "VI", alias = "vi")]
    #[serde(rename = "VI")]
    TypeVI,
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
    /// The preset `--skin light` names (type II).
    pub const LIGHT: SkinPreset = SkinPreset::TypeII;
    /// The preset `--skin dark` names (type V).
    pub const DARK: SkinPreset = SkinPreset::TypeV;
    /// Every type, lightest first.
    pub const ALL: [SkinPreset; 6] = [
        SkinPreset::TypeI,
        SkinPreset::TypeII,
        SkinPreset::TypeIII,
        SkinPreset::TypeIV,
        SkinPreset::TypeV,
        SkinPreset::TypeVI,
    ];

    /// Epidermal melanin volume fraction of the base skin (sources on [`SkinPreset`]).
    pub fn melanin(self) -> f64 {
        match self {
            SkinPreset::TypeI => 0.013,
            SkinPreset::TypeII => 0.02,
            SkinPreset::TypeIII => 0.063,
            SkinPreset::TypeIV => 0.13,
            SkinPreset::TypeV => 0.25,
            SkinPreset::TypeVI => 0.40,
        }
    }

    /// The Fitzpatrick type's Roman numeral (what `--skin` takes and reports print).
    pub fn label(self) -> &'static str {
        match self {
            SkinPreset::TypeI => "I",
            SkinPreset::TypeII => "II",
            SkinPreset::TypeIII => "III",
            SkinPreset::TypeIV => "IV",
            SkinPreset::TypeV => "V",
            SkinPreset::TypeVI => "VI",
        }
    }

    /// Melanin of a mole (weight 1 in the melanin map); freckles use partial weights. A mole is
    /// darker than the skin around it: 0.3 on light skin (types I-III), rising with the base
    /// melanin to 0.45 (type V, as before) and 0.55 (type VI).
    fn mole_melanin(self) -> f64 {
        match self {
            SkinPreset::TypeI | SkinPreset::TypeII | SkinPreset::TypeIII => 0.3,
            SkinPreset::TypeIV => 0.35,
            SkinPreset::TypeV => 0.45,
            SkinPreset::TypeVI => 0.55,
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
        let light = &SkinPreset::LIGHT.materials()[BASE].layers[0];
        let dark = &SkinPreset::DARK.materials()[BASE].layers[0];
        assert!(dark.mu_a[2] > 5.0 * light.mu_a[2]);
        // Both share the scattering of the dermis and the skin index.
        assert_eq!(dark.mu_s, light.mu_s);
        assert_eq!(dark.n, SKIN_INDEX);
    }

    #[test]
    fn presets_span_the_literature_range_and_darken_monotonically() {
        // Jacques 1998: epidermal melanosome fraction from 1.3 % (light) to 43 % (dark).
        let melanin: Vec<f64> = SkinPreset::ALL.iter().map(|s| s.melanin()).collect();
        assert!(melanin[0] >= 0.013 && melanin[5] <= 0.43, "{melanin:?}");
        assert!(melanin.windows(2).all(|w| w[0] < w[1]), "{melanin:?}");
        // Blue absorption of the epidermis follows the melanin, and a mole stays darker than
        // the skin around it on every type.
        for s in SkinPreset::ALL {
            let m = s.materials();
            assert!(
                m[MELANIN_RICH].layers[0].mu_a[2] > m[BASE].layers[0].mu_a[2],
                "{s:?}"
            );
        }
        // `light` and `dark` name the presets they named before the six types.
        assert_eq!(SkinPreset::LIGHT.melanin(), 0.02);
        assert_eq!(SkinPreset::DARK.melanin(), 0.25);
    }

    #[test]
    fn light_and_dark_parse_as_aliases_of_types_ii_and_v() {
        use clap::ValueEnum;
        let parse = |s: &str| SkinPreset::from_str(s, false).ok();
        assert_eq!(parse("light"), Some(SkinPreset::TypeII));
        assert_eq!(parse("dark"), Some(SkinPreset::TypeV));
        assert_eq!(parse("VI"), Some(SkinPreset::TypeVI));
        assert_eq!(parse("i"), Some(SkinPreset::TypeI));
        assert_eq!(
            serde_json::to_value(SkinPreset::TypeIV).ok(),
            Some("IV".into())
        );
    }
}

//! The layers file: a layered medium in TOML, for `mlsss mc layers --file LAYERS.toml`.
//!
//! ```toml
//! # Refractive index above the surface (where the light comes from) and below the last layer.
//! n_above = 1.0
//! n_below = 1.0          # optional, default 1.0; ignored when the last layer is semi-infinite
//!
//! [[layer]]              # top layer first
//! name = "epidermis"     # optional, for messages
//! thickness_mm = 0.1     # mm; `inf` (TOML's infinity) for a semi-infinite last layer
//! mu_a = 0.5             # absorption coefficient, 1/mm
//! mu_s = 20.0            # scattering coefficient, 1/mm (not reduced)
//! g = 0.8                # Henyey-Greenstein anisotropy
//! n = 1.4                # refractive index
//!
//! [[layer]]
//! name = "dermis"
//! thickness_mm = inf
//! mu_a = 0.03
//! mu_s = 15.0
//! g = 0.85
//! n = 1.4
//! ```
//!
//! An example lives in `host/monte-carlo/data/skin-layers.toml`.

use std::path::Path;

use serde::Deserialize;

use super::{Layer, McError, Medium};

/// One `[[layer]]` table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayerEntry {
    /// Optional label.
    #[serde(default)]
    pub name: Option<String>,
    pub thickness_mm: f64,
    pub mu_a: f64,
    pub mu_s: f64,
    pub g: f64,
    pub n: f64,
}

/// The whole file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayersFile {
    pub n_above: f64,
    #[serde(default = "default_ambient")]
    pub n_below: f64,
    pub layer: Vec<LayerEntry>,
}

fn default_ambient() -> f64 {
    1.0
}

impl LayersFile {
    /// Reads a layers file and validates the medium it describes.
    pub fn read(path: &Path) -> Result<Self, McError> {
        let text = std::fs::read_to_string(path).map_err(|source| McError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parses layers TOML; `path` is only used in error messages.
    pub fn parse(text: &str, path: &Path) -> Result<Self, McError> {
        let file: LayersFile = toml::from_str(text).map_err(|e| {
            let (line, column) = mlsss_core::booth::toml_error_location(text, &e);
            McError::Parse {
                path: path.to_owned(),
                line,
                column,
                message: e.message().to_owned(),
            }
        })?;
        file.medium().validate()?;
        Ok(file)
    }

    /// The medium described by the file.
    pub fn medium(&self) -> Medium {
        Medium {
            layers: self
                .layer
                .iter()
                .map(|l| Layer {
                    thickness_mm: l.thickness_mm,
                    mu_a: l.mu_a,
                    mu_s: l.mu_s,
                    g: l.g,
                    n: l.n,
                })
                .collect(),
            n_above: self.n_above,
            n_below: self.n_below,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = include_str!("../data/skin-layers.toml");

    #[test]
    fn example_file_parses_into_a_two_layer_medium() {
        let file = LayersFile::parse(EXAMPLE, Path::new("skin-layers.toml")).unwrap();
        let medium = file.medium();
        assert_eq!(medium.layers.len(), 2);
        assert!(medium.layers[1].thickness_mm.is_infinite());
        assert_eq!(medium.n_above, 1.0);
    }

    #[test]
    fn unknown_key_is_reported_with_its_line() {
        let text = "n_above = 1.0\n[[layer]]\nthickness_mm = 1.0\nmu_a = 0.1\nmu_s = 1.0\ng = 0.0\nn = 1.4\nmus = 3\n";
        match LayersFile::parse(text, Path::new("x.toml")).unwrap_err() {
            McError::Parse { line, message, .. } => {
                assert_eq!(line, 8, "{message}");
                assert!(message.contains("mus"), "{message}");
            }
            other => panic!("expected a parse error, got {other}"),
        }
    }

    #[test]
    fn physically_invalid_layer_is_rejected() {
        let text = "n_above = 1.0\n[[layer]]\nthickness_mm = 1.0\nmu_a = 0.1\nmu_s = 1.0\ng = 1.5\nn = 1.4\n";
        assert!(matches!(
            LayersFile::parse(text, Path::new("x.toml")).unwrap_err(),
            McError::InvalidLayer { field: "g", .. }
        ));
    }
}

//! The booth description (`hardware/booth.toml`): camera, projectors, pattern plan and timing.
//!
//! Conventions
//! - World frame: millimetres, origin at the nominal subject centre, x right, y down, z away from the
//!   camera (OpenCV handedness). Device extrinsics follow OpenCV: `x_device = R x_world + t`.
//! - Intrinsics in pixels, pixel centres at integer coordinates, origin at the top-left pixel;
//!   distortion is OpenCV's `[k1, k2, p1, p2, k3]`.
//! - Projector response: emitted = black + (1 - black) * value^gamma, value in [0, 1].

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::calibration::{
    Calibration, DeviceCalibration, Extrinsics, Intrinsics, ProjectorCalibration, ProjectorResponse,
};

/// Errors reading a booth description.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BoothError {
    /// The file could not be read.
    #[error("cannot read booth file {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The TOML is malformed, or a field is missing or has the wrong type.
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        path: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    /// A field parsed but its value is not physically valid.
    #[error("{path}: invalid value for `{field}`: {reason}")]
    Invalid {
        path: PathBuf,
        field: String,
        reason: String,
    },
}

/// The camera of the booth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub width: u32,
    pub height: u32,
    /// Bits per sample of the sensor output (12 for the booth camera).
    pub bit_depth: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: [f64; 5],
    pub position_mm: [f64; 3],
    pub look_at_mm: [f64; 3],
    pub up: [f64; 3],
    /// Read noise, in digital numbers of the sensor output.
    pub read_noise_dn: f64,
    /// Electrons at saturation (sets the shot noise).
    pub full_well_e: f64,
    pub exposure_ms: f64,
}

/// One projector of the booth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectorSpec {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: [f64; 5],
    pub position_mm: [f64; 3],
    pub look_at_mm: [f64; 3],
    pub up: [f64; 3],
    /// Exponent of the response curve: emitted = black + (1 - black) * value^gamma.
    pub gamma: f64,
    /// Light emitted for a black pixel, as a fraction of white.
    pub black_level: f64,
    /// Standard deviation of the lens blur, in projector pixels.
    pub defocus_px: f64,
    /// This projector's own refresh rate (projectors are not genlocked).
    pub refresh_hz: f64,
    /// The monitor (video output of the booth PC) the projector is plugged into, as numbered by
    /// `mlsss rig displays`; absent: projector K is on monitor K.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub monitor: Option<u32>,
}

/// Geometry of the projected patterns (DESIGN section 3).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PatternSpec {
    pub gray_bits_x: u32,
    pub gray_bits_y: u32,
    pub slit_width_px: u32,
    pub slit_period_px: u32,
    pub hf_stripe_px: u32,
}

impl PatternSpec {
    /// Number of slit frames per axis (one period swept in steps of the slit width).
    pub fn slit_shifts(&self) -> u32 {
        self.slit_period_px / self.slit_width_px
    }

    /// Number of high-frequency frames (one full period shifted 1 px at a time).
    pub fn hf_shifts(&self) -> u32 {
        2 * self.hf_stripe_px
    }
}

/// Capture timing (DESIGN section 7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimingSpec {
    pub fps: f64,
    pub refresh_hz: f64,
    pub exposure_periods: u32,
    pub settle_vsyncs: u32,
    pub trigger_phase_us: u32,
    pub trigger_width_us: u32,
}

impl TimingSpec {
    /// Length of one frame slot in microseconds (200 000 at 5 fps).
    pub fn slot_us(&self) -> u32 {
        (1e6 / self.fps).round() as u32
    }
}

/// A whole booth: one camera, the projectors, the pattern plan and the timing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Booth {
    pub name: String,
    pub camera: CameraSpec,
    #[serde(rename = "projector")]
    pub projectors: Vec<ProjectorSpec>,
    pub patterns: PatternSpec,
    pub timing: TimingSpec,
}

/// The repository's default booth file, relative to the workspace root.
pub const DEFAULT_BOOTH_FILE: &str = "hardware/booth.toml";
/// The repository's `--quick` booth file, relative to the workspace root.
pub const QUICK_BOOTH_FILE: &str = "hardware/booth-quick.toml";

/// The booth files are compiled in so `mlsss` works from any directory.
const DEFAULT_BOOTH_TOML: &str = include_str!("../../../hardware/booth.toml");
const QUICK_BOOTH_TOML: &str = include_str!("../../../hardware/booth-quick.toml");

impl Booth {
    /// Reads and validates a booth description.
    pub fn from_file(path: &Path) -> Result<Self, BoothError> {
        let text = std::fs::read_to_string(path).map_err(|source| BoothError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml_str(&text, path)
    }

    /// The built-in default booth (`hardware/booth.toml`) or its `--quick` variant.
    pub fn builtin(quick: bool) -> Self {
        let (text, name) = if quick {
            (QUICK_BOOTH_TOML, QUICK_BOOTH_FILE)
        } else {
            (DEFAULT_BOOTH_TOML, DEFAULT_BOOTH_FILE)
        };
        Self::from_toml_str(text, Path::new(name))
            .unwrap_or_else(|e| panic!("built-in booth file is invalid (a build defect): {e}"))
    }

    /// Parses and validates booth TOML; `path` is only used in error messages.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Self, BoothError> {
        let booth: Booth = toml::from_str(text).map_err(|e| {
            let (line, column) = toml_error_location(text, &e);
            BoothError::Parse {
                path: path.to_owned(),
                line,
                column,
                message: e.message().to_owned(),
            }
        })?;
        booth.validate(path)?;
        Ok(booth)
    }

    fn validate(&self, path: &Path) -> Result<(), BoothError> {
        let invalid = |field: String, reason: &str| BoothError::Invalid {
            path: path.to_owned(),
            field,
            reason: reason.to_owned(),
        };
        let c = &self.camera;
        if c.width == 0 || c.height == 0 {
            return Err(invalid("camera.width/height".into(), "must be positive"));
        }
        if !(1..=16).contains(&c.bit_depth) {
            return Err(invalid("camera.bit_depth".into(), "must be 1..=16"));
        }
        if !(c.fx > 0.0 && c.fy > 0.0) {
            return Err(invalid("camera.fx/fy".into(), "must be positive"));
        }
        if self.projectors.is_empty() {
            return Err(invalid(
                "projector".into(),
                "at least one [[projector]] is required",
            ));
        }
        for (i, p) in self.projectors.iter().enumerate() {
            let field = |name: &str| format!("projector[{i}].{name}");
            if p.width == 0 || p.height == 0 {
                return Err(invalid(field("width/height"), "must be positive"));
            }
            if !(p.fx > 0.0 && p.fy > 0.0) {
                return Err(invalid(field("fx/fy"), "must be positive"));
            }
            if !(p.gamma > 0.0 && p.gamma.is_finite()) {
                return Err(invalid(field("gamma"), "must be a positive number"));
            }
            if !(0.0..0.5).contains(&p.black_level) {
                return Err(invalid(field("black_level"), "must be in [0, 0.5)"));
            }
            if p.defocus_px.is_nan() || p.defocus_px < 0.0 {
                return Err(invalid(field("defocus_px"), "must be >= 0"));
            }
            if (1u64 << self.patterns.gray_bits_x) < p.width as u64
                || (1u64 << self.patterns.gray_bits_y) < p.height as u64
            {
                return Err(invalid(
                    "patterns.gray_bits_x/y".into(),
                    &format!("too few bits for a {}x{} projector", p.width, p.height),
                ));
            }
        }
        let pat = &self.patterns;
        if pat.slit_width_px == 0 || !pat.slit_period_px.is_multiple_of(pat.slit_width_px) {
            return Err(invalid(
                "patterns.slit_period_px".into(),
                "must be a positive multiple of slit_width_px",
            ));
        }
        if pat.hf_stripe_px == 0 {
            return Err(invalid("patterns.hf_stripe_px".into(), "must be positive"));
        }
        let t = &self.timing;
        if !(t.fps > 0.0 && t.refresh_hz > 0.0) {
            return Err(invalid("timing.fps/refresh_hz".into(), "must be positive"));
        }
        Ok(())
    }

    /// Ideal calibration of the camera (truth for the virtual booth).
    pub fn camera_calibration(&self) -> DeviceCalibration {
        let c = &self.camera;
        DeviceCalibration {
            width: c.width,
            height: c.height,
            intrinsics: Intrinsics {
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
                distortion: c.distortion,
            },
            extrinsics: Extrinsics::look_at(c.position_mm, c.look_at_mm, c.up),
        }
    }

    /// Ideal calibration of projector `k` (truth for the virtual booth).
    pub fn projector_calibration(&self, k: usize) -> Option<DeviceCalibration> {
        let p = self.projectors.get(k)?;
        Some(DeviceCalibration {
            width: p.width,
            height: p.height,
            intrinsics: Intrinsics {
                fx: p.fx,
                fy: p.fy,
                cx: p.cx,
                cy: p.cy,
                distortion: p.distortion,
            },
            extrinsics: Extrinsics::look_at(p.position_mm, p.look_at_mm, p.up),
        })
    }

    /// The exact calibration of this booth description (truth of the virtual booth).
    pub fn calibration(&self) -> Calibration {
        let projectors = self
            .projectors
            .iter()
            .enumerate()
            .filter_map(|(k, spec)| {
                Some(ProjectorCalibration {
                    device: self.projector_calibration(k)?,
                    response: Some(ProjectorResponse {
                        gamma: spec.gamma,
                        black_level: spec.black_level,
                    }),
                    rms_px: None,
                })
            })
            .collect();
        Calibration {
            camera: self.camera_calibration(),
            camera_rms_px: None,
            projectors,
        }
    }
}

/// 1-based line and column where a TOML parse error points (0, 0 when it has no span).
pub fn toml_error_location(text: &str, error: &toml::de::Error) -> (usize, usize) {
    error
        .span()
        .map(|span| line_column(text, span.start))
        .unwrap_or((0, 0))
}

/// 1-based line and column of a byte offset.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
    (line, column)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_booths_parse_and_match_design_numbers() {
        let full = Booth::builtin(false);
        assert_eq!((full.camera.width, full.camera.height), (1379, 1029));
        assert_eq!(full.projectors.len(), 4);
        assert!(
            full.projectors
                .iter()
                .all(|p| (p.width, p.height) == (1024, 768))
        );
        assert_eq!(full.timing.slot_us(), 200_000);
        assert_eq!(full.patterns.slit_shifts(), 10);
        assert_eq!(full.patterns.hf_shifts(), 6);
        let quick = Booth::builtin(true);
        assert_eq!(quick.projectors.len(), 4);
        assert_eq!(quick.patterns.slit_shifts(), 10);
    }

    #[test]
    fn missing_field_names_the_field_and_line() {
        let text = DEFAULT_BOOTH_TOML.replace("gamma = 2.1\n", "");
        let err = Booth::from_toml_str(&text, Path::new("b.toml")).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("gamma"), "{msg}");
        assert!(msg.starts_with("b.toml:"), "{msg}");
        // The error points into the second [[projector]] table, not at line 0.
        let BoothError::Parse { line, .. } = err else {
            panic!("expected a parse error, got {err:?}")
        };
        let second_projector_line = DEFAULT_BOOTH_TOML
            .lines()
            .enumerate()
            .filter(|(_, l)| l.starts_with("[[projector]]"))
            .nth(1)
            .map(|(i, _)| i + 1)
            .unwrap();
        assert!(line >= second_projector_line, "line {line}");
    }

    #[test]
    fn invalid_value_is_reported_with_its_field() {
        let text = DEFAULT_BOOTH_TOML.replacen("black_level = 0.02\n", "black_level = 0.9\n", 1);
        let err = Booth::from_toml_str(&text, Path::new("b.toml")).unwrap_err();
        assert!(
            err.to_string().contains("projector[0].black_level"),
            "{err}"
        );
    }

    #[test]
    fn wrong_type_reports_line_of_the_value() {
        let text = DEFAULT_BOOTH_TOML.replace("width = 1379", "width = \"wide\"");
        let err = Booth::from_toml_str(&text, Path::new("b.toml")).unwrap_err();
        let expected_line = DEFAULT_BOOTH_TOML
            .lines()
            .position(|l| l == "width = 1379")
            .unwrap()
            + 1;
        match err {
            BoothError::Parse { line, .. } => assert_eq!(line, expected_line),
            other => panic!("expected parse error, got {other:?}"),
        }
    }

    #[test]
    fn projector_monitors_are_read_and_optional() {
        let full = Booth::builtin(false);
        let monitors: Vec<_> = full.projectors.iter().map(|p| p.monitor).collect();
        assert_eq!(monitors, [Some(0), Some(1), Some(2), Some(3)]);
        // The quick booth leaves it out (projector K on monitor K), and a snapshot without it
        // round-trips without the key.
        let quick = Booth::builtin(true);
        assert!(quick.projectors.iter().all(|p| p.monitor.is_none()));
        let json = serde_json::to_string(&quick.projectors[0]).unwrap();
        assert!(!json.contains("monitor"), "{json}");
    }

    #[test]
    fn ray_through_projected_pixel_hits_the_point() {
        let booth = Booth::builtin(false);
        let cam = booth.camera_calibration();
        let p = nalgebra::Point3::new(12.0, -30.0, 25.0);
        let px = cam.project(&p).unwrap();
        let (o, d) = cam.ray(px.x, px.y);
        let along = (p - o).dot(&d);
        let closest = o + d * along;
        approx::assert_relative_eq!(closest, p, epsilon = 1e-6);
    }
}

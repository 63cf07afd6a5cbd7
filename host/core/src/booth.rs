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
    /// 0 for a slit width of 0 (which [`Booth::validate`] refuses).
    pub fn slit_shifts(&self) -> u32 {
        self.slit_period_px
            .checked_div(self.slit_width_px)
            .unwrap_or(0)
    }

    /// Number of high-frequency frames (one full period shifted 1 px at a time).
    pub fn hf_shifts(&self) -> u32 {
        self.hf_stripe_px.saturating_mul(2)
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

    /// Checks every value of the description (also of one read from a `capture.json`): finite,
    /// in range and consistent. `path` is only used in error messages.
    pub fn validate(&self, path: &Path) -> Result<(), BoothError> {
        let invalid = |field: String, reason: String| BoothError::Invalid {
            path: path.to_owned(),
            field,
            reason,
        };
        self.validate_camera().map_err(|(f, r)| invalid(f, r))?;
        if self.projectors.is_empty() {
            return Err(invalid(
                "projector".into(),
                "at least one [[projector]] is required".into(),
            ));
        }
        if self.projectors.len() > MAX_PROJECTORS {
            return Err(invalid(
                "projector".into(),
                format!("at most {MAX_PROJECTORS} projectors are supported"),
            ));
        }
        for (i, p) in self.projectors.iter().enumerate() {
            self.validate_projector(p)
                .map_err(|(f, r)| invalid(format!("projector[{i}].{f}"), r))?;
        }
        validate_patterns(&self.patterns).map_err(|e| invalid(e.field, e.reason))?;
        let t = &self.timing;
        if !(t.fps > 0.0 && t.fps.is_finite() && t.refresh_hz > 0.0 && t.refresh_hz.is_finite()) {
            return Err(invalid(
                "timing.fps/refresh_hz".into(),
                "must be finite and positive".into(),
            ));
        }
        Ok(())
    }

    /// The camera's values; on error the field (below `camera.`) and the reason.
    fn validate_camera(&self) -> Result<(), (String, String)> {
        let c = &self.camera;
        let field = |name: &str| format!("camera.{name}");
        check_image_size(c.width, c.height).map_err(|r| (field("width/height"), r))?;
        if !(1..=16).contains(&c.bit_depth) {
            return Err((field("bit_depth"), "must be 1..=16".into()));
        }
        check_intrinsics([c.fx, c.fy, c.cx, c.cy], &c.distortion)
            .map_err(|(f, r)| (field(f), r))?;
        check_pose(c.position_mm, c.look_at_mm, c.up).map_err(|(f, r)| (field(f), r))?;
        if !(c.read_noise_dn >= 0.0 && c.read_noise_dn.is_finite()) {
            return Err((field("read_noise_dn"), "must be finite and >= 0".into()));
        }
        if !(c.full_well_e > 0.0 && c.full_well_e.is_finite()) {
            return Err((field("full_well_e"), "must be finite and positive".into()));
        }
        if !(c.exposure_ms > 0.0 && c.exposure_ms.is_finite()) {
            return Err((field("exposure_ms"), "must be finite and positive".into()));
        }
        Ok(())
    }

    /// One projector's values; on error the field (below `projector[i].`) and the reason.
    fn validate_projector(&self, p: &ProjectorSpec) -> Result<(), (String, String)> {
        check_image_size(p.width, p.height).map_err(|r| ("width/height".into(), r))?;
        check_intrinsics([p.fx, p.fy, p.cx, p.cy], &p.distortion)
            .map_err(|(f, r)| (f.to_owned(), r))?;
        check_pose(p.position_mm, p.look_at_mm, p.up).map_err(|(f, r)| (f.to_owned(), r))?;
        if !(p.gamma > 0.0 && p.gamma.is_finite()) {
            return Err(("gamma".into(), "must be a positive number".into()));
        }
        if !(0.0..0.5).contains(&p.black_level) {
            return Err(("black_level".into(), "must be in [0, 0.5)".into()));
        }
        if !(p.defocus_px >= 0.0 && p.defocus_px <= MAX_DEFOCUS_PX) {
            return Err((
                "defocus_px".into(),
                format!("must be in [0, {MAX_DEFOCUS_PX}]"),
            ));
        }
        if !(p.refresh_hz > 0.0 && p.refresh_hz.is_finite()) {
            return Err(("refresh_hz".into(), "must be finite and positive".into()));
        }
        let pat = &self.patterns;
        // Bits are checked against 1..=MAX_GRAY_BITS in `validate_patterns`; clamp the shift here.
        let covers = |bits: u32, size: u32| (1u64 << bits.min(MAX_GRAY_BITS)) >= size as u64;
        if !covers(pat.gray_bits_x, p.width) || !covers(pat.gray_bits_y, p.height) {
            return Err((
                "width/height".into(),
                format!(
                    "a {}x{} projector needs more Gray-code bits than patterns.gray_bits_x/y = \
                     {}/{}",
                    p.width, p.height, pat.gray_bits_x, pat.gray_bits_y
                ),
            ));
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

/// Largest image side of a camera or projector, pixels (a booth camera is 1379 px wide).
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Largest number of pixels of a camera or projector image (64 Mpx: a frame is then 768 MB
/// of linear RGB already).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;
/// Largest number of Gray-code bits per axis (2^16 projector pixels; more cannot be shown).
pub const MAX_GRAY_BITS: u32 = 16;
/// Largest number of projectors (frame specs store the projector in a byte).
pub const MAX_PROJECTORS: usize = 255;
/// Largest number of slit shifts or high-frequency shifts per axis.
pub const MAX_PATTERN_SHIFTS: u32 = 256;
/// Largest projector defocus, projector pixels.
pub const MAX_DEFOCUS_PX: f64 = 100.0;

/// A camera or projector image size: positive and small enough to allocate.
fn check_image_size(width: u32, height: u32) -> Result<(), String> {
    if width == 0 || height == 0 {
        return Err(format!("must be positive, got {width}x{height}"));
    }
    if width > MAX_IMAGE_SIDE
        || height > MAX_IMAGE_SIDE
        || width as u64 * height as u64 > MAX_IMAGE_PIXELS
    {
        return Err(format!(
            "{width}x{height} is too large (at most {MAX_IMAGE_SIDE} px a side and \
             {MAX_IMAGE_PIXELS} px in all)"
        ));
    }
    Ok(())
}

/// Pinhole intrinsics `[fx, fy, cx, cy]` and distortion: finite, focal lengths positive.
fn check_intrinsics(k: [f64; 4], distortion: &[f64; 5]) -> Result<(), (&'static str, String)> {
    if !(k[0] > 0.0 && k[1] > 0.0 && k[0].is_finite() && k[1].is_finite()) {
        return Err(("fx/fy", "must be finite and positive".into()));
    }
    if !(k[2].is_finite() && k[3].is_finite()) {
        return Err(("cx/cy", "must be finite".into()));
    }
    if !distortion.iter().all(|d| d.is_finite()) {
        return Err(("distortion", "must be finite".into()));
    }
    Ok(())
}

/// A device pose given as position, point looked at and up hint: finite, the point looked at
/// away from the position, and `up` not along the viewing direction (else there is no pose).
fn check_pose(
    position: [f64; 3],
    look_at: [f64; 3],
    up: [f64; 3],
) -> Result<(), (&'static str, String)> {
    let finite = |v: [f64; 3]| v.iter().all(|x| x.is_finite());
    if !finite(position) || !finite(look_at) || !finite(up) {
        return Err(("position_mm/look_at_mm/up", "must be finite".into()));
    }
    let view = nalgebra::Vector3::from(look_at) - nalgebra::Vector3::from(position);
    if view.norm() < 1e-6 {
        return Err((
            "look_at_mm",
            "is the device's own position: look at a point in front of it".into(),
        ));
    }
    let up = nalgebra::Vector3::from(up);
    if up.norm() < 1e-12 || view.normalize().cross(&up.normalize()).norm() < 1e-6 {
        return Err((
            "up",
            "must be a non-zero vector not along the viewing direction".into(),
        ));
    }
    Ok(())
}

/// A value of the pattern plan out of range: the field (e.g. `patterns.slit_period_px`) and why.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{field}`: {reason}")]
pub struct InvalidPattern {
    pub field: String,
    pub reason: String,
}

/// The pattern plan: Gray-code bits in 1..=[`MAX_GRAY_BITS`], slit width and period positive
/// with the period a multiple of the width, a positive stripe width; a bounded number of shifts.
pub fn validate_patterns(pat: &PatternSpec) -> Result<(), InvalidPattern> {
    for (field, bits) in [
        ("patterns.gray_bits_x", pat.gray_bits_x),
        ("patterns.gray_bits_y", pat.gray_bits_y),
    ] {
        if !(1..=MAX_GRAY_BITS).contains(&bits) {
            return Err(InvalidPattern {
                field: field.into(),
                reason: format!("must be 1..={MAX_GRAY_BITS}, got {bits}"),
            });
        }
    }
    if pat.slit_width_px == 0 {
        return Err(InvalidPattern {
            field: "patterns.slit_width_px".into(),
            reason: "must be positive".into(),
        });
    }
    if pat.slit_period_px == 0 || !pat.slit_period_px.is_multiple_of(pat.slit_width_px) {
        return Err(InvalidPattern {
            field: "patterns.slit_period_px".into(),
            reason: format!(
                "must be a positive multiple of slit_width_px ({}), got {}",
                pat.slit_width_px, pat.slit_period_px
            ),
        });
    }
    if pat.slit_shifts() > MAX_PATTERN_SHIFTS {
        return Err(InvalidPattern {
            field: "patterns.slit_period_px".into(),
            reason: format!("at most {MAX_PATTERN_SHIFTS} slit widths per period"),
        });
    }
    if pat.hf_stripe_px == 0 || pat.hf_shifts() > MAX_PATTERN_SHIFTS {
        return Err(InvalidPattern {
            field: "patterns.hf_stripe_px".into(),
            reason: format!("must be 1..={}", MAX_PATTERN_SHIFTS / 2),
        });
    }
    Ok(())
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

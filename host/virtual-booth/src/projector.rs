//! The projector model: which projector pixel lights a surface point, how much light a pattern
//! emits there (response curve, black level, lens defocus), and the irradiance it produces
//! (inverse-square falloff, cosine of incidence).
//!
//! Conventions
//! - Projector pixel (u, v): column, row; pixel centres at integer coordinates, pixel `i` covers
//!   `[i - 0.5, i + 0.5)`; nothing is emitted outside `[-0.5, width - 0.5)`.
//! - Emission: a pixel showing value `x` emits `black + (1 - black) * x^gamma` (fraction of
//!   white); the lens blurs the pixel grid with a Gaussian of `defocus_px` (projector pixels).
//! - Irradiance unit: white on a plane perpendicular to the projector axis at the look-at distance
//!   gives irradiance 1. Radiant intensity grows as 1/cos^3 off axis so that this plane is evenly
//!   lit (the pixel grid is flat).

use nalgebra::{Point3, Vector3};

use mlsss_core::booth::{Booth, ProjectorSpec};
use mlsss_core::calibration::DeviceCalibration;
use mlsss_core::capture::{Axis, Pattern};
use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_1d};

/// Samples per projector pixel of the tabulated emission profiles.
const PROFILE_OVERSAMPLING: usize = 8;

/// One projector of the virtual booth.
#[derive(Debug, Clone)]
pub struct ProjectorModel {
    pub calib: DeviceCalibration,
    pub gamma: f64,
    pub black_level: f64,
    pub defocus_px: f64,
    /// Centre of projection, world mm.
    pub centre: Point3<f64>,
    axis: Vector3<f64>,
    /// Squared distance from the centre to the look-at point, mm^2 (irradiance normalisation).
    reference_distance_sq: f64,
}

/// Where a projector lights a surface point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Illumination {
    /// Sub-pixel projector coordinates.
    pub u: f64,
    pub v: f64,
    /// Irradiance per unit of emitted level (see the module conventions); 0 when the point faces
    /// away from the projector.
    pub irradiance_per_level: f64,
    /// Unit direction from the point towards the projector.
    pub to_light: Vector3<f64>,
}

impl ProjectorModel {
    /// Projector `k` of the booth.
    pub fn new(booth: &Booth, k: usize) -> Option<Self> {
        let spec: &ProjectorSpec = booth.projectors.get(k)?;
        let calib = booth.projector_calibration(k)?;
        let centre = calib.extrinsics.centre();
        let axis = calib.extrinsics.device_to_world_dir(&Vector3::z());
        let look_at = Point3::from(spec.look_at_mm);
        Some(Self {
            calib,
            gamma: spec.gamma,
            black_level: spec.black_level,
            defocus_px: spec.defocus_px,
            centre,
            axis,
            reference_distance_sq: (look_at - centre).norm_squared(),
        })
    }

    /// Emitted fraction of white for a requested pattern value.
    pub fn response(&self, value: f64) -> f64 {
        self.black_level + (1.0 - self.black_level) * value.clamp(0.0, 1.0).powf(self.gamma)
    }

    /// How this projector lights point `p` with outward normal `n` (ignoring occlusion).
    pub fn illuminate(&self, p: &Point3<f64>, n: &Vector3<f64>) -> Option<Illumination> {
        let uv = self.calib.project(p)?;
        let d = p - self.centre;
        let r2 = d.norm_squared();
        let dir = d / r2.sqrt();
        let cos_axis = dir.dot(&self.axis);
        if cos_axis <= 0.0 {
            return None;
        }
        let to_light = -dir;
        let cos_incidence = n.dot(&to_light).max(0.0);
        let intensity = self.reference_distance_sq / cos_axis.powi(3);
        Some(Illumination {
            u: uv.x,
            v: uv.y,
            irradiance_per_level: intensity * cos_incidence / r2,
            to_light,
        })
    }

    /// Whether (u, v) falls inside the projector image.
    pub fn in_image(&self, u: f64, v: f64) -> bool {
        u >= -0.5
            && v >= -0.5
            && u < self.calib.width as f64 - 0.5
            && v < self.calib.height as f64 - 0.5
    }

    /// The emitted light field of a pattern, through the response curve and the lens blur.
    pub fn emission(&self, pattern: &Pattern) -> EmissionField {
        let (w, h) = (self.calib.width as usize, self.calib.height as usize);
        let levels = |count: usize, value: &dyn Fn(u32) -> f32| -> Vec<f64> {
            (0..count)
                .map(|i| self.response(value(i as u32) as f64))
                .collect()
        };
        let ones = |count: usize| vec![1.0; count];
        let (along_u, along_v) = match *pattern {
            Pattern::White | Pattern::Black | Pattern::Grey { .. } => {
                let level = self.response(pattern.value(0, 0) as f64);
                (vec![level; w], ones(h))
            }
            Pattern::Gray { axis, .. } | Pattern::Slit { axis, .. } => match axis {
                Axis::X => (levels(w, &|u| pattern.value(u, 0)), ones(h)),
                Axis::Y => (ones(w), levels(h, &|v| pattern.value(0, v))),
            },
            Pattern::HighFrequency { .. } => (levels(w, &|u| pattern.value(u, 0)), ones(h)),
        };
        EmissionField {
            u: BlurredProfile::new(&along_u, self.defocus_px),
            v: BlurredProfile::new(&along_v, self.defocus_px),
        }
    }
}

/// A separable emitted light field: `emitted(u, v) = u_profile(u) * v_profile(v)`. Every pattern
/// of the capture format is constant along one projector axis, so this is exact for them.
#[derive(Debug, Clone)]
pub struct EmissionField {
    u: BlurredProfile,
    v: BlurredProfile,
}

impl EmissionField {
    /// Emitted fraction of white towards projector coordinates (u, v).
    pub fn at(&self, u: f64, v: f64) -> f32 {
        self.at_position(&self.position(u, v))
    }

    /// Where (u, v) falls on the tabulated profiles. Every emission field of one projector has
    /// the same sample layout, so a position found on one serves for all of them: a batch of
    /// frames locates each point once instead of once per frame.
    pub fn position(&self, u: f64, v: f64) -> ProfilePosition {
        ProfilePosition {
            u: self.u.position(u),
            v: self.v.position(v),
        }
    }

    /// Emitted fraction of white at a position found by [`Self::position`] (on this field or
    /// another field of the same projector); the same value as [`Self::at`].
    #[inline]
    pub fn at_position(&self, position: &ProfilePosition) -> f32 {
        (self.u.value(position.u) * self.v.value(position.v)) as f32
    }
}

/// A point's place on a projector's emission profiles: per axis, the sample below it and the
/// interpolation weight towards the next (`None` outside the profile, where nothing is emitted).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProfilePosition {
    u: Option<(usize, f64)>,
    v: Option<(usize, f64)>,
}

/// A row of pixel levels as a continuous function: box pixels convolved with the lens Gaussian,
/// tabulated at `PROFILE_OVERSAMPLING` samples per pixel.
#[derive(Debug, Clone)]
struct BlurredProfile {
    /// Coordinate of sample 0, projector pixels.
    start: f64,
    samples: Vec<f64>,
}

impl BlurredProfile {
    fn new(levels: &[f64], sigma_px: f64) -> Self {
        let os = PROFILE_OVERSAMPLING as f64;
        let pad = (4.0 * sigma_px).ceil() + 1.0;
        let start = -0.5 - pad;
        let count = ((levels.len() as f64 + 2.0 * pad) * os).ceil() as usize + 1;
        let coord = |i: usize| start + i as f64 / os;
        let level_at = |x: f64| {
            let pixel = (x + 0.5).floor();
            if pixel >= 0.0 && (pixel as usize) < levels.len() {
                levels[pixel as usize]
            } else {
                0.0
            }
        };
        // Each sample is the mean over its 1/os-wide interval; pixel edges fall on sample
        // centres, so probing a quarter interval either side gives that mean exactly.
        let quarter = 0.25 / os;
        let sharp: Vec<f64> = (0..count)
            .map(|i| 0.5 * (level_at(coord(i) - quarter) + level_at(coord(i) + quarter)))
            .collect();
        let samples = if sigma_px > 0.0 {
            // Truncated at 3.5 sigma, zero outside, each output divided by the weights' sum.
            let kernel = GaussianKernel::new(sigma_px * os, 3.5, Normalisation::Outputs);
            blur_1d(&sharp, &kernel, Border::Zero)
        } else {
            sharp
        };
        Self { start, samples }
    }

    /// The sample below `x` and the interpolation weight towards the next; `None` outside.
    fn position(&self, x: f64) -> Option<(usize, f64)> {
        let f = (x - self.start) * PROFILE_OVERSAMPLING as f64;
        if f < 0.0 {
            return None;
        }
        // f >= 0: truncation is the floor (and avoids a libm call on baseline x86-64).
        let i = f as usize;
        if i + 1 >= self.samples.len() {
            return None;
        }
        Some((i, f - i as f64))
    }

    /// Linear interpolation at a position from [`Self::position`]; 0 outside.
    #[inline]
    fn value(&self, position: Option<(usize, f64)>) -> f64 {
        let Some((i, t)) = position else {
            return 0.0;
        };
        match (self.samples.get(i), self.samples.get(i + 1)) {
            (Some(a), Some(b)) => a * (1.0 - t) + b * t,
            _ => 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn projector() -> ProjectorModel {
        ProjectorModel::new(&Booth::builtin(true), 0).unwrap()
    }

    #[test]
    fn white_on_the_axis_at_the_look_at_distance_gives_unit_irradiance() {
        let p = projector();
        let target = Point3::origin();
        let n = (p.centre - target).normalize();
        let ill = p.illuminate(&target, &n).unwrap();
        assert!((ill.irradiance_per_level - 1.0).abs() < 1e-12);
        let field = p.emission(&Pattern::White);
        assert!((field.at(ill.u, ill.v) - 1.0).abs() < 1e-6);
    }

    #[test]
    fn black_emits_the_black_level_and_grey_follows_the_gamma_curve() {
        let p = projector();
        let black = p.emission(&Pattern::Black).at(100.0, 80.0) as f64;
        assert!((black - p.black_level).abs() < 1e-6);
        let grey = p
            .emission(&Pattern::Grey { level_milli: 500 })
            .at(100.0, 80.0) as f64;
        let expected = p.black_level + (1.0 - p.black_level) * 0.5f64.powf(p.gamma);
        assert!((grey - expected).abs() < 1e-6);
        assert_eq!(p.emission(&Pattern::White).at(-3.0, 80.0), 0.0);
    }

    /// A position located on one pattern's field gives, on every other pattern's field of the
    /// same projector, exactly the value of locating it there.
    #[test]
    fn a_position_serves_every_pattern_of_the_projector() {
        use mlsss_core::capture::FramePlan;
        let booth = Booth::builtin(true);
        let p = projector();
        let fields: Vec<EmissionField> = FramePlan::scan(&booth.patterns, 1)
            .frames
            .iter()
            .map(|f| p.emission(&f.pattern))
            .collect();
        assert!(fields.len() > 20);
        let (w, h) = (p.calib.width as f64, p.calib.height as f64);
        for i in 0..500 {
            // Inside, at the edges and outside the image.
            let u = -8.0 + (w + 16.0) * ((i as f64 * 0.618).fract());
            let v = -8.0 + (h + 16.0) * ((i as f64 * 0.377).fract());
            let position = fields[0].position(u, v);
            for field in &fields {
                assert_eq!(
                    field.at_position(&position).to_bits(),
                    field.at(u, v).to_bits()
                );
            }
        }
    }

    #[test]
    fn defocus_keeps_the_mean_of_a_stripe_pattern_and_softens_edges() {
        let p = projector();
        let pattern = Pattern::HighFrequency {
            stripe: 3,
            shift: 0,
        };
        let field = p.emission(&pattern);
        // Mean over one period (6 px) equals the mean of the pixel levels.
        let mean: f64 = (0..600)
            .map(|i| field.at(60.0 + i as f64 / 100.0, 50.0) as f64)
            .sum::<f64>()
            / 600.0;
        let expected = 0.5 * (1.0 + p.black_level);
        assert!((mean - expected).abs() < 2e-3, "{mean} {expected}");
        // Pixel centres of lit stripes stay near 1; the edge between pixels 2 and 3 is half-way.
        let edge = field.at(62.5, 50.0) as f64;
        assert!((edge - expected).abs() < 0.02, "{edge}");
    }
}

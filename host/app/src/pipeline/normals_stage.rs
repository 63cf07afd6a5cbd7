//! Stage `normals`: 4-source near-light photometric stereo (`photometry::photometric_stereo`,
//! Barsky & Petrou 2003) on the separated images (which ones: [`PsInput`]), the projectors
//! acting as calibrated point lights placed at their centres of projection; by default combined
//! with the normals of the geometry stage's points (`photometry::normal_fusion`: the geometry's
//! low frequencies, photometric detail; [`NormalSource`]).
//!
//! Conventions
//! - World frame of the calibration, mm. Normals point out of the surface, towards the camera side.
//! - The projectors' irradiance: `projector_lights`.
//!
//! Artefacts in `OUT/normals/`: `normals.exr` (RGB = unit normal, 0 where unknown), `albedo.exr`
//! (RGB), `lights_used.exr` (one channel: number of lights photometric stereo used, 0 where it
//! flagged the pixel), `normals.png` (0.5 n + 0.5 preview), and `photometric_normals.exr`
//! (photometric stereo's own normals, [`photometric_normals_path`]).
//!
//! Report fragment: `pixels`, `solved`, `lights_used_mean`, flagged counts, and with ground truth
//! `mean_angular_error_deg`, `median_angular_error_deg`, `p95_angular_error_deg` over the solved
//! pixels of the truth mask, plus `coverage` (solved fraction of the truth mask).

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::geometry_stage::{GeometryReadError, load_point_normals, load_points_file, points_path};
use super::phase_clock::{PhaseClock, PhaseTimes};
use super::projector_lights::ProjectorLights;
use super::separate_stage::{direct_path, global_path, nayar_direct_path, white_path};
use super::{Stage, StageContext, StageFailure, write_side_by_side};
use mlsss_core::capture::{CaptureManifest, truth};
use mlsss_core::imageio::{self, GrayF32, ImageIoError};
use mlsss_vision::geometry::point_normals::{PointNormalParams, fit_point_normals};
use mlsss_vision::photometry::normal_fusion::{
    FusionError, FusionParams, FusionSummary, fuse_normals, photometric_noise_proxy,
};
use mlsss_vision::photometry::photometric_stereo::{
    Method, NormalMap, NormalMapStats, PhotometricStereoError, PsParams, angular_errors,
    solve_images,
};
use mlsss_vision::photometry::specular_ps::{SpecularParams, solve_specular};
use mlsss_vision::photometry::transmission_ps::{TransmissionParams, solve_transmitted};

/// The photometric-stereo stage.
pub const STAGE: Stage = Stage {
    name: "normals",
    // 9: the fusion reads the geometry stage's point normals.
    version: 9,
    inputs: &["separate", "geometry"],
    uses_calibration: true,
    run,
};

/// Which images photometric stereo reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PsInput {
    /// The direct image of the Nayar baseline (`separate_stage::nayar_direct_path`), whatever
    /// the separation method. With the Lambertian model it gave the lowest normal error of the
    /// inputs here on held-out quick heads (light skin 4.8 deg, dark 7.9; white 4.2 and 10.7;
    /// the kernel-aware direct 26 and 14, global 9.4 and 18; README). Why a worse separation makes better
    /// normals: photometric stereo needs Lambertian shading, and the Nayar "direct" image is
    /// mostly the short-range subsurface light, which is, while the surface's own reflection
    /// is a specular lobe.
    NayarDirect,
    /// The direct components of the separation (DESIGN). On skin the true direct part is the
    /// surface's specular reflection alone, which photometric stereo cannot read as Lambertian
    /// (36 deg mean error on the simulator's exact direct images of a quick head); what reaches
    /// it is the subsurface light the separation leaves in.
    Direct,
    /// The white frames without stray light (direct + global: subsurface light blurs the shading
    /// and follows the cosine law times skin's Fresnel transmittance). Default, with
    /// [`ShadingModel::Specular`].
    White,
    /// The global components of the separation (white less the direct part): Lambertian where
    /// the separation is right, but every error of the direct part lands in the shading.
    Global,
}

/// Where the surface points (light directions, falloff) come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PointSource {
    /// The triangulated points of the geometry stage.
    Geometry,
    /// The simulator's true points (isolates photometric errors from geometric ones).
    Truth,
}

/// Parameters of the normals stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct NormalsParams {
    pub input: PsInput,
    pub points: PointSource,
    pub method: Method,
    /// Shading model of the solve.
    pub model: ShadingModel,
    /// What the stage's normals are.
    pub source: NormalSource,
    pub fusion: FusionParams,
}

/// What the stage's normals are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormalSource {
    /// Photometric stereo's normals alone.
    Photometric,
    /// The geometry's low frequencies with photometric detail (`photometry::normal_fusion`).
    /// Default (README for figures).
    Fused,
}

/// What photometric stereo assumes the readings follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShadingModel {
    /// `rho cos(incidence)`: the textbook model, the baseline.
    Lambertian,
    /// `rho cos T / T(1)` with the Fresnel transmittance `T` of skin's surface
    /// (`photometry::transmission_ps`, ours). Quick light head, seed 7, white frames: 4.54 deg
    /// Lambertian, 2.31 deg with it; on the simulator's exact global images 2.96 and 1.22.
    Transmission,
    /// The transmission model plus the surface's white specular lobe, fitted per pixel
    /// (`photometry::specular_ps`, ours). Default: quick heads, seed 61, white frames, type II
    /// 2.31 deg with `Transmission`, 2.00 with it; type V 8.96 and 4.91.
    Specular,
}

impl Default for NormalsParams {
    fn default() -> Self {
        Self {
            // With the transmission model the white frames beat the Nayar direct image on
            // light skin (quick heads, seed 33: 2.31 deg against 5.09) and lose on dark skin
            // (8.97 against 7.29; README).
            input: PsInput::White,
            points: PointSource::Geometry,
            method: Method::Robust,
            model: ShadingModel::Specular,
            source: NormalSource::Fused,
            fusion: FusionParams::default(),
        }
    }
}

/// The normals stage's report fragment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalsReport {
    /// Pixels attempted (with a surface point).
    pub pixels: u64,
    /// Pixels solved.
    pub solved: u64,
    /// Mean number of lights used over the solved pixels.
    pub lights_used_mean: f64,
    pub flagged: NormalsFlagged,
    pub input: PsInput,
    pub points: PointSource,
    pub method: Method,
    #[serde(default = "lambertian")]
    pub model: ShadingModel,
    #[serde(default = "photometric")]
    pub source: NormalSource,
    /// With fusion: where each normal came from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fusion: Option<FusionSummary>,
    /// With ground truth: angular errors over the solved pixels of the truth mask.
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<NormalErrors>,
    /// Where the stage's time went: `read` (images and points), `photometric_stereo`, `fusion`,
    /// `write`, `truth`.
    #[serde(flatten, default)]
    pub timing: PhaseTimes,
}

fn lambertian() -> ShadingModel {
    ShadingModel::Lambertian
}

fn photometric() -> NormalSource {
    NormalSource::Photometric
}

/// Pixels photometric stereo flagged, by reason.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct NormalsFlagged {
    pub too_few_lights: u64,
    pub ill_conditioned: u64,
    pub no_signal: u64,
    pub back_facing: u64,
}

/// Normals against the simulator's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NormalErrors {
    pub mean_angular_error_deg: f64,
    pub median_angular_error_deg: f64,
    pub p95_angular_error_deg: f64,
    pub compared_pixels: u64,
    /// Solved fraction of the truth mask.
    pub coverage: f64,
}

impl NormalsReport {
    fn new(stats: &NormalMapStats, params: &NormalsParams) -> Self {
        Self {
            pixels: stats.pixels,
            solved: stats.solved,
            lights_used_mean: stats.lights_used_mean,
            flagged: NormalsFlagged {
                too_few_lights: stats.too_few_lights,
                ill_conditioned: stats.ill_conditioned,
                no_signal: stats.no_signal,
                back_facing: stats.back_facing,
            },
            input: params.input,
            points: params.points,
            method: params.method,
            model: params.model,
            source: params.source,
            fusion: None,
            truth: None,
            timing: PhaseTimes::default(),
        }
    }
}

/// Errors of the normals stage.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum NormalsStageError {
    /// An artefact could not be read or written.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// Photometric stereo refused its input.
    #[error(transparent)]
    PhotometricStereo(#[from] PhotometricStereoError),
    /// The calibration has fewer projectors than the capture.
    #[error("the calibration has {calibrated} projectors, the capture {captured}")]
    ProjectorCount { calibrated: usize, captured: usize },
    /// `points: truth` on a capture without ground truth.
    #[error("points = truth needs a simulated capture with truth/points.exr")]
    NoTruthPoints,
    /// The photometric and geometric normals could not be combined.
    #[error(transparent)]
    Fusion(#[from] FusionError),
    /// The points or their normals could not be read or differ from the images in size.
    #[error(transparent)]
    Geometry(#[from] GeometryReadError),
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: NormalsParams = ctx.params()?;
    super::fragment(&run_normals(ctx, &params).map_err(StageFailure::new)?)
}

fn run_normals(
    ctx: &StageContext,
    params: &NormalsParams,
) -> Result<NormalsReport, NormalsStageError> {
    let calib = ctx.calibration.ok_or(NormalsStageError::ProjectorCount {
        calibrated: 0,
        captured: 1,
    })?;
    let captured = ctx.capture.manifest.booth.projectors.len();
    if calib.projectors.len() < captured {
        return Err(NormalsStageError::ProjectorCount {
            calibrated: calib.projectors.len(),
            captured,
        });
    }
    let mut clock = PhaseClock::start();
    let images = read_images(ctx, params.input, captured)?;
    let (width, height) = images.first().map_or((0, 0), |i| i.dimensions());
    let points = read_points(ctx, params.points, (width, height))?;
    clock.lap("read");
    let lights = ProjectorLights::from_calibration(calib, captured, width, &points);
    let ps_params = PsParams {
        method: params.method,
        noise_floor: noise_floor(&ctx.capture.manifest, captured),
        ..PsParams::default()
    };
    let refs: Vec<&Rgb32FImage> = images.iter().collect();
    let map = match params.model {
        ShadingModel::Lambertian => solve_images(&refs, &lights, None, &ps_params)?,
        ShadingModel::Transmission => solve_transmitted(
            &refs,
            &lights,
            None,
            &ps_params,
            &TransmissionParams::default(),
        )?,
        ShadingModel::Specular => {
            solve_specular(&refs, &lights, None, &ps_params, &SpecularParams::default())?
        }
    };
    clock.lap("photometric_stereo");
    let photometric = map.normal_image();
    let mut report = NormalsReport::new(&map.stats(), params);
    // Photometric stereo's normals are written beside the fusion (phase `fusion`), as are the
    // artefacts beside the truth check (phase `write`; `truth` then only books what is left of
    // the check).
    let (written, fused) = rayon::join(
        || imageio::write_exr_rgb(&photometric_normals_path(&ctx.dir()), &photometric),
        || match params.source {
            NormalSource::Photometric => Ok(None),
            NormalSource::Fused => fused_normals(ctx, &map, &lights, params).map(Some),
        },
    );
    written?;
    let normals = match fused? {
        Some((normals, counts)) => {
            report.fusion = Some(counts);
            normals
        }
        None => photometric,
    };
    clock.lap("fusion");
    let truth_dir = ctx.truth_dir();
    let (written, truth) = rayon::join(
        || write_artefacts(&ctx.dir(), &map, &normals),
        || truth_dir.map(|t| truth_errors(&t, &normals)).transpose(),
    );
    written?;
    clock.lap("write");
    if let Some(errors) = truth? {
        report.truth = errors;
    }
    clock.lap("truth");
    report.timing = clock.finish();
    Ok(report)
}

/// Path of photometric stereo's own normals in the stage folder (`normals.exr` holds the
/// stage's normals, fused by default). The relighting model is fitted with these: they are the
/// shading normals of skin's subsurface light under a local shading model, which is what the
/// model renders. With the fused (truer) normals a quick light head (seed 1, `mlsss demo
/// --quick`) relit worse: subsurface error 0.115 -> 0.131, and MLSSS no longer beat the
/// homogeneous model (0.1148 against 0.1154 -> 0.1312 against 0.1307).
pub fn photometric_normals_path(dir: &Path) -> PathBuf {
    dir.join("photometric_normals.exr")
}

/// Photometric stereo's normals `map` combined with the normals of the surface points of
/// `lights` (`photometry::normal_fusion`), as an image, with where each came from. The
/// geometry's points come with their normals fitted by the geometry stage; the truth's are
/// fitted here, as the geometry stage would.
fn fused_normals(
    ctx: &StageContext,
    map: &NormalMap,
    lights: &ProjectorLights,
    params: &NormalsParams,
) -> Result<(Rgb32FImage, FusionSummary), NormalsStageError> {
    let geometry = match params.points {
        PointSource::Geometry => {
            load_point_normals(&ctx.stage_dir("geometry"), (map.width, map.height))?
        }
        PointSource::Truth => fit_point_normals(
            &lights.points,
            map.width,
            map.height,
            lights.camera_centre,
            &PointNormalParams::default(),
        ),
    };
    let photometric: Vec<[f32; 3]> = map.pixels.iter().map(|p| p.normal).collect();
    let noise = photometric_noise_proxy(map, lights);
    let fused = fuse_normals(&photometric, &noise, &geometry, &params.fusion)?;
    let data = fused.normals.into_iter().flatten().collect();
    // The fusion returns one normal per pixel of the map, so the buffer always fits.
    let image = Rgb32FImage::from_raw(map.width, map.height, data)
        .unwrap_or_else(|| Rgb32FImage::new(map.width, map.height));
    Ok((image, fused.summary))
}

/// Every projector's image of the separation that photometric stereo reads.
fn read_images(
    ctx: &StageContext,
    input: PsInput,
    captured: usize,
) -> Result<Vec<Rgb32FImage>, NormalsStageError> {
    let sep_dir = ctx.stage_dir("separate");
    // One file per thread: reading an EXR is mostly serial.
    let images = (0..captured)
        .into_par_iter()
        .map(|k| {
            let path = match input {
                PsInput::Direct => direct_path(&sep_dir, k),
                PsInput::White => white_path(&sep_dir, k),
                PsInput::NayarDirect => nayar_direct_path(&sep_dir, k),
                PsInput::Global => global_path(&sep_dir, k),
            };
            imageio::read_exr_rgb(&path)
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(images)
}

/// The surface points from `source`, checked to be the images' `size`.
fn read_points(
    ctx: &StageContext,
    source: PointSource,
    size: (u32, u32),
) -> Result<Rgb32FImage, NormalsStageError> {
    let path = match source {
        PointSource::Geometry => points_path(&ctx.stage_dir("geometry")),
        PointSource::Truth => ctx
            .truth_dir()
            .map(|t| truth::points(&t))
            .filter(|p| p.is_file())
            .ok_or(NormalsStageError::NoTruthPoints)?,
    };
    Ok(load_points_file(&path, size)?)
}

/// Writes `normals.exr`, `albedo.exr`, `lights_used.exr` and the `normals.png` preview to `dir`.
fn write_artefacts(
    dir: &Path,
    map: &NormalMap,
    normals: &Rgb32FImage,
) -> Result<(), NormalsStageError> {
    let (width, height) = normals.dimensions();
    write_side_by_side::<NormalsStageError>(vec![
        Box::new(|| Ok(imageio::write_exr_rgb(&dir.join("normals.exr"), normals)?)),
        Box::new(|| {
            Ok(imageio::write_exr_rgb(
                &dir.join("albedo.exr"),
                &map.albedo_image(),
            )?)
        }),
        Box::new(|| {
            Ok(write_lights_used(
                &dir.join("lights_used.exr"),
                map,
                (width, height),
            )?)
        }),
        Box::new(|| write_preview(&dir.join("normals.png"), normals)),
    ])
}

/// Writes how many lights photometric stereo used per pixel (0 where it flagged the pixel).
fn write_lights_used(
    path: &Path,
    map: &NormalMap,
    (width, height): (u32, u32),
) -> Result<(), ImageIoError> {
    let data = map
        .pixels
        .iter()
        .map(|p| {
            if p.normal == [0.0; 3] {
                0.0
            } else {
                p.lights_used() as f32
            }
        })
        .collect();
    imageio::write_exr_gray(
        path,
        &GrayF32 {
            width,
            height,
            data,
        },
    )
}

/// The normals' angular errors against the simulator's in `truth_dir`, over the solved pixels
/// of the truth mask; none when the truth's size differs or nothing was compared.
fn truth_errors(
    truth_dir: &Path,
    normals: &Rgb32FImage,
) -> Result<Option<NormalErrors>, NormalsStageError> {
    let truth_normals = imageio::read_exr_rgb(&truth::normals(truth_dir))?;
    let mask = image::open(truth::mask(truth_dir)).ok().map(|m| {
        m.to_luma8()
            .into_raw()
            .into_iter()
            .map(|v| v > 0)
            .collect::<Vec<bool>>()
    });
    if truth_normals.dimensions() == normals.dimensions()
        && let Some(errors) = angular_errors(normals, &truth_normals, mask.as_deref())
    {
        let skin = mask
            .as_ref()
            .map_or(0, |m| m.iter().filter(|v| **v).count());
        return Ok(Some(NormalErrors {
            mean_angular_error_deg: errors.mean_deg,
            median_angular_error_deg: errors.median_deg,
            p95_angular_error_deg: errors.p95_deg,
            compared_pixels: errors.pixels,
            coverage: errors.pixels as f64 / skin.max(1) as f64,
        }));
    }
    Ok(None)
}

fn write_preview(path: &Path, normals: &Rgb32FImage) -> Result<(), NormalsStageError> {
    let img = image::RgbImage::from_fn(normals.width(), normals.height(), |x, y| {
        let n = normals.get_pixel(x, y).0;
        if n == [0.0; 3] {
            image::Rgb([0, 0, 0])
        } else {
            image::Rgb(n.map(|v| ((0.5 * v + 0.5).clamp(0.0, 1.0) * 255.0).round() as u8))
        }
    });
    // Atomic: a reader (the HTML report, a viewer) never sees a half-written preview.
    Ok(imageio::write_png(path, &img)?)
}

/// Readings below this many sigmas of the camera's read noise, at the frames' exposure, are noise
/// to photometric stereo.
const NOISE_FLOOR_READ_SIGMAS: f64 = 8.0;

/// The solver's noise floor in frame units (full scale 1 at the nominal exposure): 8 read-noise
/// sigmas at the lowest metered exposure, never above the former fixed floor
/// (`PsParams::default`, 2e-3; 8 sigmas give 1.9e-3 on light skin metered at about 2x). Dark skin
/// is metered at 9-12x, so its frames' noise is that much lower and the fixed floor threw away
/// real grazing light: quick heads seed 81 (`--calib truth`), type VI 6.77 -> 5.08 deg at
/// coverage 0.82 -> 0.93, type V 4.33 -> 4.08, type I unchanged (2.08).
fn noise_floor(manifest: &CaptureManifest, projectors: usize) -> f64 {
    let fixed = PsParams::default().noise_floor;
    // The largest read noise of the frames: the projector metered at the lowest exposure.
    let read_sigma = (0..projectors)
        .map(|k| manifest.frame_noise_of(k).read_sigma)
        .fold(0.0, f64::max);
    let floor = NOISE_FLOOR_READ_SIGMAS * read_sigma;
    if floor.is_finite() && floor > 0.0 {
        floor.min(fixed)
    } else {
        fixed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::booth::Booth;
    use mlsss_core::capture::folder::CaptureKind;
    use mlsss_core::capture::{FramePlan, ProjectorExposure};

    /// A scan manifest of the quick booth whose projectors were metered at `scales`.
    fn metered(scales: &[f64]) -> CaptureManifest {
        let booth = Booth::builtin(true);
        let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
        let mut manifest = CaptureManifest::new(CaptureKind::Scan, booth, plan);
        manifest.exposure = scales
            .iter()
            .enumerate()
            .map(|(k, &scale)| ProjectorExposure {
                scale,
                ..ProjectorExposure::nominal(k as u8, &manifest.booth.timing)
            })
            .collect();
        manifest
    }

    #[test]
    fn the_noise_floor_is_eight_read_noise_sigmas_at_the_lowest_exposure_capped_at_the_fixed_one() {
        // Quick booth: 12-bit camera, read noise 2 DN. Dark skin metered at 9-12x nominal.
        let dark = noise_floor(&metered(&[12.0, 9.0, 10.0, 11.0]), 4);
        assert!((dark - 8.0 * 2.0 / 4095.0 / 9.0).abs() < 1e-12, "{dark}");
        // Light skin (about 2x): close to the fixed floor. Unmetered (nominal, 1x): 8 sigmas
        // would be 3.9e-3, so the fixed floor.
        let light = noise_floor(&metered(&[2.1; 4]), 4);
        assert!((light - 8.0 * 2.0 / 4095.0 / 2.1).abs() < 1e-12, "{light}");
        assert_eq!(noise_floor(&metered(&[]), 4), 2e-3);
    }
}

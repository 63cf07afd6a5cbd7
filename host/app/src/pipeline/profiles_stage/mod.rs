//! Stage `profiles` (DESIGN stage 6): the global part of every projector's 20 slit frames
//! (`subsurface::slit_global`) and the per-pixel geometry that turns them into 1-D radiance profiles
//! against the signed distance in mm on the surface (`subsurface::profiles`).
//!
//! Why the profiles are not stored: a pixel's profile is its 20 slit-frame values per projector
//! plus a few geometry numbers; stored for every pixel that is the slit frames themselves again
//! (1.4 GB of f32 for the full-size booth). The fit stage rebuilds them, for its training
//! projectors only, from the capture and the cached artefacts of decode, geometry, separate and
//! normals (a subtraction per frame): [`ProfileInputs::take_or_load`], which starts from this
//! stage's inputs in memory when it ran in the same `process` run ([`ProfileInputs::load`]
//! otherwise). This stage itself extracts only the slit frames its checks read (those with truth,
//! the plotted one). What it stores is small: the parameters the profiles were built with, a
//! scanline of measured global light for plots, and its checks.
//!
//! Artefacts in `OUT/profiles/`:
//! - `profiles.json`: [`ProfilesRecord`] (parameters, scanline row and columns, per projector
//!   counts).
//! - `scanline.svg`, `scanline.png`: R channel of the global part of projector
//!   `scanline_projector`'s first vertical slit frame along the scanline (a forehead row for a
//!   head: a quarter down the subject), measured and, for a simulated capture, true.
//!
//! Report fragment: per projector `pixels_with_profiles`, `slit_frames`, `blur_px`,
//! `black_level`; `scanline_row`; with ground truth `slit_global_rel_rmse` (relative RMS error of
//! the extracted global part against the simulator's, over the subject, for every slit frame with
//! truth) and, with [`ProfilesParams::compare_variants`], `slit_global_rel_rmse_hard_mask`
//! (unblurred slit edges) and `slit_global_rel_rmse_direct_{separation,none,colourless,auto}` (each
//! rule of [`DirectPart`]); `phase_s`, `phase_cpu_s`: where the stage's time went (`load`: the
//! inputs and the global light of the slit frames the checks read, `report`: the per-projector
//! figures, `truth`, `write`: the record and the scanline plot).

use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::decode_stage::{DecodeStageError, coords_path, load_coords};
use super::line_plot::{LinePlot, LinePlotError, Mark, Series};
use super::normals_stage::photometric_normals_path;
use super::phase_clock::{PhaseClock, PhaseTimes};
use super::separate_stage::{direct_path, global_path, stripe_blur};
use super::{Stage, StageContext, StageFailure};
use mlsss_core::calibration::DeviceCalibration;
use mlsss_core::capture::{Axis, CaptureError, FrameNoise, Pattern, truth};
use mlsss_core::imageio::{self, ImageIoError};
use mlsss_layer_model::profiles::{
    Falloff, GeometryMap, ProfileError, ProjectorIllumination, SlitStack, SlitSweep, pixel_geometry,
};
use mlsss_layer_model::slit_global::{
    SlitGlobalError, SweepExtraction, WhiteSeparation, slit_global,
};
use mlsss_layer_model::surface::{Surface, ViewRay};
use mlsss_vision::photometry::response::stray_light;

/// The profiles stage.
pub const STAGE: Stage = Stage {
    name: "profiles",
    version: 1,
    inputs: &["decode", "geometry", "separate", "normals"],
    uses_calibration: true,
    run,
};

/// Name of the record file in the stage folder.
pub const RECORD_FILE: &str = "profiles.json";

/// Parameters of the profiles stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProfilesParams {
    /// Refractive index of the skin (refraction of the light and view rays).
    pub eta: f64,
    /// View-ray model of DESIGN section 5. Default: the exit point (no view term; diffuse light
    /// leaving the skin, as the virtual booth's truth: `subsurface::layer_depth`).
    pub view_ray: ViewRay,
    /// Blur the slit edges by the projector defocus and pixel footprint when removing the direct
    /// reflection (see `subsurface::slit_global`).
    pub blur_edges: bool,
    /// Projector whose slit frame the scanline plot shows.
    pub scanline_projector: usize,
    /// Where the direct reflection on a lit slit comes from (see [`DirectPart`]).
    pub direct: DirectPart,
    /// [`DirectPart::Auto`]: direct fractions of a pixel's light over which the separated
    /// direct light goes from ignored to removed (see [`auto_direct_weight`]).
    pub direct_fraction_range: (f32, f32),
    /// Which projector coordinates place the slits on the surface (see [`SlitCoordinates`]).
    pub coordinates: SlitCoordinates,
    /// With ground truth, also extract every slit frame by the other rules (`VARIANTS`) and
    /// compare them with the truth. A design check, off by default: it decodes every slit frame
    /// again and extracts it four more times (about 4 s of the full-size booth's processing).
    pub compare_variants: bool,
    /// How the fits weigh each profile against the others (see [`ProfileWeights`]).
    pub weights: ProfileWeights,
}

/// How the layer fits (EM, dipole baseline) weigh a pixel's profiles against each other.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProfileWeights {
    /// By the information each carries under the camera's noise model at its projector's
    /// exposure (`Profile::information`: effective photons): a dim profile, from a projector at
    /// grazing incidence or far away, counts for less than a bright one.
    #[default]
    Information,
    /// Every profile alike (the paper's pooling).
    Equal,
}

/// The projector coordinates of each camera pixel that the profiles measure distances in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SlitCoordinates {
    /// The pixel's surface point projected into the projector through the calibration, where
    /// the projector decoded it (elsewhere none): the coordinates every render places a light's
    /// pattern with (`SubsurfaceModel::projector_coords`), so the fitted layers' shifts mean the
    /// same thing in the fit and in a relit image.
    #[default]
    Projected,
    /// The decoded Gray-code coordinates. Subsurface light blurs the stripes forward, away from
    /// the projector, so a pixel decodes the column lit slightly toward the light (0.1 mm on
    /// the quick demo's skin against the truth coordinates): measured in these coordinates the
    /// slit profiles lose the forward shift that the layer depth should explain
    /// (`subsurface::layer_depth`).
    Decoded,
}

/// Default of [`ProfilesParams::direct_fraction_range`], chosen by the held-out relighting error
/// (README, "Skin types and exposure"). Quick heads, held-out white, MLSSS: (0.2, 0.3) gave type I
/// 0.0905 and VI 0.339 (seed 31), but removed half of the separated direct light on a type-II
/// head (median direct fraction 0.21, seed 41: 0.120 against 0.102 with no direct part);
/// (0.25, 0.45) gave I 0.0847 and VI 0.387 (seed 31) and leaves light skin alone.
pub const DEFAULT_DIRECT_FRACTION_RANGE: (f32, f32) = (0.25, 0.45);

/// The direct (surface) reflection removed from a slit frame where the slit lands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DirectPart {
    /// Default. The separation stage's direct image (its method: kernel-aware by default, or
    /// Nayar et al.). With the separate stage's version 5 (dichromatic direct part) the best
    /// rule on every type tried: held-out relighting error on quick heads
    /// (`fit.heldout_global_rel_rmse.white.mlsss`, holdout 3, components 4, block 6), seed 97
    /// (seed 93): type I 0.069 (0.071) against `auto` 0.078 (0.082), V 0.098 (0.100) against
    /// 0.219 (0.212), VI 0.127 (0.128) against 0.188 (0.191). With the separation before it
    /// was the worse rule for light skin (seed 21: 0.181 against `none` 0.090; README).
    #[default]
    Separation,
    /// None: all light of a slit frame counts as subsurface light, and renders get no direct
    /// part. Right where the surface reflection is a small part of the light (light skin away
    /// from highlights: relative RMSE of the extracted slit light 0.105 against 0.95 with the
    /// Nayar separation, 0.71 colourless, on the quick booth), wrong where it is not: on very
    /// dark skin the surface reflection is as bright as the subsurface light and lands in every
    /// profile's peak.
    None,
    /// The separation's direct image made colourless: its smallest channel in every channel.
    /// Skin's surface reflection is a dielectric's, colourless under white light, while the
    /// subsurface light that contaminates the separated direct image (stripes not fine enough)
    /// is coloured and weakest in blue; the smallest channel bounds the surface reflection from
    /// above and the rest goes back to the subsurface part.
    Colourless,
    /// Per pixel from the data: the separation's direct image times a weight that
    /// grows with the share of the pixel's light the separation calls direct
    /// ([`auto_direct_weight`]). Where the surface reflection is small beside the subsurface
    /// light (light skin) this is [`DirectPart::None`], where it is large (dark skin,
    /// highlights) [`DirectPart::Separation`]: no skin type is needed, only the pixel's own
    /// light. The default before the separate stage's version 5.
    Auto,
}

/// Share of a pixel's white light that the separation calls direct, `mean(d) / mean(d + g)`
/// over the channels; `None` without light or with non-finite input.
pub fn direct_fraction(d: [f32; 3], g: [f32; 3]) -> Option<f32> {
    let direct = (d[0] + d[1] + d[2]) / 3.0;
    let total = direct + (g[0] + g[1] + g[2]) / 3.0;
    let f = direct / total;
    (total > 0.0 && f.is_finite()).then_some(f.clamp(0.0, 1.0))
}

/// [`DirectPart::Auto`]'s weight of the separated direct light of one pixel: 0 where the
/// separation calls at most `range.0` of the pixel's light direct, 1 from `range.1` on, linear
/// between; 0 without a finite [`direct_fraction`] (all light stays subsurface light).
///
/// Why a weight on the direct fraction: a separation leaves some short-range subsurface light
/// in its direct image, about a fifth of the subsurface light on light skin's quick heads
/// (`slit_global_rel_rmse_direct_separation`), while skin's surface reflection is a few percent
/// of its light there; so on a pixel whose direct fraction is about that leak, removing the
/// separated direct light costs more than leaving the surface reflection in the profiles. Where
/// melanin absorbs most of the subsurface light (type VI: the surface reflection is about as
/// bright as the subsurface light) the direct fraction is large and the separation's direct
/// image is mostly surface reflection; so are specular highlights on any skin.
pub fn auto_direct_weight(d: [f32; 3], g: [f32; 3], range: (f32, f32)) -> f32 {
    let Some(f) = direct_fraction(d, g) else {
        return 0.0;
    };
    let span = range.1 - range.0;
    if span.is_nan() || span <= 0.0 {
        // A step at the range's end (or no direct part for a nonsense range).
        return if f >= range.1 { 1.0 } else { 0.0 };
    }
    ((f - range.0) / span).clamp(0.0, 1.0)
}

impl DirectPart {
    /// Splits a white frame's separation `(direct, global)` by this rule (`fraction_range`:
    /// [`ProfilesParams::direct_fraction_range`], read by [`DirectPart::Auto`] only).
    pub fn split(
        self,
        fraction_range: (f32, f32),
        direct: &[[f32; 3]],
        global: &[[f32; 3]],
    ) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        direct
            .iter()
            .zip(global)
            .map(|(d, g)| {
                let keep = match self {
                    DirectPart::Separation => return (*d, *g),
                    DirectPart::None => [0.0; 3],
                    DirectPart::Colourless => [d[0].min(d[1]).min(d[2]).max(0.0); 3],
                    DirectPart::Auto => {
                        let w = auto_direct_weight(*d, *g, fraction_range);
                        d.map(|v| (w * v).max(0.0))
                    }
                };
                (keep, [0, 1, 2].map(|c| d[c] + g[c] - keep[c]))
            })
            .unzip()
    }
}

impl Default for ProfilesParams {
    fn default() -> Self {
        Self {
            eta: 1.4,
            view_ray: ViewRay::ExitPoint,
            blur_edges: true,
            scanline_projector: 0,
            direct: DirectPart::Separation,
            direct_fraction_range: DEFAULT_DIRECT_FRACTION_RANGE,
            coordinates: SlitCoordinates::Projected,
            compare_variants: false,
            weights: ProfileWeights::default(),
        }
    }
}

/// Errors of the profiles stage (and of rebuilding profiles in later stages).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ProfilesStageError {
    /// A frame could not be read.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// An artefact could not be read or written.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// Decoded coordinates could not be read.
    #[error(transparent)]
    Decode(#[from] DecodeStageError),
    /// The global part of a slit frame could not be extracted.
    #[error("projector {projector}: {source}")]
    SlitGlobal {
        projector: usize,
        source: SlitGlobalError,
    },
    /// Profiles could not be built.
    #[error(transparent)]
    Profile(#[from] ProfileError),
    /// A plot could not be written.
    #[error(transparent)]
    Plot(#[from] LinePlotError),
    /// The calibration has fewer projectors than the capture.
    #[error("the calibration has {calibrated} projectors, the capture {captured}")]
    ProjectorCount { calibrated: usize, captured: usize },
    /// An artefact's size differs from the camera's.
    #[error("{path} is {got:?}; the camera is {expected:?}")]
    Size {
        path: PathBuf,
        got: (u32, u32),
        expected: (u32, u32),
    },
    /// No pixel has a surface point and a normal.
    #[error("the geometry and normals stages left no surface pixel")]
    NoSurface,
    /// The record file could not be read or written.
    #[error("{path}: {message}")]
    Record { path: PathBuf, message: String },
}

/// The profiles stage's report fragment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProfilesReport {
    pub projectors: Vec<ProjectorProfilesReport>,
    /// Camera row of the plotted scanline.
    pub scanline_row: usize,
    pub eta: f64,
    pub view_ray: ViewRay,
    pub direct: DirectPart,
    /// With ground truth: relative RMS error of the extracted slit light, as configured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slit_global_rel_rmse: Option<f64>,
    /// With [`ProfilesParams::compare_variants`]: the same error of each of `VARIANTS`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slit_global_rel_rmse_hard_mask: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slit_global_rel_rmse_direct_separation: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slit_global_rel_rmse_direct_none: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slit_global_rel_rmse_direct_colourless: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slit_global_rel_rmse_direct_auto: Option<f64>,
    /// Where the stage's time went (see the module documentation).
    #[serde(flatten, default)]
    pub timing: PhaseTimes,
}

/// One projector's entry of [`ProfilesReport`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProjectorProfilesReport {
    pub projector: usize,
    pub pixels_with_profiles: usize,
    pub slit_frames: usize,
    pub blur_px: f64,
    pub black_level: f64,
    /// Over the subject: median share of a pixel's white light that the separation calls
    /// direct ([`direct_fraction`]), and the mean weight [`DirectPart::Auto`] gives the
    /// separated direct light (0: none removed, 1: all).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direct_fraction_median: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direct_weight_mean: Option<f64>,
}

/// Median [`direct_fraction`] and mean [`auto_direct_weight`] of projector `p` over `mask`.
fn direct_share(
    p: &ProjectorInputs,
    mask: &[bool],
    range: (f32, f32),
) -> (Option<f64>, Option<f64>) {
    let pairs = || {
        p.separation_direct
            .iter()
            .zip(&p.separation_global)
            .zip(mask)
            .filter(|(_, m)| **m)
            .map(|(dg, _)| dg)
    };
    let mut fractions: Vec<f32> = pairs()
        .filter_map(|(d, g)| direct_fraction(*d, *g))
        .collect();
    if fractions.is_empty() {
        return (None, None);
    }
    let mid = fractions.len() / 2;
    let median = *fractions.select_nth_unstable_by(mid, f32::total_cmp).1;
    let weights: Vec<f64> = pairs()
        .map(|(d, g)| f64::from(auto_direct_weight(*d, *g, range)))
        .collect();
    let mean = weights.iter().sum::<f64>() / weights.len() as f64;
    (Some(f64::from(median)), Some(mean))
}

/// What the stage stores about the profiles it built (read back by the fit stage).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProfilesRecord {
    pub params: ProfilesParams,
    /// Camera row of the plotted scanline and its first and last subject columns.
    pub scanline_row: usize,
    pub scanline_columns: (usize, usize),
    /// Per projector: pixels with a profile geometry.
    pub pixels_with_profiles: Vec<usize>,
}

impl ProfilesRecord {
    /// Reads `OUT/profiles/profiles.json`.
    pub fn load(dir: &Path) -> Result<Self, ProfilesStageError> {
        let path = dir.join(RECORD_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| ProfilesStageError::Record {
            path: path.clone(),
            message: e.to_string(),
        })?;
        serde_json::from_str(&text).map_err(|e| ProfilesStageError::Record {
            path,
            message: e.to_string(),
        })
    }
}

/// A white frame's direct and global parts by a [`DirectPart`] rule.
type WhiteParts = (Vec<[f32; 3]>, Vec<[f32; 3]>);

/// A white frame's parts and the slit-edge blur to use with them.
type WhiteSplit = (WhiteParts, f32);

/// One projector's inputs to the profiles.
#[derive(Debug, Clone)]
pub struct ProjectorInputs {
    pub k: usize,
    /// Optical centre (world, mm) and falloff of the projector as a light.
    pub centre: Vector3<f64>,
    pub falloff: Falloff,
    pub black_level: f32,
    /// Decoded projector coordinates per camera pixel.
    pub coords: Vec<Option<(f32, f32)>>,
    /// The separation stage's images as read.
    pub separation_direct: Vec<[f32; 3]>,
    pub separation_global: Vec<[f32; 3]>,
    /// The white frame's direct and global parts by a [`DirectPart`] rule other than
    /// [`DirectPart::Separation`] (derived from the images above); `None` under that rule,
    /// whose parts are the separation's own images. Private so that only
    /// [`ProfileInputs::load`] sets it, from [`ProfilesParams::direct`]; read through
    /// [`ProjectorInputs::direct_white`] and [`ProjectorInputs::global_white`].
    white_split: Option<WhiteParts>,
    /// Light of the other projectors' black level in every frame of this projector.
    pub stray: Vec<[f32; 3]>,
    pub blur_px: f32,
    /// Camera noise of this projector's frames when the fits weigh profiles by it
    /// ([`ProfileWeights::Information`]).
    pub noise: Option<FrameNoise>,
    /// Global part of slit frames (capture order): in the profiles stage the frames its checks
    /// read at the subject's pixels, in the fit's [`ProfileInputs::take_or_load`] every slit
    /// frame at the subject's pixels with projector coordinates; empty when not asked for.
    pub stack: SlitStack,
    /// Per-pixel profile geometry (`None`: off the subject, undecoded, facing away).
    pub geometry: GeometryMap,
}

impl ProjectorInputs {
    /// Direct part under white (separation stage), stray light removed; with
    /// [`DirectPart::None`] zero.
    pub fn direct_white(&self) -> &[[f32; 3]] {
        self.white_split
            .as_ref()
            .map_or(&self.separation_direct, |(direct, _)| direct)
    }

    /// Global part under white; with [`DirectPart::None`] the whole white frame.
    pub fn global_white(&self) -> &[[f32; 3]] {
        self.white_split
            .as_ref()
            .map_or(&self.separation_global, |(_, global)| global)
    }

    /// Frees the white frame's parts (the separation's images and any split of them) and the
    /// stray light; [`ProjectorInputs::direct_white`] and [`ProjectorInputs::global_white`] are
    /// empty after.
    pub fn release_white_images(&mut self) {
        self.white_split = None;
        for image in [
            &mut self.separation_direct,
            &mut self.separation_global,
            &mut self.stray,
        ] {
            *image = Vec::new();
        }
    }

    /// The projector as the subsurface library sees it.
    pub fn view(&self) -> ProjectorIllumination<'_> {
        ProjectorIllumination {
            centre: self.centre,
            falloff: self.falloff,
            coords: &self.coords,
        }
    }

    /// The slit sweep over this projector's global slit frames (empty without slits).
    pub fn sweep(&self) -> Result<SlitSweep<'_>, ProfileError> {
        let sweep = if self.stack.patterns().is_empty() {
            SlitSweep::new(&[], self.coords.len())?
        } else {
            SlitSweep::from_stack(&self.stack, self.coords.len())?
        };
        Ok(match self.noise {
            Some(noise) => sweep.with_noise(noise),
            None => sweep,
        })
    }

    /// Slit frame `j` (capture order) as a camera-sized image: zero at the pixels the stack does
    /// not hold.
    pub fn slit_image(&self, j: usize) -> Option<(Pattern, Vec<[f32; 3]>)> {
        let pattern = *self.stack.patterns().get(j)?;
        Some((pattern, self.stack.frame(j)?))
    }

    /// The patterns of the loaded slit frames, in capture order.
    pub fn slit_patterns(&self) -> Vec<Pattern> {
        self.stack.patterns().to_vec()
    }
}

/// Everything the profiles of a capture are built from.
#[derive(Debug, Clone)]
pub struct ProfileInputs {
    pub surface: Surface,
    /// Every projector of the capture, index = projector number.
    pub projectors: Vec<ProjectorInputs>,
    pub params: ProfilesParams,
}

fn pixels(img: &image::Rgb32FImage) -> Vec<[f32; 3]> {
    img.pixels().map(|p| p.0).collect()
}

fn read_rgb(path: &Path, size: (u32, u32)) -> Result<Vec<[f32; 3]>, ProfilesStageError> {
    let (width, height, pixels) = imageio::read_exr_rgb_pixels(path)?;
    if (width, height) != size {
        return Err(ProfilesStageError::Size {
            path: path.to_owned(),
            got: (width, height),
            expected: size,
        });
    }
    Ok(pixels)
}

/// The surface from the geometry stage's points and photometric stereo's normals (the shading
/// normals the model is fitted and rendered with, `normals_stage::photometric_normals_path`);
/// where photometric stereo flagged a pixel, the normal of the triangulated surface (facing the
/// camera).
pub fn load_surface(
    ctx: &StageContext,
    size: (u32, u32),
    camera_centre: Vector3<f64>,
) -> Result<Surface, ProfilesStageError> {
    let geo = ctx.stage_dir("geometry");
    // Three independent reads, each mostly serial EXR decoding: side by side.
    let ((points, depth), ps_normals) = rayon::join(
        || {
            rayon::join(
                || read_rgb(&geo.join("points.exr"), size),
                || imageio::read_exr_gray(&geo.join("depth.exr")),
            )
        },
        || read_rgb(&photometric_normals_path(&ctx.stage_dir("normals")), size),
    );
    let (points, depth, ps_normals) = (points?, depth?, ps_normals?);
    let (w, h) = (size.0 as usize, size.1 as usize);
    let mask: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            depth.data.get(i).is_some_and(|d| *d > 0.0) && points[i].iter().all(|v| v.is_finite())
        })
        .collect();
    let mut surface = Surface {
        width: w,
        height: h,
        points: points
            .par_iter()
            .map(|p| Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
            .collect(),
        normals: vec![Vector3::zeros(); w * h],
        mask,
        camera_centre,
    };
    let normals: Vec<Vector3<f64>> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            if !surface.mask[i] {
                return Vector3::zeros();
            }
            let n = Vector3::new(
                f64::from(ps_normals[i][0]),
                f64::from(ps_normals[i][1]),
                f64::from(ps_normals[i][2]),
            );
            if let Some(n) = n.try_normalize(1e-6) {
                return n;
            }
            surface
                .footprint(i)
                .and_then(|fp| fp.dx.cross(&fp.dy).try_normalize(1e-12))
                .map(|n| {
                    let to_camera = camera_centre - surface.points[i];
                    if n.dot(&to_camera) < 0.0 { -n } else { n }
                })
                .unwrap_or_else(Vector3::zeros)
        })
        .collect();
    for (i, n) in normals.iter().enumerate() {
        if n.norm_squared() == 0.0 {
            surface.mask[i] = false;
        }
    }
    surface.normals = normals;
    if !surface.mask.iter().any(|m| *m) {
        return Err(ProfilesStageError::NoSurface);
    }
    Ok(surface)
}

/// `decoded`'s pixels (on the subject) with the projection of their surface point instead.
fn projected_coords(
    surface: &Surface,
    device: &DeviceCalibration,
    decoded: &[Option<(f32, f32)>],
) -> Vec<Option<(f32, f32)>> {
    decoded
        .par_iter()
        .enumerate()
        .map(|(i, c)| {
            c.filter(|_| surface.mask[i])?;
            let q = device.project(&Point3::from(surface.points[i]))?;
            Some((q.x as f32, q.y as f32))
        })
        .collect()
}

impl ProfileInputs {
    /// What the profiles stage of this run handed over, else [`ProfileInputs::load`], with
    /// every slit frame of the projectors in `with_slits` stacked at the subject's pixels that
    /// have projector coordinates (a profile geometry needs them), the others' slits dropped.
    /// Why the fit stacks them and not the profiles stage: the profiles stage's own checks read
    /// a few slit frames a projector, and the fit's slits are those of the training projectors
    /// only (at full size the held-out projector's 20 frames were a quarter of the extraction's
    /// ~2.4 CPU-s and 139 MB, stacked for nothing).
    pub fn take_or_load(
        ctx: &StageContext,
        params: &ProfilesParams,
        with_slits: &[usize],
    ) -> Result<Self, ProfilesStageError> {
        let mut inputs = match ctx.take_handed_over::<ProfileInputs>(STAGE.name) {
            Some(inputs) if inputs.params == *params => inputs,
            _ => Self::load(ctx, params)?,
        };
        // The profiles stage's few frames go first.
        for p in &mut inputs.projectors {
            p.stack = SlitStack::default();
        }
        let mask = &inputs.surface.mask;
        for p in &mut inputs.projectors {
            if with_slits.contains(&p.k) {
                let kept = (0..mask.len())
                    .filter(|&i| mask[i] && p.coords.get(i).is_some_and(Option::is_some))
                    .collect();
                p.stack = stacked_slit_globals(ctx, p, slit_frames(ctx, p.k), kept)?;
            }
        }
        Ok(inputs)
    }

    /// Rebuilds the profiles' inputs from the cached artefacts: the surface and every
    /// projector's images and geometry, no slits ([`ProjectorInputs::stack`] empty).
    pub fn load(ctx: &StageContext, params: &ProfilesParams) -> Result<Self, ProfilesStageError> {
        let calib = ctx.calibration.ok_or(ProfilesStageError::ProjectorCount {
            calibrated: 0,
            captured: ctx.capture.manifest.booth.projectors.len(),
        })?;
        let captured = ctx.capture.manifest.booth.projectors.len();
        if calib.projectors.len() < captured {
            return Err(ProfilesStageError::ProjectorCount {
                calibrated: calib.projectors.len(),
                captured,
            });
        }
        let cam = &ctx.capture.manifest.booth.camera;
        let size = (cam.width, cam.height);
        let camera_centre = calib.camera.extrinsics.centre().coords;
        let black: Vec<f64> = (0..captured)
            .map(|k| calib.projectors[k].response.map_or(0.0, |r| r.black_level))
            .collect();
        // The surface, the stray light and every projector's cached images are independent
        // reads, each mostly serial EXR or PNG decoding: read side by side instead of one
        // after another (one core sat idle through them, about 0.8 CPU-s at full size).
        let (surface, (stray, cached)) = rayon::join(
            || load_surface(ctx, size, camera_centre),
            || {
                rayon::join(
                    || stray_for_all(ctx, &black),
                    || {
                        (0..captured)
                            .into_par_iter()
                            .map(|k| CachedImages::read(ctx, params, k, size))
                            .collect::<Result<Vec<_>, _>>()
                    },
                )
            },
        );
        let (surface, stray, cached) = (surface?, stray?, cached?);
        let mut projectors = Vec::with_capacity(captured);
        for (k, (stray, cached)) in stray.into_iter().zip(cached).enumerate() {
            let device = &calib.projectors[k].device;
            let centre = device.extrinsics.centre().coords;
            let falloff = Falloff::Projector {
                axis: device.extrinsics.device_to_world_dir(&Vector3::z()).into(),
                scale: centre.norm_squared(),
            };
            let CachedImages {
                decoded,
                separation_direct,
                separation_global,
                white_split,
            } = cached;
            let coords = match params.coordinates {
                SlitCoordinates::Decoded => decoded,
                SlitCoordinates::Projected => projected_coords(&surface, device, &decoded),
            };
            let mut inputs = ProjectorInputs {
                k,
                centre,
                falloff,
                black_level: black[k] as f32,
                separation_direct,
                separation_global,
                white_split,
                stray,
                blur_px: if params.blur_edges {
                    stripe_blur(ctx, k)
                } else {
                    0.0
                },
                noise: match params.weights {
                    ProfileWeights::Information => Some(ctx.capture.manifest.frame_noise_of(k)),
                    ProfileWeights::Equal => None,
                },
                stack: SlitStack::default(),
                coords,
                geometry: GeometryMap::default(),
            };
            inputs.geometry =
                pixel_geometry(&surface, &inputs.view(), params.eta, params.view_ray)?;
            projectors.push(inputs);
        }
        Ok(Self {
            surface,
            projectors,
            params: params.clone(),
        })
    }
}

/// What [`ProfileInputs::load`] reads of one projector from the earlier stages' artefacts and
/// does not need the surface for: its decoded coordinates and the separation's white images,
/// split by [`ProfilesParams::direct`] when that is not the separation's own split.
struct CachedImages {
    decoded: Vec<Option<(f32, f32)>>,
    separation_direct: Vec<[f32; 3]>,
    separation_global: Vec<[f32; 3]>,
    white_split: Option<WhiteParts>,
}

impl CachedImages {
    /// Projector `k`'s images, the three files read side by side (none without its
    /// coordinates file: no pixel decoded).
    fn read(
        ctx: &StageContext,
        params: &ProfilesParams,
        k: usize,
        size: (u32, u32),
    ) -> Result<Self, ProfilesStageError> {
        let path = coords_path(&ctx.stage_dir("decode"), k);
        let sep = ctx.stage_dir("separate");
        let (decoded, (separation_direct, separation_global)) = rayon::join(
            || -> Result<Vec<Option<(f32, f32)>>, ProfilesStageError> {
                if !path.is_file() {
                    return Ok(vec![None; size.0 as usize * size.1 as usize]);
                }
                Ok(load_coords(&path, size)?
                    .into_iter()
                    .map(|c| c.map(|(u, v)| (u as f32, v as f32)))
                    .collect())
            },
            || {
                rayon::join(
                    || read_rgb(&direct_path(&sep, k), size),
                    || read_rgb(&global_path(&sep, k), size),
                )
            },
        );
        let (decoded, separation_direct, separation_global) =
            (decoded?, separation_direct?, separation_global?);
        // The default rule keeps the separation's images as they are: no copies of them (at
        // full size 34 MB a projector, copied on one core each and faulted in: ~0.25 CPU-s).
        let white_split = (params.direct != DirectPart::Separation).then(|| {
            params.direct.split(
                params.direct_fraction_range,
                &separation_direct,
                &separation_global,
            )
        });
        Ok(Self {
            decoded,
            separation_direct,
            separation_global,
            white_split,
        })
    }
}

/// Stray light of every projector's frames (zeros when it cannot be estimated). The white frames
/// are decoded in parallel.
fn stray_for_all(
    ctx: &StageContext,
    black: &[f64],
) -> Result<Vec<Vec<[f32; 3]>>, ProfilesStageError> {
    let plan = &ctx.capture.manifest.plan;
    let cam = &ctx.capture.manifest.booth.camera;
    let n = (cam.width * cam.height) as usize;
    let indices: Option<Vec<u32>> = (0..black.len())
        .map(|k| plan.find(k as u8, &Pattern::White).map(|f| f.index))
        .collect();
    let Some(indices) = indices else {
        return Ok(vec![vec![[0.0; 3]; n]; black.len()]);
    };
    let whites = indices
        .par_iter()
        .map(|&index| ctx.capture.read_frame(index))
        .collect::<Result<Vec<_>, _>>()?;
    let refs: Vec<&image::Rgb32FImage> = whites.iter().collect();
    Ok(match stray_light(&refs, black) {
        Some(s) => s.iter().map(pixels).collect(),
        None => vec![vec![[0.0; 3]; n]; black.len()],
    })
}

/// The global parts of projector `p`'s slit frames `frames` (index and pattern, capture order)
/// at the camera pixels `kept` (ascending), stacked. The frames of one axis are read together
/// (in parallel, their sensor codes held: 85 MB at full size) and the stack is written in place
/// pixel by pixel from them, each pixel's frames together ([`SweepExtraction`]: the slits of an axis share edges,
/// whose `erf` a pixel computes once). Why: a camera-sized (and then a subject-sized) buffer of
/// linear values per frame, extracted and gathered into the stack after, was fresh memory for
/// the kernel to fault in, frame after frame (a fifth of the stage's CPU time with the copies).
fn stacked_slit_globals(
    ctx: &StageContext,
    p: &ProjectorInputs,
    frames: Vec<(u32, Pattern)>,
    kept: Vec<usize>,
) -> Result<SlitStack, ProfilesStageError> {
    let white = WhiteSeparation {
        direct: p.direct_white(),
        global: p.global_white(),
        stray: &p.stray,
        black_level: p.black_level,
        blur_px: p.blur_px,
    };
    let slit_error = |source| ProfilesStageError::SlitGlobal {
        projector: p.k,
        source,
    };
    let patterns: Vec<Pattern> = frames.iter().map(|&(_, pattern)| pattern).collect();
    let n = p.coords.len();
    let sweep = SweepExtraction::new(n, &patterns, &p.coords, &white).map_err(slit_error)?;
    let mut stack = SlitStack::zeros(patterns, n, kept)?;
    for range in same_axis_runs(&frames) {
        let samples = frames[range.clone()]
            .par_iter()
            .map(|&(index, _)| ctx.capture.read_frame_samples(index))
            .collect::<Result<Vec<_>, _>>()?;
        if let Some(short) = samples.iter().find(|s| s.len() != n) {
            return Err(ProfilesStageError::Size {
                path: ctx.capture.root.join("frames"),
                got: (short.len() as u32, 1),
                expected: (n as u32, 1),
            });
        }
        let first = range.start;
        stack.fill_frames(range.clone(), |i, out| {
            // Every frame holds pixel `i` (sizes checked above): the NaN is never read.
            let value = |j: usize| samples[j - first].rgb(i).unwrap_or([f32::NAN; 3]);
            sweep
                .pixel(i, range.clone(), value, out)
                .map_err(slit_error)
        })?;
    }
    Ok(stack)
}

/// The runs of consecutive `frames` of the same slit axis, as index ranges (a capture's slits
/// come axis by axis: two runs).
fn same_axis_runs(frames: &[(u32, Pattern)]) -> Vec<std::ops::Range<usize>> {
    let axis = |j: usize| match frames[j].1 {
        Pattern::Slit { axis, .. } => Some(axis),
        _ => None,
    };
    let mut runs = Vec::new();
    let mut start = 0;
    for j in 1..=frames.len() {
        if j == frames.len() || axis(j) != axis(start) {
            runs.push(start..j);
            start = j;
        }
    }
    runs
}

/// Frame index and pattern of projector `k`'s slit frames, in capture order.
fn slit_frames(ctx: &StageContext, k: usize) -> Vec<(u32, Pattern)> {
    ctx.capture
        .manifest
        .plan
        .for_projector(k as u8)
        .filter(|f| matches!(f.pattern, Pattern::Slit { .. }))
        .map(|f| (f.index, f.pattern))
        .collect()
}

/// The slit frames of projector `k` (index and pattern, capture order) this stage reads itself,
/// at the subject's pixels: those with truth (the truth check's; none without `truth_dir`) and,
/// for the projector of the scanline plot, its reference slit ([`reference_slit`]).
fn checked_slit_frames(
    ctx: &StageContext,
    k: usize,
    params: &ProfilesParams,
    truth_dir: Option<&Path>,
) -> Vec<(u32, Pattern)> {
    let frames = slit_frames(ctx, k);
    let patterns: Vec<Pattern> = frames.iter().map(|&(_, pattern)| pattern).collect();
    let plotted = (k == params.scanline_projector)
        .then(|| reference_slit(&patterns))
        .flatten();
    frames
        .into_iter()
        .enumerate()
        .filter(|&(j, (_, pattern))| {
            Some(j) == plotted || truth_dir.is_some_and(|t| truth::global(t, k, &pattern).is_file())
        })
        .map(|(_, frame)| frame)
        .collect()
}

/// The scanline of the plots: a quarter down the subject (the forehead of a head), over the
/// subject's columns on that row.
pub fn scanline(surface: &Surface) -> (usize, (usize, usize)) {
    let rows: Vec<usize> = (0..surface.height)
        .filter(|&y| (0..surface.width).any(|x| surface.mask[y * surface.width + x]))
        .collect();
    let (top, bottom) = (
        rows.first().copied().unwrap_or(0),
        rows.last().copied().unwrap_or(0),
    );
    let row = top + (bottom - top) / 4;
    let cols: Vec<usize> = (0..surface.width)
        .filter(|&x| surface.mask[row * surface.width + x])
        .collect();
    (
        row,
        (
            cols.first().copied().unwrap_or(0),
            cols.last().copied().unwrap_or(0),
        ),
    )
}

/// Index of the first vertical slit (offset 0) of a sweep's `patterns`, the pattern the plots
/// show (else the first).
pub fn reference_slit(patterns: &[Pattern]) -> Option<usize> {
    patterns
        .iter()
        .position(|p| {
            matches!(
                p,
                Pattern::Slit {
                    axis: Axis::X,
                    offset: 0,
                    ..
                }
            )
        })
        .or_else(|| (!patterns.is_empty()).then_some(0))
}

/// The simulator's global part of a slit alone at full level: `(G_slit - b G_white) / (1 - b)`
/// (the truth's global images include the black level's light).
pub fn true_slit_global(
    truth_dir: &Path,
    k: usize,
    pattern: &Pattern,
    black_level: f32,
    size: (u32, u32),
) -> Result<Option<Vec<[f32; 3]>>, ProfilesStageError> {
    let Some(white) = true_white_global(truth_dir, k, size)? else {
        return Ok(None);
    };
    true_slit_global_with(truth_dir, k, pattern, &white, black_level, size)
}

/// The simulator's global image of projector `k`'s white frame, if the truth has it.
fn true_white_global(
    truth_dir: &Path,
    k: usize,
    size: (u32, u32),
) -> Result<Option<Vec<[f32; 3]>>, ProfilesStageError> {
    let path = truth::global(truth_dir, k, &Pattern::White);
    if !path.is_file() {
        return Ok(None);
    }
    read_rgb(&path, size).map(Some)
}

/// [`true_slit_global`] with the white truth already read (it is the same for every slit of a
/// projector).
fn true_slit_global_with(
    truth_dir: &Path,
    k: usize,
    pattern: &Pattern,
    white: &[[f32; 3]],
    black_level: f32,
    size: (u32, u32),
) -> Result<Option<Vec<[f32; 3]>>, ProfilesStageError> {
    let slit_path = truth::global(truth_dir, k, pattern);
    if !slit_path.is_file() {
        return Ok(None);
    }
    let slit = read_rgb(&slit_path, size)?;
    let b = black_level;
    Ok(Some(
        slit.iter()
            .zip(white)
            .map(|(s, w)| {
                let mut o = [0.0f32; 3];
                for c in 0..3 {
                    o[c] = (s[c] - b * w[c]) / (1.0 - b);
                }
                o
            })
            .collect(),
    ))
}

/// Accumulates `sum (a - t)^2` and `sum t^2` over the pixels of `mask`.
fn accumulate(acc: &mut (f64, f64), a: &[[f32; 3]], t: &[[f32; 3]], mask: &[bool]) {
    for ((a, t), m) in a.iter().zip(t).zip(mask) {
        if !m {
            continue;
        }
        for c in 0..3 {
            acc.0 += (f64::from(a[c]) - f64::from(t[c])).powi(2);
            acc.1 += f64::from(t[c]).powi(2);
        }
    }
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: ProfilesParams = ctx.params()?;
    super::fragment(&run_profiles(ctx, &params).map_err(StageFailure::new)?)
}

fn run_profiles(
    ctx: &StageContext,
    params: &ProfilesParams,
) -> Result<ProfilesReport, ProfilesStageError> {
    let mut clock = PhaseClock::start();
    let mut inputs = ProfileInputs::load(ctx, params)?;
    let truth_dir = ctx.truth_dir();
    let subject: Vec<usize> = (0..inputs.surface.len())
        .filter(|&i| inputs.surface.mask[i])
        .collect();
    for p in &mut inputs.projectors {
        let frames = checked_slit_frames(ctx, p.k, params, truth_dir.as_deref());
        if !frames.is_empty() {
            p.stack = stacked_slit_globals(ctx, p, frames, subject.clone())?;
        }
    }
    clock.lap("load");
    let cam = &ctx.capture.manifest.booth.camera;
    let size = (cam.width, cam.height);
    let (row, cols) = scanline(&inputs.surface);
    let mut per_projector = Vec::new();
    for p in &inputs.projectors {
        p.sweep()?; // checks the frames: slits only, camera-sized
        let (direct_fraction_median, direct_weight_mean) =
            direct_share(p, &inputs.surface.mask, params.direct_fraction_range);
        per_projector.push(ProjectorProfilesReport {
            projector: p.k,
            pixels_with_profiles: p.geometry.lit_count(),
            slit_frames: slit_frames(ctx, p.k).len(),
            blur_px: f64::from(p.blur_px),
            black_level: f64::from(p.black_level),
            direct_fraction_median,
            direct_weight_mean,
        });
    }
    let mut report = ProfilesReport {
        projectors: per_projector,
        scanline_row: row,
        eta: params.eta,
        view_ray: params.view_ray,
        direct: params.direct,
        slit_global_rel_rmse: None,
        slit_global_rel_rmse_hard_mask: None,
        slit_global_rel_rmse_direct_separation: None,
        slit_global_rel_rmse_direct_none: None,
        slit_global_rel_rmse_direct_colourless: None,
        slit_global_rel_rmse_direct_auto: None,
        timing: PhaseTimes::default(),
    };
    clock.lap("report");
    if let Some(t) = &truth_dir {
        let errors = truth_check(ctx, &inputs, t, size, params.compare_variants)?;
        let variant = |n: usize| errors.get(n + 1).copied().flatten();
        report.slit_global_rel_rmse = errors[0];
        report.slit_global_rel_rmse_hard_mask = variant(0);
        report.slit_global_rel_rmse_direct_separation = variant(1);
        report.slit_global_rel_rmse_direct_none = variant(2);
        report.slit_global_rel_rmse_direct_colourless = variant(3);
        report.slit_global_rel_rmse_direct_auto = variant(4);
    }
    clock.lap("truth");
    let record = ProfilesRecord {
        params: params.clone(),
        scanline_row: row,
        scanline_columns: cols,
        pixels_with_profiles: inputs
            .projectors
            .iter()
            .map(|p| p.geometry.lit_count())
            .collect(),
    };
    let path = ctx.dir().join(RECORD_FILE);
    let text = serde_json::to_string_pretty(&record).unwrap_or_default();
    mlsss_core::atomic_file::write_bytes_atomically(&path, text).map_err(|e| {
        ProfilesStageError::Record {
            path,
            message: e.to_string(),
        }
    })?;
    write_scanline_plot(ctx, &inputs, &record, truth_dir.as_deref(), size)?;
    clock.lap("write");
    report.timing = clock.finish();
    // The fit stage of the same run starts from these instead of decoding the slit frames again.
    ctx.hand_over(inputs);
    Ok(report)
}

/// The truth check's variants besides the configured one: hard slit edges, and each rule for
/// the direct part (report key suffixes: the fields `slit_global_rel_rmse_<suffix>` of
/// [`ProfilesReport`], in this order).
const VARIANTS: [(&str, Option<DirectPart>); 5] = [
    ("hard_mask", None),
    ("direct_separation", Some(DirectPart::Separation)),
    ("direct_none", Some(DirectPart::None)),
    ("direct_colourless", Some(DirectPart::Colourless)),
    ("direct_auto", Some(DirectPart::Auto)),
];

/// Relative RMS errors of the extracted slit globals against the truth: as configured, then
/// (with `variants`) the [`VARIANTS`]. `None` entries when the capture has no slit truth. The
/// slit frames of a projector are checked in parallel; each projector's white truth is read
/// once.
fn truth_check(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    truth_dir: &Path,
    size: (u32, u32),
    variants: bool,
) -> Result<Vec<Option<f64>>, ProfilesStageError> {
    let rules = if variants { &VARIANTS[..] } else { &[] };
    // The projectors side by side: each reads its white truth, mostly serial EXR decoding,
    // before its slits go in parallel. Their sums are added in projector order below, as one
    // after another added them.
    let per_projector = inputs
        .projectors
        .par_iter()
        .map(|p| projector_truth_sums(ctx, inputs, p, rules, truth_dir, size))
        .collect::<Result<Vec<_>, _>>()?;
    let mut acc = vec![(0.0, 0.0); rules.len() + 1];
    let mut compared = 0;
    for sums in per_projector.into_iter().flatten() {
        compared += 1;
        for (a, s) in acc.iter_mut().zip(sums) {
            a.0 += s.0;
            a.1 += s.1;
        }
    }
    Ok(acc
        .into_iter()
        .map(|a| (compared > 0 && a.1 > 0.0).then(|| (a.0 / a.1).sqrt()))
        .collect())
}

/// [`truth_check`]'s error sums of projector `p`'s slit frames that have truth, in capture
/// order ([`check_slit`]); none without its white truth.
fn projector_truth_sums(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    p: &ProjectorInputs,
    rules: &[(&str, Option<DirectPart>)],
    truth_dir: &Path,
    size: (u32, u32),
) -> Result<Vec<Vec<(f64, f64)>>, ProfilesStageError> {
    let Some(white_truth) = true_white_global(truth_dir, p.k, size)? else {
        return Ok(Vec::new());
    };
    let splits: Vec<WhiteSplit> = rules
        .iter()
        .map(|(_, rule)| match rule {
            None => ((p.direct_white().to_vec(), p.global_white().to_vec()), 0.0),
            Some(r) => (
                r.split(
                    inputs.params.direct_fraction_range,
                    &p.separation_direct,
                    &p.separation_global,
                ),
                p.blur_px,
            ),
        })
        .collect();
    // Only the slits with a truth image are made into images again (two of twenty in a
    // simulated capture).
    let patterns = p.slit_patterns();
    let per_slit = (0..patterns.len())
        .into_par_iter()
        .filter(|&j| truth::global(truth_dir, p.k, &patterns[j]).is_file())
        .filter_map(|j| p.slit_image(j))
        .map(|(pattern, global)| {
            check_slit(
                ctx,
                inputs,
                p,
                &splits,
                &pattern,
                &global,
                &white_truth,
                truth_dir,
                size,
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(per_slit.into_iter().flatten().collect())
}

/// The error sums `(sum err^2, sum truth^2)` of one slit frame of projector `p`: its extracted
/// global part, then each of `splits` (the frame is decoded again only for those); `None`
/// without truth for that slit.
#[allow(clippy::too_many_arguments)]
fn check_slit(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    p: &ProjectorInputs,
    splits: &[WhiteSplit],
    pattern: &Pattern,
    global: &[[f32; 3]],
    white_truth: &[[f32; 3]],
    truth_dir: &Path,
    size: (u32, u32),
) -> Result<Option<Vec<(f64, f64)>>, ProfilesStageError> {
    let mask = &inputs.surface.mask;
    let Some(truth) =
        true_slit_global_with(truth_dir, p.k, pattern, white_truth, p.black_level, size)?
    else {
        return Ok(None);
    };
    let mut sums = vec![(0.0, 0.0); splits.len() + 1];
    accumulate(&mut sums[0], global, &truth, mask);
    if splits.is_empty() {
        return Ok(Some(sums));
    }
    let Some(frame) = ctx.capture.manifest.plan.find(p.k as u8, pattern) else {
        return Ok(Some(sums));
    };
    let frame = ctx.capture.read_frame_pixels(frame.index)?;
    for (slot, ((direct, global_white), blur_px)) in splits.iter().enumerate() {
        let white = WhiteSeparation {
            direct,
            global: global_white,
            stray: &p.stray,
            black_level: p.black_level,
            blur_px: *blur_px,
        };
        let other = slit_global(&frame, pattern, &p.coords, &white).map_err(|source| {
            ProfilesStageError::SlitGlobal {
                projector: p.k,
                source,
            }
        })?;
        accumulate(&mut sums[slot + 1], &other, &truth, mask);
    }
    Ok(Some(sums))
}

fn write_scanline_plot(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    record: &ProfilesRecord,
    truth_dir: Option<&Path>,
    size: (u32, u32),
) -> Result<(), ProfilesStageError> {
    let Some(p) = inputs.projectors.get(record.params.scanline_projector) else {
        return Ok(());
    };
    let Some((pattern, global)) = reference_slit(&p.slit_patterns()).and_then(|j| p.slit_image(j))
    else {
        return Ok(());
    };
    let pattern = &pattern;
    let (row, (c0, c1)) = (record.scanline_row, record.scanline_columns);
    let w = inputs.surface.width;
    let along = |img: &[[f32; 3]]| -> Vec<(f64, f64)> {
        (c0..=c1)
            .filter(|&x| inputs.surface.mask[row * w + x])
            .map(|x| (x as f64, f64::from(img[row * w + x][0])))
            .collect()
    };
    let mut series = vec![Series {
        label: "measured global (R)".into(),
        colour: [200, 30, 30],
        mark: Mark::Line,
        points: along(&global),
    }];
    if let Some(t) = truth_dir
        && let Some(truth) = true_slit_global(t, p.k, pattern, p.black_level, size)?
    {
        series.push(Series {
            label: "true global (R)".into(),
            colour: [40, 40, 40],
            mark: Mark::Dashed,
            points: along(&truth),
        });
    }
    let plot = LinePlot {
        title: format!(
            "Global light of projector {}'s slit {} along row {row}",
            p.k,
            pattern.label()
        ),
        x_label: "camera column (px)".into(),
        y_label: "radiance (camera units)".into(),
        series,
    };
    plot.write(&ctx.dir().join("scanline"))?;
    Ok(())
}

#[cfg(test)]
mod tests;

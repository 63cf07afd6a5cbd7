//! Simulating whole captures: a scan of a skin subject (every frame of `FramePlan::scan`) or a
//! set of chessboard calibration poses (`FramePlan::calibration`), each written as a capture
//! folder with its `truth/`.
//!
//! Conventions
//! - Frames are lit by one projector; the others show black and still emit their black level
//!   (`stray_black`), which the truth records separately (`capture::truth::stray_light`).
//! - Noise of frame `i` comes from its own random stream (seed, i): the capture does not depend on
//!   the number of threads.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use image::Rgb32FImage;
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rayon::prelude::*;
use serde::Serialize;

use super::VirtualBoothError;
use super::camera::CameraModel;
use super::frame_render::{FrameRadiance, ProjectorTransport, Scene};
use super::material_maps::MaterialMaps;
use super::metering::meter_projector;
use super::projector::ProjectorModel;
use super::response_cache::{CacheStats, McSettings, ResponseCache};
use super::scene::{CameraRays, GeometryBuffer};
use super::skin_optics::{CHANNEL_WAVELENGTHS_NM, SkinPreset};
use super::subjects::{Chessboard, Subject, SubjectKind};
use super::subsurface_transport::{
    INNER_BAND_PIXELS, MIN_INNER_BAND_PIXELS, ResponseSet, SubsurfaceKernel,
};
use super::surface_reflection::SKIN_ROUGHNESS;
use super::truth_writer;
use mlsss_core::booth::{Booth, TimingSpec};
use mlsss_core::capture::folder::CaptureKind;
use mlsss_core::capture::{
    CaptureManifest, CaptureWriter, FramePlan, FrameSpec, Pattern, ProjectorExposure, TriggerRecord,
};
use mlsss_mc::NormalStream;

/// Receives progress (the CLI shows it as a bar).
pub trait Progress: Sync {
    /// A new stage with `total` steps.
    fn stage(&self, name: &str, total: u64);
    /// `n` more steps of the current stage are done.
    fn advance(&self, n: u64);
}

/// A [`Progress`] that ignores everything.
pub struct NoProgress;

impl Progress for NoProgress {
    fn stage(&self, _: &str, _: u64) {}
    fn advance(&self, _: u64) {}
}

/// What to simulate and how.
#[derive(Debug, Clone)]
pub struct SimulationOptions {
    pub subject: SubjectKind,
    pub skin: SkinPreset,
    pub seed: u64,
    /// Camera sub-samples per pixel along each axis.
    pub supersampling: u32,
    /// Innermost band of the subsurface transport, pixels ([`INNER_BAND_PIXELS`]: its cost and
    /// error).
    pub inner_band_px: f64,
    /// Spatial variation of the skin (freckles, vessels, stubble); off = uniform base skin.
    pub material_maps: bool,
    /// Other projectors emit their black level while one is lit.
    pub stray_black: bool,
    /// Meter the subject before a scan and expose each projector's frames to fit it
    /// (`metering`); off = every frame at the booth's nominal exposure, as before metering.
    pub metering: bool,
    /// Write the capture's `truth/` folder (on by default). The demo's calibration poses go
    /// without: nothing reads their truth there, and it was 100 MB of EXR files and about 7 % of
    /// the poses' CPU time in the quick demo.
    pub truth: bool,
    pub mc: McSettings,
    pub cache: ResponseCache,
}

impl SimulationOptions {
    /// Defaults scaled to the booth's camera resolution on the subject.
    pub fn for_booth(booth: &Booth, subject: SubjectKind, skin: SkinPreset, seed: u64) -> Self {
        let pixel_mm = nominal_pixel_mm(booth);
        // Response grid: a few cells per pixel footprint, out to 10 mm (red light in skin
        // decays by e^-5 over ~10 mm).
        let cell_mm = (pixel_mm / 3.0 * 1000.0).round() / 1000.0;
        let cells = (2.0 * 10.0 / cell_mm).round() as usize | 1;
        let small = booth.camera.width <= 640;
        Self {
            subject,
            skin,
            seed,
            supersampling: 2,
            // Small booths: 3 px. Its error against 4 px's (a third to a half of a percent of
            // the global light, RMS) is below the 10k photons' Monte Carlo noise, and on the
            // quick demo (seeds 11 and 23) every held-out figure stayed within a thousandth
            // of itself (relight 0.1003 / 0.0990 -> 0.1003 / 0.0991, separation, normals,
            // depth, decoding alike) for a quarter of the scan's CPU time. Full size: not
            // measured, kept.
            inner_band_px: if small {
                MIN_INNER_BAND_PIXELS
            } else {
                INNER_BAND_PIXELS
            },
            material_maps: true,
            stray_black: true,
            metering: true,
            truth: true,
            mc: McSettings {
                // Small booths: 10k photons per response. Measured on the quick head scan
                // against 20k (truth global images: white, slits, high frequency): the Monte
                // Carlo difference is 0.07-0.15 of one frame's camera noise RMS (99th percentile
                // 0.39), i.e. invisible to the camera, for half the Monte Carlo time (it was ~44 %
                // of the quick scan's CPU). Full size: not measured, kept.
                photons: if small { 10_000 } else { 200_000 },
                seed: 1,
                angles_deg: if small {
                    vec![0.0, 30.0, 55.0, 80.0]
                } else {
                    vec![0.0, 20.0, 40.0, 60.0, 80.0]
                },
                cell_mm,
                cells,
            },
            cache: ResponseCache::new(ResponseCache::default_dir()),
        }
    }
}

/// Camera pixel footprint at the look-at distance, mm.
fn nominal_pixel_mm(booth: &Booth) -> f64 {
    let c = &booth.camera;
    let d = (nalgebra::Vector3::from(c.look_at_mm) - nalgebra::Vector3::from(c.position_mm)).norm();
    d / c.fx
}

/// A booth scaled down by `factor` (camera and projector resolutions and focal lengths), with
/// Gray code bits reduced to fit: for fast tests.
pub fn scaled_booth(booth: &Booth, factor: u32) -> Booth {
    let f = factor as f64;
    let mut b = booth.clone();
    b.name = format!("{}-div{factor}", booth.name);
    let c = &mut b.camera;
    c.width /= factor;
    c.height /= factor;
    c.fx /= f;
    c.fy /= f;
    c.cx = (c.cx + 0.5) / f - 0.5;
    c.cy = (c.cy + 0.5) / f - 0.5;
    for p in &mut b.projectors {
        p.width /= factor;
        p.height /= factor;
        p.fx /= f;
        p.fy /= f;
        p.cx = (p.cx + 0.5) / f - 0.5;
        p.cy = (p.cy + 0.5) / f - 0.5;
    }
    let bits = |n: u32| u32::BITS - n.saturating_sub(1).leading_zeros();
    let max_w = b.projectors.iter().map(|p| p.width).max().unwrap_or(1);
    let max_h = b.projectors.iter().map(|p| p.height).max().unwrap_or(1);
    b.patterns.gray_bits_x = bits(max_w);
    b.patterns.gray_bits_y = bits(max_h);
    b
}

/// What a simulation did.
#[derive(Debug, Clone, Serialize)]
pub struct SimulationReport {
    pub captures: Vec<PathBuf>,
    pub frames: usize,
    pub seconds: f64,
    pub cache: CacheStats,
    pub camera: [u32; 2],
    /// Fraction of the camera pixels that see the subject.
    pub coverage: f64,
}

fn build_scene(booth: &Booth, subject: Subject, ss: u32) -> Scene {
    let camera = CameraModel::new(booth);
    let geometry = GeometryBuffer::trace(&camera, &subject, ss);
    scene_of(booth, camera, subject, geometry)
}

/// [`build_scene`] along the camera's precomputed rays.
fn build_scene_along(booth: &Booth, subject: Subject, rays: &CameraRays) -> Scene {
    let camera = CameraModel::new(booth);
    let geometry = GeometryBuffer::trace_rays(&camera, &subject, rays);
    scene_of(booth, camera, subject, geometry)
}

fn scene_of(
    booth: &Booth,
    camera: CameraModel,
    subject: Subject,
    geometry: GeometryBuffer,
) -> Scene {
    let projectors = (0..booth.projectors.len())
        .filter_map(|k| ProjectorModel::new(booth, k))
        .collect();
    Scene {
        camera,
        projectors,
        subject,
        geometry,
    }
}

fn make_subject(kind: SubjectKind, booth: &Booth) -> Subject {
    let field_mm = nominal_pixel_mm(booth) * booth.camera.width as f64;
    match kind {
        SubjectKind::Plane => Subject::Plane,
        SubjectKind::Sphere => Subject::Sphere {
            radius_mm: (0.3 * field_mm).round(),
        },
        SubjectKind::Head => Subject::Head(super::head::Head),
        SubjectKind::Chessboard => Subject::Chessboard(board_for_pose(booth, 0, 0)),
    }
}

/// Square size: about 13 squares across the camera's field.
fn board_for_pose(booth: &Booth, pose: usize, seed: u64) -> Chessboard {
    let field_mm = nominal_pixel_mm(booth) * booth.camera.width as f64;
    let square = (field_mm / 13.0 * 2.0).round() / 2.0;
    if pose == 0 {
        return Chessboard::posed([9, 7], square, 0.0, 0.0, 0.0, [0.0; 3]);
    }
    let mut rng = Pcg64::seed_from_u64(seed ^ (pose as u64).wrapping_mul(0x9e37_79b9));
    use rand::Rng;
    // Alternate the tilt directions so every pose set spans both axes.
    let sx = if pose.is_multiple_of(2) { 1.0 } else { -1.0 };
    let sy = if (pose / 2).is_multiple_of(2) {
        1.0
    } else {
        -1.0
    };
    Chessboard::posed(
        [9, 7],
        square,
        sx * rng.gen_range(20.0..35.0),
        sy * rng.gen_range(20.0..35.0),
        rng.gen_range(-10.0..10.0),
        [
            rng.gen_range(-0.04..0.04) * field_mm,
            rng.gen_range(-0.04..0.04) * field_mm,
            rng.gen_range(-20.0..20.0),
        ],
    )
}

fn trigger_log(booth: &Booth, plan: &FramePlan) -> Vec<TriggerRecord> {
    let slot = booth.timing.slot_us() as u64;
    plan.frames
        .iter()
        .map(|f| {
            let t = f.index as u64 * slot + booth.timing.trigger_phase_us as u64;
            let refresh = f
                .projector
                .and_then(|k| booth.projectors.get(k as usize))
                .map_or(booth.timing.refresh_hz, |p| p.refresh_hz);
            TriggerRecord {
                frame_index: f.index,
                timestamp_us: t,
                vsync_count: (t as f64 * refresh / 1e6).floor() as u32,
                retries: 0,
                late: false,
            }
        })
        .collect()
}

/// Simulates a scan of a skin subject into the capture folder `out` (must not exist).
pub fn simulate_scan(
    booth: &Booth,
    opts: &SimulationOptions,
    out: &Path,
    progress: &dyn Progress,
) -> Result<SimulationReport, VirtualBoothError> {
    simulate_scan_holding(booth, opts, out, progress, HOLD_BUDGET_BYTES)
}

/// [`simulate_scan`] holding at most `hold_budget` bytes of noise-free frames (see
/// [`render_frames`]); the capture does not depend on it.
fn simulate_scan_holding(
    booth: &Booth,
    opts: &SimulationOptions,
    out: &Path,
    progress: &dyn Progress,
    hold_budget: usize,
) -> Result<SimulationReport, VirtualBoothError> {
    let start = Instant::now();
    if opts.subject == SubjectKind::Chessboard {
        return Err(VirtualBoothError::InvalidOption {
            option: "subject",
            reason: "the chessboard is a calibration target: use --calibration".into(),
        });
    }
    let scene = trace_skin_scene(booth, opts, progress)?;

    let materials = opts.skin.materials();
    progress.stage(
        "Monte Carlo responses",
        (materials.len() * opts.mc.angles_deg.len()) as u64,
    );
    let (responses, cache_stats) = opts
        .cache
        .response_set(&materials, &opts.mc, &|_| progress.advance(1))?;
    let kernel = scan_kernel(&scene, &responses, opts.inner_band_px);

    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
    let manifest = scan_manifest(booth, opts, &plan);
    let mut writer = CaptureWriter::create(out, manifest)?;
    let truth_dir = create_truth_dir(&writer, opts)?;
    if let Some(dir) = &truth_dir {
        truth_writer::write_geometry(dir, booth, &scene)?;
        write_optics(dir, opts, &materials)?;
    }

    let rendered = render_frames(
        &scene,
        Some(&kernel),
        &plan,
        opts,
        &writer,
        truth_dir.as_deref(),
        progress,
        hold_budget,
        opts.metering.then_some(&booth.timing),
        scan_truth_pattern,
    )?;
    if opts.metering {
        writer.manifest_mut().exposure = rendered.exposure;
    }
    let contact: Vec<Rgb32FImage> = rendered.sheet;
    truth_writer::write_contact_sheet(
        &writer.staging_dir().join("contact_sheet.png"),
        &contact,
        4,
        360,
    )?;
    let path = writer.finish()?;
    Ok(SimulationReport {
        captures: vec![path],
        frames: plan.len(),
        seconds: start.elapsed().as_secs_f64(),
        cache: cache_stats,
        camera: [booth.camera.width, booth.camera.height],
        coverage: coverage(&scene),
    })
}

/// Traces the camera rays against the scan subject and paints its skin materials (freckles,
/// vessels, stubble, or uniform skin when material maps are off) over what the camera sees.
fn trace_skin_scene(
    booth: &Booth,
    opts: &SimulationOptions,
    progress: &dyn Progress,
) -> Result<Scene, VirtualBoothError> {
    progress.stage("tracing camera rays", 1);
    let mut scene = build_scene(booth, make_subject(opts.subject, booth), opts.supersampling);
    let extent = scene
        .geometry
        .extent()
        .ok_or(VirtualBoothError::EmptyView)?;
    let maps = if opts.material_maps {
        MaterialMaps::generate(opts.subject, extent, opts.seed)
    } else {
        MaterialMaps::uniform()
    };
    scene.geometry.assign_materials(&maps);
    progress.advance(1);
    Ok(scene)
}

/// The subsurface transport kernel for the scene's pixel footprints. Its finest level must
/// resolve the smallest footprint: that of the nearest surface point seen (with a 0.8 margin).
fn scan_kernel(scene: &Scene, responses: &ResponseSet, inner_band_px: f64) -> SubsurfaceKernel {
    let geo = &scene.geometry;
    let min_pixel_mm = 0.8
        * geo
            .centre
            .iter()
            .flatten()
            .map(|h| h.t)
            .fold(f64::INFINITY, f64::min)
        / scene
            .camera
            .calib
            .intrinsics
            .fx
            .max(scene.camera.calib.intrinsics.fy);
    SubsurfaceKernel::new(
        responses,
        geo.mean_pixel_size_mm(),
        min_pixel_mm,
        geo.width.max(geo.height) as usize,
        inner_band_px,
    )
}

/// The scan's manifest: the frame plan, its simulated trigger log and the simulation settings
/// as the capture's source.
fn scan_manifest(booth: &Booth, opts: &SimulationOptions, plan: &FramePlan) -> CaptureManifest {
    let mut manifest = CaptureManifest::new(CaptureKind::Scan, booth.clone(), plan.clone());
    manifest.trigger_log = trigger_log(booth, plan);
    manifest.source = serde_json::json!({
        "simulator": "mlsss virtual booth",
        "subject": opts.subject,
        "skin": opts.skin,
        "seed": opts.seed,
        "supersampling": opts.supersampling,
        "inner_band_px": opts.inner_band_px,
        "material_maps": opts.material_maps,
        "stray_black": opts.stray_black,
        "metering": opts.metering,
        "truth": opts.truth,
        "monte_carlo": opts.mc,
    });
    manifest
}

/// Creates the `truth/` folder of a capture being written, if `opts` asks for the truth.
fn create_truth_dir(
    writer: &CaptureWriter,
    opts: &SimulationOptions,
) -> Result<Option<PathBuf>, VirtualBoothError> {
    if !opts.truth {
        return Ok(None);
    }
    let truth_dir = writer.staging_dir().join("truth");
    std::fs::create_dir_all(&truth_dir).map_err(|source| VirtualBoothError::Io {
        path: truth_dir.clone(),
        source,
    })?;
    Ok(Some(truth_dir))
}

/// Scan patterns whose noise-free components go into the truth: the white, the high-frequency
/// patterns and, of the slits, the first shift of each axis (the reference of the slit profiles'
/// global part).
fn scan_truth_pattern(p: &Pattern) -> bool {
    matches!(
        p,
        Pattern::White | Pattern::HighFrequency { .. } | Pattern::Slit { offset: 0, .. }
    )
}

fn coverage(scene: &Scene) -> f64 {
    let g = &scene.geometry;
    g.centre.iter().filter(|h| h.is_some()).count() as f64 / g.pixels() as f64
}

/// Simulates `poses` calibration captures of a chessboard into `out/pose00`, `out/pose01`, ...
pub fn simulate_calibration(
    booth: &Booth,
    opts: &SimulationOptions,
    poses: usize,
    out: &Path,
    progress: &dyn Progress,
) -> Result<SimulationReport, VirtualBoothError> {
    let start = Instant::now();
    if out.exists() {
        return Err(VirtualBoothError::Capture(
            mlsss_core::capture::CaptureError::Exists(out.to_owned()),
        ));
    }
    let plan = FramePlan::calibration(&booth.patterns, booth.projectors.len());
    let mut captures = Vec::new();
    let mut sheet = Vec::new();
    let mut cov = 0.0;
    // The camera does not move between poses: its rays are computed once.
    let rays = CameraRays::new(&CameraModel::new(booth), opts.supersampling);
    for pose in 0..poses {
        progress.stage(&format!("pose {}/{poses}: tracing", pose + 1), 1);
        let board = board_for_pose(booth, pose, opts.seed);
        let scene = build_scene_along(booth, Subject::Chessboard(board.clone()), &rays);
        cov += coverage(&scene) / poses as f64;
        progress.advance(1);
        let mut manifest =
            CaptureManifest::new(CaptureKind::Calibration, booth.clone(), plan.clone());
        manifest.trigger_log = trigger_log(booth, &plan);
        manifest.source = serde_json::json!({
            "simulator": "mlsss virtual booth",
            "subject": "chessboard",
            "pose": pose,
            "seed": opts.seed,
            "board": board,
            "stray_black": opts.stray_black,
            "truth": opts.truth,
        });
        let target = out.join(format!("pose{pose:02}"));
        let writer = CaptureWriter::create(&target, manifest)?;
        let truth_dir = create_truth_dir(&writer, opts)?;
        if let Some(dir) = &truth_dir {
            truth_writer::write_geometry(dir, booth, &scene)?;
            truth_writer::write_target(dir, &scene, &board)?;
        }
        let pose_opts = SimulationOptions {
            seed: opts.seed.wrapping_add(1000 * pose as u64),
            ..opts.clone()
        };
        let rendered = render_frames(
            &scene,
            None,
            &plan,
            &pose_opts,
            &writer,
            truth_dir.as_deref(),
            progress,
            HOLD_BUDGET_BYTES,
            None,
            |p| matches!(p, Pattern::White),
        )?;
        if let Some(first) = rendered.sheet.into_iter().next() {
            sheet.push(first);
        }
        captures.push(writer.finish()?);
    }
    truth_writer::write_contact_sheet(&out.join("contact_sheet.png"), &sheet, 4, 360)?;
    Ok(SimulationReport {
        captures,
        frames: plan.len() * poses,
        seconds: start.elapsed().as_secs_f64(),
        cache: CacheStats::default(),
        camera: [booth.camera.width, booth.camera.height],
        coverage: cov,
    })
}

/// Largest budget for the buffers of one render batch (flux, direct, exitance and the frames
/// built from them: about [`BATCH_BYTES_PER_PIXEL_FRAME`] per pixel and frame). Every batch
/// gathers the subsurface pairs once (the bulk of a frame's cost), so fewer batches are faster;
/// but the batch is most of the peak: 3 GiB held the 67 frames of one projector of a full-size
/// capture (1379 x 1029) in one batch at 4.1-4.2 GB peak, above the 4 GB the booth's host is
/// given; 2 GiB renders them in two (34 and 33 frames): 3.2 GB peak for 27 % more CPU (full-size
/// type I head from an empty cache, idle machine: 2 min 38 s against 2 min 10 s wall). Never
/// more than half the memory the system reports available.
const BATCH_BUDGET_BYTES: usize = 2 << 30;
/// Smallest batch budget, whatever the system reports.
const MIN_BATCH_BUDGET_BYTES: usize = 256 << 20;
/// Peak bytes per pixel and frame of a render batch: direct 4 and exitance 12 while the frames
/// (direct 4 + global 12) are built from them (flux, 4, is dropped after the operator ran).
const BATCH_BYTES_PER_PIXEL_FRAME: usize = 32;
/// Budget for noise-free frames held until every projector's white is known (12 bytes per
/// pixel and frame). Holding frames lets each projector's white come from its own frame batch
/// instead of a separate render (one pair gathering less per projector); a quick capture holds
/// three projectors' frames in ~340 MB, a full-size one holds none and pre-renders the whites.
const HOLD_BUDGET_BYTES: usize = 1 << 30;

/// Frames rendered per batch: as few batches as keep the per-batch buffers under `budget`
/// bytes, of balanced sizes (67 frames in two batches of 34 and 33, not 60 and 7).
fn batch_size(pixels: usize, frames: usize, budget: usize) -> usize {
    let fits = (budget / (pixels * BATCH_BYTES_PER_PIXEL_FRAME).max(1)).max(1);
    let frames = frames.max(1);
    frames.div_ceil(frames.div_ceil(fits))
}

/// The batch budget on this machine: [`BATCH_BUDGET_BYTES`], or half the memory the system
/// reports available when that is less (Linux `MemAvailable`; the full budget elsewhere).
/// Speed and memory depend on it, the frames hardly: batched differently, a few hundred pixels
/// of a frame can round to the next 12-bit code (full-size type I head, seed 96, 3 GiB against
/// 2 GiB: 28 of 268 frames, up to 641 pixels each, by one code).
fn batch_budget() -> usize {
    let available = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| mem_available_bytes(&text));
    available.map_or(BATCH_BUDGET_BYTES, |bytes| {
        (bytes / 2).clamp(MIN_BATCH_BUDGET_BYTES, BATCH_BUDGET_BYTES)
    })
}

/// `MemAvailable` of a `/proc/meminfo` text, bytes.
fn mem_available_bytes(meminfo: &str) -> Option<usize> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: usize = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// How many leading projectors' frames are held (their stray light needs the whites of
/// projectors rendered after them): as many as fit in `budget` bytes, at most all but the last
/// projector.
fn held_projectors(frames_per_projector: &[usize], pixels: usize, budget: usize) -> usize {
    let frame_bytes = pixels * 12;
    let mut held = 0;
    let mut bytes = 0;
    for &frames in frames_per_projector
        .iter()
        .take(frames_per_projector.len().saturating_sub(1))
    {
        bytes += frames * frame_bytes;
        if bytes > budget {
            break;
        }
        held += 1;
    }
    held
}

/// The light the black level of every projector but `k` adds to `k`'s frames; `whites[j]` is
/// projector `j`'s noise-free white (needed for every `j != k`).
fn stray_light(
    scene: &Scene,
    whites: &[Option<Vec<[f32; 3]>>],
    k: usize,
    pixels: usize,
) -> Result<Vec<[f32; 3]>, VirtualBoothError> {
    let mut stray = vec![[0.0f32; 3]; pixels];
    for (j, white) in whites.iter().enumerate().filter(|(j, _)| *j != k) {
        let white = white.as_ref().ok_or(VirtualBoothError::Internal(
            "a projector's white is needed for stray light before it was rendered",
        ))?;
        let b = scene.projectors[j].black_level as f32;
        for (s, t) in stray.iter_mut().zip(white) {
            for c in 0..3 {
                s[c] += b * t[c];
            }
        }
    }
    Ok(stray)
}

/// Noise stream of frame 0; frame i's is this + i (the metering frames' are apart, see
/// `metering`).
const FRAME_NOISE_STREAM: u64 = 0x5eed_0000;

/// Adds stray light and camera noise to a frame's noise-free values and writes it.
struct FrameFinisher<'a> {
    scene: &'a Scene,
    seed: u64,
    writer: &'a CaptureWriter,
    progress: &'a dyn Progress,
    sheet_patterns: Vec<u32>,
    sheet: Mutex<Vec<(usize, Rgb32FImage)>>,
}

impl FrameFinisher<'_> {
    /// Finishes frame `spec` from its noise-free `totals` (its buffer becomes the frame's) at
    /// `exposure` (its projector's; nominal units when `None`).
    fn finish(
        &self,
        spec: &FrameSpec,
        mut totals: Vec<[f32; 3]>,
        stray: &[[f32; 3]],
        exposure: Option<ProjectorExposure>,
    ) -> Result<(), VirtualBoothError> {
        let geo = &self.scene.geometry;
        let (scale, gain) = exposure.map_or((1.0, 1.0), |e| (e.scale as f32, e.analog_gain));
        // The exposure scales all the light the camera collects, stray light included.
        for (t, s) in totals.iter_mut().zip(stray) {
            for c in 0..3 {
                t[c] = (t[c] + s[c]) * scale;
            }
        }
        let mut values = totals.into_flattened();
        // The frame's own noise stream: the same draws whichever thread finishes it, when.
        let mut normals = NormalStream::new(self.seed, FRAME_NOISE_STREAM + u64::from(spec.index));
        self.scene
            .camera
            .add_noise_with_gain(&mut values, gain, &mut normals);
        let img = Rgb32FImage::from_raw(geo.width, geo.height, values)
            .ok_or(VirtualBoothError::Internal("frame buffer size mismatch"))?;
        self.writer.write_frame(spec.index, &img)?;
        if let Some(pos) = self.sheet_patterns.iter().position(|&i| i == spec.index) {
            let clamped = Rgb32FImage::from_fn(img.width(), img.height(), |x, y| {
                image::Rgb(img.get_pixel(x, y).0.map(|v| v.clamp(0.0, 1.0)))
            });
            self.sheet
                .lock()
                .map_err(|_| VirtualBoothError::Internal("contact sheet lock poisoned"))?
                .push((pos, clamped));
        }
        self.progress.advance(1);
        Ok(())
    }

    fn into_sheet(self) -> Result<Vec<Rgb32FImage>, VirtualBoothError> {
        let mut tiles = self
            .sheet
            .into_inner()
            .map_err(|_| VirtualBoothError::Internal("contact sheet lock poisoned"))?;
        tiles.sort_by_key(|(pos, _)| *pos);
        Ok(tiles.into_iter().map(|(_, img)| img).collect())
    }
}

/// What [`render_frames`] hands back: a few frames for the contact sheet and each projector's
/// exposure (metered, or the manifest's).
struct RenderedFrames {
    sheet: Vec<Rgb32FImage>,
    exposure: Vec<ProjectorExposure>,
}

/// Each projector's exposure, settled before any of its frames is finished: the manifest's
/// when not metering, else metered from its noise-free white once that is known.
struct Exposures<'a> {
    scene: &'a Scene,
    metering: Option<&'a TimingSpec>,
    seed: u64,
    settled: Vec<Option<ProjectorExposure>>,
}

impl<'a> Exposures<'a> {
    fn new(
        scene: &'a Scene,
        manifest: &CaptureManifest,
        metering: Option<&'a TimingSpec>,
        seed: u64,
    ) -> Self {
        let count = scene.projectors.len();
        let settled = match metering {
            Some(_) => vec![None; count],
            None => (0..count).map(|k| Some(manifest.exposure_of(k))).collect(),
        };
        Self {
            scene,
            metering,
            seed,
            settled,
        }
    }

    /// Projector `k`'s exposure, metering it from `whites[k]` the first time.
    fn of(
        &mut self,
        k: usize,
        whites: &[Option<Vec<[f32; 3]>>],
    ) -> Result<ProjectorExposure, VirtualBoothError> {
        if let Some(e) = self.settled[k] {
            return Ok(e);
        }
        let timing = self.metering.ok_or(VirtualBoothError::Internal(
            "an exposure is neither nominal nor metered",
        ))?;
        let white = whites[k].as_deref().ok_or(VirtualBoothError::Internal(
            "a projector's white is needed for metering before it was rendered",
        ))?;
        let e = meter_projector(self.scene, k, white, timing, self.seed);
        self.settled[k] = Some(e);
        Ok(e)
    }

    fn into_settled(self) -> Result<Vec<ProjectorExposure>, VirtualBoothError> {
        self.settled
            .into_iter()
            .map(|e| e.ok_or(VirtualBoothError::Internal("a projector was never metered")))
            .collect()
    }
}

/// Renders every frame of `plan`, writes it (with noise, at each projector's exposure) and, with
/// a `truth_dir`, the truth of the patterns selected by `truth_for`; returns a few frames for the
/// contact sheet and the exposures. With `metering` (the booth's timing), each projector's
/// exposure is metered from its noise-free white (`metering`), else taken from the writer's
/// manifest.
///
/// Every frame of projector `k` carries the stray light of the other projectors' black level,
/// i.e. their whites. Projectors are rendered in order, each in batches of frames; each white is
/// taken from its projector's own batch, so the frames of the first projectors are held
/// (noise-free) until the last white is known. Whites of projectors whose frames cannot be held
/// (memory budget) are rendered alone beforehand. Each projector's white thus is rendered once,
/// for its frame, the stray light and the metering.
#[allow(clippy::too_many_arguments)]
fn render_frames(
    scene: &Scene,
    kernel: Option<&SubsurfaceKernel>,
    plan: &FramePlan,
    opts: &SimulationOptions,
    writer: &CaptureWriter,
    truth_dir: Option<&Path>,
    progress: &dyn Progress,
    hold_budget: usize,
    metering: Option<&TimingSpec>,
    truth_for: impl Fn(&Pattern) -> bool + Sync,
) -> Result<RenderedFrames, VirtualBoothError> {
    let geo = &scene.geometry;
    let dims = (geo.width, geo.height);
    let n = geo.pixels();
    let count = scene.projectors.len();
    let specs: Vec<Vec<FrameSpec>> = (0..count)
        .map(|k| plan.for_projector(k as u8).copied().collect())
        .collect();
    // Metering needs every projector's white, as stray light does.
    let needs_whites = opts.stray_black || metering.is_some();
    let held = if needs_whites {
        held_projectors(
            &specs.iter().map(Vec::len).collect::<Vec<_>>(),
            n,
            hold_budget,
        )
    } else {
        0
    };
    let mut whites: Vec<Option<Vec<[f32; 3]>>> = if needs_whites {
        whites_rendered_alone(scene, kernel, &specs, held, progress)
    } else {
        vec![None; count]
    };
    let mut exposures = Exposures::new(scene, writer.manifest(), metering, opts.seed);

    progress.stage("frames", plan.len() as u64);
    let finisher = FrameFinisher {
        scene,
        seed: opts.seed,
        writer,
        progress,
        sheet_patterns: contact_sheet_frames(plan),
        sheet: Mutex::new(Vec::new()),
    };
    let no_stray = vec![[0.0f32; 3]; n];
    let budget = batch_budget();
    let mut strays: Vec<Option<Vec<[f32; 3]>>> = vec![None; count];
    let mut held_frames: Vec<(usize, FrameSpec, Vec<[f32; 3]>)> = Vec::new();
    for (k, specs) in specs.iter().enumerate() {
        let view = ProjectorTransport::new(scene, k, kernel);
        if let Some(dir) = truth_dir {
            truth_writer::write_projector_coords(dir, &view, dims)?;
        }
        let hold = k < held;
        // A projector not held has every other white by now: its stray light is known.
        if opts.stray_black && !hold {
            strays[k] = Some(stray_light(scene, &whites, k, n)?);
        }
        for batch in specs.chunks(batch_size(n, specs.len(), budget)) {
            let totals = render_batch(scene, &view, batch, truth_dir, &truth_for)?;
            if whites[k].is_none()
                && let Some(i) = batch.iter().position(|f| f.pattern == Pattern::White)
            {
                whites[k] = Some(totals[i].clone());
            }
            if hold {
                held_frames.extend(batch.iter().zip(totals).map(|(s, t)| (k, *s, t)));
                continue;
            }
            let exposure = exposures.of(k, &whites)?;
            let stray = strays[k].as_deref().unwrap_or(&no_stray);
            batch
                .par_iter()
                .zip(totals)
                .try_for_each(|(spec, t)| finisher.finish(spec, t, stray, Some(exposure)))?;
        }
    }
    let held_exposures = (0..held)
        .map(|k| exposures.of(k, &whites))
        .collect::<Result<Vec<_>, _>>()?;
    finish_held_frames(
        &finisher,
        held_frames,
        &held_exposures,
        &whites,
        &mut strays,
        &no_stray,
        opts.stray_black,
    )?;
    for (k, stray) in strays.iter().enumerate() {
        if let Some(dir) = truth_dir {
            truth_writer::write_stray(dir, k, stray.as_deref().unwrap_or(&no_stray), dims)?;
        }
    }
    Ok(RenderedFrames {
        sheet: finisher.into_sheet()?,
        exposure: exposures.into_settled()?,
    })
}

/// Finishes the frames of the first projectors, held noise-free until every white was known
/// (`exposures[k]`: projector `k`'s): their stray light first (kept in `strays` for the truth;
/// none without `stray_black`), then the frames.
fn finish_held_frames(
    finisher: &FrameFinisher,
    held_frames: Vec<(usize, FrameSpec, Vec<[f32; 3]>)>,
    exposures: &[ProjectorExposure],
    whites: &[Option<Vec<[f32; 3]>>],
    strays: &mut [Option<Vec<[f32; 3]>>],
    no_stray: &[[f32; 3]],
    stray_black: bool,
) -> Result<(), VirtualBoothError> {
    let n = no_stray.len();
    if stray_black {
        for (k, stray) in strays.iter_mut().enumerate().take(exposures.len()) {
            *stray = Some(stray_light(finisher.scene, whites, k, n)?);
        }
    }
    held_frames.into_par_iter().try_for_each(|(k, spec, t)| {
        finisher.finish(
            &spec,
            t,
            strays[k].as_deref().unwrap_or(no_stray),
            exposures.get(k).copied(),
        )
    })
}

/// Noise-free whites of the projectors whose white cannot come from their own frame batches
/// (frames not held, or no white among them), rendered alone before the frames; `None` for the
/// others. `specs[k]` are projector `k`'s frames; the first `held` projectors' frames are held.
fn whites_rendered_alone(
    scene: &Scene,
    kernel: Option<&SubsurfaceKernel>,
    specs: &[Vec<FrameSpec>],
    held: usize,
    progress: &dyn Progress,
) -> Vec<Option<Vec<[f32; 3]>>> {
    let n = scene.geometry.pixels();
    let count = specs.len();
    let shows_white = |k: usize| specs[k].iter().any(|f| f.pattern == Pattern::White);
    let mut whites: Vec<Option<Vec<[f32; 3]>>> = vec![None; count];
    // Held projectors take their white from their frames. So does projector `held` (the first
    // not held): the projectors after it compute their stray light once its frames are done, the
    // held ones at the very end.
    let alone: Vec<usize> = (0..count)
        .filter(|&k| k > held || !shows_white(k))
        .collect();
    progress.stage("white frames", alone.len() as u64);
    for &k in &alone {
        let view = ProjectorTransport::new(scene, k, kernel);
        let white = view.render(&[scene.projectors[k].emission(&Pattern::White)]);
        whites[k] = Some(
            white
                .first()
                .map_or_else(|| vec![[0.0; 3]; n], FrameRadiance::totals),
        );
        progress.advance(1);
    }
    whites
}

/// Renders one batch of frames of `view`'s projector, writes the truth components of those
/// selected by `truth_for` (with a `truth_dir`) and returns each frame's noise-free totals (the
/// component buffers are freed here, before the frames are finished or held).
fn render_batch(
    scene: &Scene,
    view: &ProjectorTransport,
    batch: &[FrameSpec],
    truth_dir: Option<&Path>,
    truth_for: &(impl Fn(&Pattern) -> bool + Sync),
) -> Result<Vec<Vec<[f32; 3]>>, VirtualBoothError> {
    let k = view.k;
    let dims = (scene.geometry.width, scene.geometry.height);
    let patterns: Vec<Pattern> = batch.iter().map(|f| f.pattern).collect();
    let rendered = view.render_patterns(&patterns);
    batch
        .par_iter()
        .zip(rendered.par_iter())
        .map(|(spec, frame)| -> Result<_, VirtualBoothError> {
            if let Some(dir) = truth_dir.filter(|_| truth_for(&spec.pattern)) {
                truth_writer::write_components(dir, k, &spec.pattern, frame, dims)?;
            }
            Ok(frame.totals())
        })
        .collect::<Result<_, _>>()
}

/// Frames shown on the contact sheet: every projector's white, then projector 0 under a
/// middle Gray-code bit, a slit, a high-frequency pattern and a row Gray-code bit.
fn contact_sheet_frames(plan: &FramePlan) -> Vec<u32> {
    let mut out: Vec<u32> = plan
        .frames
        .iter()
        .filter(|f| f.pattern == Pattern::White)
        .map(|f| f.index)
        .collect();
    let first = |pred: &dyn Fn(&Pattern) -> bool| {
        plan.for_projector(0)
            .find(|f| pred(&f.pattern))
            .map(|f| f.index)
    };
    use mlsss_core::capture::Axis;
    let picks: [&dyn Fn(&Pattern) -> bool; 4] = [
        &|p| {
            matches!(
                p,
                Pattern::Gray {
                    axis: Axis::X,
                    bit: 4,
                    inverted: false
                }
            )
        },
        &|p| matches!(p, Pattern::Slit { axis: Axis::X, .. }),
        &|p| matches!(p, Pattern::HighFrequency { .. }),
        &|p| {
            matches!(
                p,
                Pattern::Gray {
                    axis: Axis::Y,
                    bit: 4,
                    inverted: false
                }
            )
        },
    ];
    out.extend(picks.iter().filter_map(|p| first(*p)));
    out
}

/// The optical parameters of the materials (truth `optics.json`).
fn write_optics(
    dir: &Path,
    opts: &SimulationOptions,
    materials: &[super::skin_optics::Material],
) -> Result<(), VirtualBoothError> {
    let value = serde_json::json!({
        "skin": opts.skin,
        "channel_wavelengths_nm": CHANNEL_WAVELENGTHS_NM,
        "materials": materials,
        "material_maps": "truth/materials.exr: RGB = weights of materials[1], [2], [3]; the rest is materials[0]",
        "surface": {
            "model": "GGX microfacet specular with Fresnel (rough dielectric)",
            "roughness_alpha": SKIN_ROUGHNESS,
            "index": super::skin_optics::SKIN_INDEX,
        },
        "camera_gain": super::camera::GAIN,
        "monte_carlo": opts.mc,
        "sources": [
            "Jacques 1998, Skin optics (OMLC news): melanin, baseline absorption, reduced scattering",
            "Prahl 1999, haemoglobin molar extinction (OMLC)",
            "van Gemert et al. 1989, IEEE TBME 36:1146: anisotropy g(lambda)",
            "Meglinski & Matcher 2002, Physiol. Meas. 23:741: layer thicknesses",
            "Weyrich et al. 2006: skin specular roughness",
        ],
    });
    truth_writer::write_json(&mlsss_core::capture::truth::optics(dir), &value)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::capture::Capture;

    #[test]
    fn batches_fit_the_budget_in_balanced_sizes() {
        let frame = 1000 * BATCH_BYTES_PER_PIXEL_FRAME;
        assert_eq!(batch_size(1000, 67, 100 * frame), 67);
        assert_eq!(batch_size(1000, 67, 60 * frame), 34);
        assert_eq!(batch_size(1000, 67, 22 * frame), 17);
        assert_eq!(batch_size(1000, 67, 0), 1);
        assert_eq!(batch_size(1000, 0, frame), 1);
    }

    #[test]
    fn mem_available_is_read_from_meminfo() {
        let text = "MemTotal:       24000000 kB\nMemFree:  100 kB\nMemAvailable:   12000000 kB\n";
        assert_eq!(mem_available_bytes(text), Some(12_000_000 * 1024));
        assert_eq!(mem_available_bytes("MemTotal: 5 kB\n"), None);
    }

    #[test]
    fn held_projectors_fit_the_budget_and_never_include_the_last() {
        let frames = [10, 10, 10, 10];
        assert_eq!(held_projectors(&frames, 100, 0), 0);
        assert_eq!(held_projectors(&frames, 100, 12_000), 1);
        assert_eq!(held_projectors(&frames, 100, 23_999), 1);
        assert_eq!(held_projectors(&frames, 100, 1 << 30), 3);
        assert_eq!(held_projectors(&[], 100, 1 << 30), 0);
    }

    /// Whites taken from the projectors' own frame batches (frames held until every white is
    /// known) give exactly the capture of whites rendered alone beforehand (nothing held).
    #[test]
    fn holding_frames_gives_the_same_capture_as_rendering_whites_alone() {
        let booth = scaled_booth(&Booth::builtin(true), 8);
        let cache = tempfile::tempdir().unwrap();
        let mut opts =
            SimulationOptions::for_booth(&booth, SubjectKind::Head, SkinPreset::LIGHT, 3);
        opts.mc.photons = 300;
        opts.mc.angles_deg = vec![0.0, 60.0];
        opts.cache = ResponseCache::new(cache.path());
        // Metering renders every white first, which makes holding unnecessary: off, so the
        // holding path is the one compared.
        opts.metering = false;
        let out = tempfile::tempdir().unwrap();
        let capture = |name: &str, budget: usize| {
            let dir = out.path().join(name);
            simulate_scan_holding(&booth, &opts, &dir, &NoProgress, budget).unwrap();
            Capture::open(&dir).unwrap()
        };
        let held = capture("held", 1 << 30);
        let alone = capture("alone", 0);
        let frames = held.manifest.plan.len();
        assert!(frames > 100);
        for i in 0..frames as u32 {
            let (a, b) = (held.read_frame(i).unwrap(), alone.read_frame(i).unwrap());
            assert!(a == b, "frame {i} differs");
        }
    }

    /// Without the truth a calibration pose is the same capture, frame for frame, and has no
    /// `truth/` folder (the demo's poses); the manifest's source says which it is.
    #[test]
    fn poses_without_truth_are_the_same_frames_and_no_truth_folder() {
        let booth = scaled_booth(&Booth::builtin(true), 8);
        let opts =
            SimulationOptions::for_booth(&booth, SubjectKind::Chessboard, SkinPreset::LIGHT, 5);
        let out = tempfile::tempdir().unwrap();
        let pose = |name: &str, truth: bool| {
            let opts = SimulationOptions {
                truth,
                ..opts.clone()
            };
            let report =
                simulate_calibration(&booth, &opts, 1, &out.path().join(name), &NoProgress)
                    .unwrap();
            report.captures[0].clone()
        };
        let (with, without) = (pose("with", true), pose("without", false));
        assert!(with.join("truth").join("target.json").is_file());
        assert!(!without.join("truth").exists());
        let (a, b) = (
            Capture::open(&with).unwrap(),
            Capture::open(&without).unwrap(),
        );
        assert_eq!(a.manifest.source["truth"], true);
        assert_eq!(b.manifest.source["truth"], false);
        let frames = a.manifest.plan.len();
        assert!(frames > 40);
        for i in 0..frames as u32 {
            assert!(
                a.read_frame(i).unwrap() == b.read_frame(i).unwrap(),
                "frame {i} differs"
            );
        }
    }

    /// Property, on every complement frame of a tiny head scan and two projectors: deriving it
    /// from the white and its partner (`complement_frames`) gives the direct render within float
    /// rounding (1e-5 of the white's brightest value; camera noise is ~1e-3 of it), and every
    /// frame rendered directly is bit-identical to the plain render.
    #[test]
    fn complement_frames_match_their_direct_render() {
        use super::super::complement_frames::{Recipe, recipes};
        let booth = scaled_booth(&Booth::builtin(true), 8);
        let cache = tempfile::tempdir().unwrap();
        let mut opts =
            SimulationOptions::for_booth(&booth, SubjectKind::Head, SkinPreset::LIGHT, 5);
        opts.mc.photons = 300;
        opts.mc.angles_deg = vec![0.0, 60.0];
        opts.cache = ResponseCache::new(cache.path());
        let scene = trace_skin_scene(&booth, &opts, &NoProgress).unwrap();
        let (responses, _) = opts
            .cache
            .response_set(&opts.skin.materials(), &opts.mc, &|_| {})
            .unwrap();
        let kernel = scan_kernel(&scene, &responses, opts.inner_band_px);
        let patterns = mlsss_core::capture::frame_plan::scan_patterns(&booth.patterns);
        let plan = recipes(&patterns);
        let derived_count = plan.iter().filter(|r| **r != Recipe::Render).count();
        let spec = &booth.patterns;
        assert_eq!(
            derived_count as u32,
            spec.gray_bits_x + spec.gray_bits_y + spec.hf_stripe_px
        );
        for k in [0, 2] {
            let view = ProjectorTransport::new(&scene, k, Some(&kernel));
            let emissions: Vec<_> = patterns
                .iter()
                .map(|p| scene.projectors[k].emission(p))
                .collect();
            let direct = view.render(&emissions);
            let shortcut = view.render_patterns(&patterns);
            let white_max = direct[0]
                .global
                .iter()
                .flatten()
                .flatten()
                .chain(&direct[0].direct)
                .fold(0.0f32, |m, &v| m.max(v));
            assert!(white_max > 0.01, "projector {k} lights nothing");
            for ((a, b), recipe) in direct.iter().zip(&shortcut).zip(&plan) {
                let values = |f: &FrameRadiance| -> Vec<f32> {
                    f.direct
                        .iter()
                        .chain(f.global.iter().flatten().flatten())
                        .copied()
                        .collect()
                };
                let (va, vb) = (values(a), values(b));
                let worst = va
                    .iter()
                    .zip(&vb)
                    .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
                match recipe {
                    Recipe::Render => assert_eq!(va, vb),
                    Recipe::Complement { .. } => {
                        assert!(
                            worst <= 1e-5 * white_max,
                            "projector {k}: {worst} {white_max}"
                        )
                    }
                }
            }
        }
    }

    #[test]
    fn metering_a_dark_subject_exposes_longer_and_frames_read_back_in_nominal_units() {
        let booth = scaled_booth(&Booth::builtin(true), 8);
        let cache = tempfile::tempdir().unwrap();
        let out = tempfile::tempdir().unwrap();
        let simulate = |metering: bool, name: &str| {
            let mut opts =
                SimulationOptions::for_booth(&booth, SubjectKind::Head, SkinPreset::TypeVI, 3);
            opts.mc.photons = 300;
            opts.mc.angles_deg = vec![0.0, 60.0];
            opts.cache = ResponseCache::new(cache.path());
            opts.metering = metering;
            let dir = out.path().join(name);
            simulate_scan(&booth, &opts, &dir, &NoProgress).unwrap();
            Capture::open(&dir).unwrap()
        };
        let fixed = simulate(false, "fixed");
        let metered = simulate(true, "metered");
        assert!(fixed.manifest.exposure.is_empty());
        assert_eq!(metered.manifest.exposure.len(), booth.projectors.len());
        for e in &metered.manifest.exposure {
            // Type VI returns a few percent of the light: longer exposure, within the slot.
            assert!(
                e.scale > 2.0 && e.periods > booth.timing.exposure_periods,
                "{e:?}"
            );
        }
        // Read back in nominal units, the metered white matches the fixed one (less noise).
        let white = metered.manifest.plan.frames[0].index;
        let (a, b) = (
            fixed.read_frame(white).unwrap(),
            metered.read_frame(white).unwrap(),
        );
        let mean = |img: &image::Rgb32FImage| {
            img.as_raw().iter().map(|&v| v as f64).sum::<f64>() / img.as_raw().len() as f64
        };
        let (ma, mb) = (mean(&a), mean(&b));
        assert!((ma - mb).abs() < 0.05 * ma, "{ma} {mb}");
    }
}

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
use super::material_maps::MaterialMaps;
use super::projector::ProjectorModel;
use super::render::{FrameRadiance, ProjectorView, Scene};
use super::response_cache::{CacheStats, McSettings, ResponseCache};
use super::scene::GeometryBuffer;
use super::skin_optics::{CHANNEL_WAVELENGTHS_NM, SkinPreset};
use super::subjects::{Chessboard, Subject, SubjectKind};
use super::subsurface::SubsurfaceKernel;
use super::surface_reflection::SKIN_ROUGHNESS;
use super::truth_writer;
use crate::booth::Booth;
use crate::capture::folder::CaptureKind;
use crate::capture::{CaptureManifest, CaptureWriter, FramePlan, Pattern, TriggerRecord};

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
    /// Spatial variation of the skin (freckles, vessels, stubble); off = uniform base skin.
    pub material_maps: bool,
    /// Other projectors emit their black level while one is lit.
    pub stray_black: bool,
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
            material_maps: true,
            stray_black: true,
            mc: McSettings {
                photons: if small { 20_000 } else { 200_000 },
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
    let projectors = (0..booth.projectors.len())
        .filter_map(|k| ProjectorModel::new(booth, k))
        .collect();
    let geometry = GeometryBuffer::trace(&camera, &subject, ss);
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
    let start = Instant::now();
    if opts.subject == SubjectKind::Chessboard {
        return Err(VirtualBoothError::InvalidOption {
            option: "subject",
            reason: "the chessboard is a calibration target: use --calibration".into(),
        });
    }
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

    let materials = opts.skin.materials();
    progress.stage(
        "Monte Carlo responses",
        (materials.len() * opts.mc.angles_deg.len()) as u64,
    );
    let (responses, cache_stats) = opts
        .cache
        .response_set(&materials, &opts.mc, &|_| progress.advance(1))?;
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
    let kernel = SubsurfaceKernel::new(
        &responses,
        geo.mean_pixel_size_mm(),
        min_pixel_mm,
        geo.width.max(geo.height) as usize,
    );

    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
    let mut manifest = CaptureManifest::new(CaptureKind::Scan, booth.clone(), plan.clone());
    manifest.trigger_log = trigger_log(booth, &plan);
    manifest.source = serde_json::json!({
        "simulator": "mlsss virtual booth",
        "subject": opts.subject,
        "skin": opts.skin,
        "seed": opts.seed,
        "supersampling": opts.supersampling,
        "material_maps": opts.material_maps,
        "stray_black": opts.stray_black,
        "monte_carlo": opts.mc,
    });
    let writer = CaptureWriter::create(out, manifest)?;
    let truth_dir = writer.staging_dir().join("truth");
    std::fs::create_dir_all(&truth_dir).map_err(|source| VirtualBoothError::Io {
        path: truth_dir.clone(),
        source,
    })?;
    truth_writer::write_geometry(&truth_dir, booth, &scene)?;
    write_optics(&truth_dir, opts, &materials)?;

    let frames = render_frames(
        &scene,
        Some(&kernel),
        &plan,
        opts,
        &writer,
        &truth_dir,
        progress,
        // Slits: the first shift of each axis, the reference of the slit profiles' global part.
        |p| {
            matches!(
                p,
                Pattern::White | Pattern::HighFrequency { .. } | Pattern::Slit { offset: 0, .. }
            )
        },
    )?;
    let contact: Vec<Rgb32FImage> = frames;
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
            crate::capture::CaptureError::Exists(out.to_owned()),
        ));
    }
    let plan = FramePlan::calibration(&booth.patterns, booth.projectors.len());
    let mut captures = Vec::new();
    let mut sheet = Vec::new();
    let mut cov = 0.0;
    for pose in 0..poses {
        progress.stage(&format!("pose {}/{poses}: tracing", pose + 1), 1);
        let board = board_for_pose(booth, pose, opts.seed);
        let scene = build_scene(
            booth,
            Subject::Chessboard(board.clone()),
            opts.supersampling,
        );
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
        });
        let target = out.join(format!("pose{pose:02}"));
        let writer = CaptureWriter::create(&target, manifest)?;
        let truth_dir = writer.staging_dir().join("truth");
        std::fs::create_dir_all(&truth_dir).map_err(|source| VirtualBoothError::Io {
            path: truth_dir.clone(),
            source,
        })?;
        truth_writer::write_geometry(&truth_dir, booth, &scene)?;
        truth_writer::write_target(&truth_dir, &scene, &board)?;
        let pose_opts = SimulationOptions {
            seed: opts.seed.wrapping_add(1000 * pose as u64),
            ..opts.clone()
        };
        let frames = render_frames(
            &scene,
            None,
            &plan,
            &pose_opts,
            &writer,
            &truth_dir,
            progress,
            |p| matches!(p, Pattern::White),
        )?;
        if let Some(first) = frames.into_iter().next() {
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

/// Frames rendered per batch: bounded so the per-batch buffers stay under ~256 MB.
fn batch_size(pixels: usize, frames: usize) -> usize {
    (256_000_000 / (pixels * 20).max(1)).clamp(1, frames.max(1))
}

/// Renders every frame of `plan`, writes it (with noise) and the truth of the patterns selected
/// by `truth_for`; returns a few frames for the contact sheet.
#[allow(clippy::too_many_arguments)]
fn render_frames(
    scene: &Scene,
    kernel: Option<&SubsurfaceKernel>,
    plan: &FramePlan,
    opts: &SimulationOptions,
    writer: &CaptureWriter,
    truth_dir: &Path,
    progress: &dyn Progress,
    truth_for: impl Fn(&Pattern) -> bool + Sync,
) -> Result<Vec<Rgb32FImage>, VirtualBoothError> {
    let geo = &scene.geometry;
    let dims = (geo.width, geo.height);
    let n = geo.pixels();
    let count = scene.projectors.len();
    // Pass 1: white under every projector (truth, and the stray light of the black projectors).
    progress.stage("white frames", count as u64);
    let mut whites = Vec::with_capacity(count);
    for k in 0..count {
        let view = ProjectorView::new(scene, k, kernel);
        truth_writer::write_projector_coords(truth_dir, &view, dims)?;
        let white = view.render(&[scene.projectors[k].emission(&Pattern::White)]);
        whites.push(
            white
                .into_iter()
                .next()
                .unwrap_or_else(|| FrameRadiance::zeros(n)),
        );
        progress.advance(1);
    }
    let stray: Vec<Vec<[f32; 3]>> = (0..count)
        .map(|k| {
            (0..n)
                .map(|i| {
                    let mut s = [0.0f32; 3];
                    if opts.stray_black {
                        for (j, white) in whites.iter().enumerate().filter(|(j, _)| *j != k) {
                            let b = scene.projectors[j].black_level as f32;
                            let t = white.total(i);
                            for c in 0..3 {
                                s[c] += b * t[c];
                            }
                        }
                    }
                    s
                })
                .collect()
        })
        .collect();
    for (k, s) in stray.iter().enumerate() {
        truth_writer::write_stray(truth_dir, k, s, dims)?;
    }
    drop(whites);

    // Pass 2: every frame.
    progress.stage("frames", plan.len() as u64);
    let sheet = Mutex::new(Vec::new());
    let sheet_patterns = contact_sheet_frames(plan);
    for (k, stray) in stray.iter().enumerate() {
        let view = ProjectorView::new(scene, k, kernel);
        let specs: Vec<_> = plan.for_projector(k as u8).copied().collect();
        for batch in specs.chunks(batch_size(n, specs.len())) {
            let emissions: Vec<_> = batch
                .iter()
                .map(|f| scene.projectors[k].emission(&f.pattern))
                .collect();
            let rendered = view.render(&emissions);
            batch.par_iter().zip(rendered.par_iter()).try_for_each(
                |(spec, frame)| -> Result<(), VirtualBoothError> {
                    if truth_for(&spec.pattern) {
                        truth_writer::write_components(truth_dir, k, &spec.pattern, frame, dims)?;
                    }
                    let mut values: Vec<f32> = (0..n)
                        .flat_map(|i| {
                            let t = frame.total(i);
                            let s = stray[i];
                            [t[0] + s[0], t[1] + s[1], t[2] + s[2]]
                        })
                        .collect();
                    let mut rng =
                        Pcg64::seed_from_u64(opts.seed ^ (0x5eed_0000 + spec.index as u64) << 8);
                    scene.camera.add_noise(&mut values, &mut rng);
                    let img = Rgb32FImage::from_raw(geo.width, geo.height, values)
                        .ok_or(VirtualBoothError::Internal("frame buffer size mismatch"))?;
                    writer.write_frame(spec.index, &img)?;
                    if let Some(pos) = sheet_patterns.iter().position(|&i| i == spec.index) {
                        let clamped = Rgb32FImage::from_fn(img.width(), img.height(), |x, y| {
                            image::Rgb(img.get_pixel(x, y).0.map(|v| v.clamp(0.0, 1.0)))
                        });
                        sheet
                            .lock()
                            .map_err(|_| {
                                VirtualBoothError::Internal("contact sheet lock poisoned")
                            })?
                            .push((pos, clamped));
                    }
                    progress.advance(1);
                    Ok(())
                },
            )?;
        }
    }
    let mut tiles = sheet
        .into_inner()
        .map_err(|_| VirtualBoothError::Internal("contact sheet lock poisoned"))?;
    tiles.sort_by_key(|(pos, _)| *pos);
    Ok(tiles.into_iter().map(|(_, img)| img).collect())
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
    use crate::capture::Axis;
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
    truth_writer::write_json(&crate::capture::truth::optics(dir), &value)
}

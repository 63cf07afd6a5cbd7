//! `mlsss simulate`: the virtual booth's captures and their ground truth.

use std::path::Path;

use mlsss::calibration::Calibration;
use mlsss::capture::{Capture, Pattern, truth};
use mlsss::imageio::{read_exr_gray, read_exr_rgb};
use mlsss::mc::{self, McConfig};
use mlsss::virtual_booth::camera::GAIN;
use mlsss::virtual_booth::response_cache::material_medium;
use mlsss::virtual_booth::skin_optics::{BASE, SKIN_INDEX, SkinPreset};
use mlsss::virtual_booth::surface_reflection::DiffuseExit;
use mlsss_tests::{CALIBRATION_POSES, TestDir, calibration_captures, quick_capture, simulate};
use nalgebra::Point3;

#[test]
fn scan_is_a_readable_capture_with_every_frame_and_truth_file() {
    let root = quick_capture("head", 1);
    let cap = Capture::open(&root).unwrap();
    let plan = &cap.manifest.plan;
    // 4 projectors x (white + 2 x (7 + 7) Gray-code bits + 20 slits + 6 high-frequency).
    assert_eq!(plan.len(), 4 * 55);
    let truth_dir = cap.truth_dir().expect("simulated capture has truth/");
    let frame = cap.read_frame(0).unwrap();
    assert_eq!(frame.width(), cap.manifest.booth.camera.width);
    for path in [
        truth::calibration(&truth_dir),
        truth::mask(&truth_dir),
        truth::depth(&truth_dir),
        truth::points(&truth_dir),
        truth::normals(&truth_dir),
        truth::material_maps(&truth_dir),
        truth::optics(&truth_dir),
    ] {
        assert!(path.exists(), "{} missing", path.display());
    }
    for k in 0..4 {
        assert!(truth::projector_coords(&truth_dir, k).exists());
        for shift in 0..6 {
            let hf = Pattern::HighFrequency { stripe: 3, shift };
            assert!(truth::direct(&truth_dir, k, &hf).exists());
            assert!(truth::global(&truth_dir, k, &hf).exists());
        }
        assert!(truth::global(&truth_dir, k, &Pattern::White).exists());
    }
    assert!(root.join("contact_sheet.png").exists());
}

#[test]
fn projector_coordinates_and_depth_agree_with_the_points_and_calibration() {
    let root = quick_capture("head", 1);
    let truth_dir = root.join("truth");
    let calib = Calibration::load(&truth::calibration(&truth_dir)).unwrap();
    let points = read_exr_rgb(&truth::points(&truth_dir)).unwrap();
    let depth = read_exr_gray(&truth::depth(&truth_dir)).unwrap();
    let mut lit = 0;
    for k in 0..4 {
        let coords = read_exr_rgb(&truth::projector_coords(&truth_dir, k)).unwrap();
        for (x, y, c) in coords.enumerate_pixels() {
            let [u, v, is_lit] = c.0;
            if is_lit == 0.0 {
                continue;
            }
            lit += 1;
            let p = points.get_pixel(x, y).0;
            let world = Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            let q = calib.projectors[k].device.project(&world).unwrap();
            assert!(
                (q.x - u as f64).abs() < 0.01 && (q.y - v as f64).abs() < 0.01,
                "projector {k} pixel ({x}, {y}): truth ({u}, {v}) vs reprojected {q}"
            );
        }
    }
    assert!(lit > 10_000, "too few lit pixels: {lit}");
    for (x, y, p) in points.enumerate_pixels() {
        let world = Point3::new(p.0[0] as f64, p.0[1] as f64, p.0[2] as f64);
        let z = calib.camera.extrinsics.world_to_device(&world).z;
        let d = depth.get(x, y) as f64;
        if d > 0.0 {
            assert!(
                (z - d).abs() < 1e-3 * d,
                "({x}, {y}): depth {d} vs point z {z}"
            );
            // The camera sees the point at this pixel.
            let px = calib.camera.project(&world).unwrap();
            assert!((px.x - x as f64).abs() < 0.02 && (px.y - y as f64).abs() < 0.02);
        }
    }
}

#[test]
fn sphere_normals_are_radial() {
    let root = quick_capture("sphere", 3);
    let truth_dir = root.join("truth");
    let points = read_exr_rgb(&truth::points(&truth_dir)).unwrap();
    let normals = read_exr_rgb(&truth::normals(&truth_dir)).unwrap();
    // The sphere touches z = 0 at the origin, so its centre is (0, 0, R); R follows from any point.
    let mut checked = 0;
    for (p, n) in points.pixels().zip(normals.pixels()) {
        let [x, y, z] = p.0.map(|v| v as f64);
        if z == 0.0 && x == 0.0 && y == 0.0 {
            continue;
        }
        let r = (x * x + y * y + z * z) / (2.0 * z);
        let radial = [x / r, y / r, (z - r) / r];
        for c in 0..3 {
            assert!(
                (n.0[c] as f64 - radial[c]).abs() < 1e-4,
                "{:?} vs {radial:?}",
                n.0
            );
        }
        checked += 1;
    }
    assert!(checked > 1000);
}

/// Global light under uniform white on a flat, uniform skin plane equals what Monte Carlo
/// predicts for an infinite plane: exitance = irradiance x diffuse reflectance, leaving with the
/// Fresnel-transmitted angular distribution.
#[test]
fn global_light_on_a_plane_matches_the_monte_carlo_albedo() {
    let out_dir = TestDir::new("plane-uniform");
    let out = out_dir.path();
    let sim_photons: f64 = 16_000.0;
    simulate(
        out,
        4,
        &[
            "--subject",
            "plane",
            "--no-maps",
            "--seed",
            "2",
            "--photons",
            "16000",
        ],
    );
    let cap = Capture::open(out).unwrap();
    let booth = &cap.manifest.booth;
    let global = read_exr_rgb(&truth::global(&out.join("truth"), 0, &Pattern::White)).unwrap();
    // The camera looks at the origin along +z; there the plane's irradiance is cos(theta_i).
    let calib = booth.calibration();
    let centre = calib.camera.project(&Point3::origin()).unwrap();
    let (cx, cy) = (centre.x.round() as u32, centre.y.round() as u32);
    let p = nalgebra::Vector3::from(booth.projectors[0].position_mm);
    let cos_i = p.z.abs() / p.norm();
    let angle = cos_i.acos().to_degrees();
    let exit = DiffuseExit::new(SKIN_INDEX);
    let base = &SkinPreset::LIGHT.materials()[BASE];
    for c in 0..3 {
        let result = mc::run(
            &material_medium(base, c),
            &McConfig {
                incidence_deg: angle,
                ..McConfig::new(40_000, 9)
            },
        )
        .unwrap();
        let rd = result.diffuse_reflectance;
        let expected = GAIN * exit.factor(1.0) * cos_i * rd;
        let got = global.get_pixel(cx, cy).0[c] as f64;
        // Noise of both Monte Carlo estimates (the simulator's responses used fewer photons),
        // plus 3 % for the angle interpolation and the 10 mm response grid.
        let se = result.diffuse_reflectance_se / rd * (1.0 + (40_000.0 / sim_photons).sqrt());
        assert!(
            (got / expected - 1.0).abs() < 0.03 + 3.0 * se,
            "channel {c}: simulated global {got}, Monte Carlo albedo predicts {expected} (se {se})"
        );
    }
}

#[test]
fn same_seed_gives_the_same_frames_and_the_second_run_uses_the_cache() {
    let a_dir = TestDir::new("determinism-a");
    let a = a_dir.path();
    let b_dir = TestDir::new("determinism-b");
    let b = b_dir.path();
    simulate(a, 4, &["--subject", "sphere", "--seed", "5"]);
    let report = simulate(b, 4, &["--subject", "sphere", "--seed", "5"]);
    assert_eq!(report["cache"]["misses"], 0, "{report}");
    assert_eq!(report["cache"]["photons_traced"], 0, "{report}");
    for index in [0u32, 7, 40, 100] {
        let name = mlsss::capture::folder::frame_file(index);
        let fa = std::fs::read(a.join(&name)).unwrap();
        let fb = std::fs::read(b.join(&name)).unwrap();
        assert!(
            fa == fb,
            "frame {index} differs between two runs with the same seed"
        );
    }
    let c_dir = TestDir::new("determinism-c");
    let c = c_dir.path();
    simulate(c, 4, &["--subject", "sphere", "--seed", "6"]);
    let name = mlsss::capture::folder::frame_file(0);
    assert_ne!(
        std::fs::read(a.join(&name)).unwrap(),
        std::fs::read(c.join(&name)).unwrap(),
        "another seed must change the noise"
    );
}

#[test]
fn calibration_poses_are_captures_with_the_board_in_view() {
    let root = calibration_captures(CALIBRATION_POSES);
    for pose in 0..CALIBRATION_POSES {
        let dir = root.join(format!("pose{pose:02}"));
        let cap = Capture::open(&dir).unwrap();
        assert_eq!(
            cap.manifest.kind,
            mlsss::capture::folder::CaptureKind::Calibration
        );
        let cam = &cap.manifest.booth.camera;
        let target: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(truth::target(&dir.join("truth"))).unwrap(),
        )
        .unwrap();
        let corners = target["corners_camera_px"].as_array().unwrap();
        assert_eq!(corners.len(), 63);
        for c in corners {
            let (x, y) = (c[0].as_f64().unwrap(), c[1].as_f64().unwrap());
            assert!(x > 0.0 && y > 0.0 && x < cam.width as f64 && y < cam.height as f64);
        }
        // White squares are brighter than black ones in the white frame of projector 0.
        let white = cap.read_frame(0).unwrap();
        let black = cap.read_frame(1).unwrap();
        let mean = |img: &image::Rgb32FImage| {
            img.pixels().map(|p| p.0[1] as f64).sum::<f64>() / img.pixels().len() as f64
        };
        assert!(mean(&white) > 3.0 * mean(&black));
    }
    assert!(Path::new(&root.join("contact_sheet.png")).exists());
}

/// `--no-truth` writes the capture as a real booth gives it: the same frames, no `truth/`; the
/// manifest's source records the choice.
#[test]
fn no_truth_gives_the_same_frames_without_the_truth_folder() {
    let dir = TestDir::new("simulate-no-truth");
    let args = [
        "--subject",
        "chessboard",
        "--calibration",
        "--poses",
        "1",
        "--seed",
        "7",
    ];
    simulate(&dir.path().join("with"), 4, &args);
    let without_args: Vec<&str> = args.iter().copied().chain(["--no-truth"]).collect();
    simulate(&dir.path().join("without"), 4, &without_args);
    let (with, without) = (
        Capture::open(&dir.path().join("with/pose00")).unwrap(),
        Capture::open(&dir.path().join("without/pose00")).unwrap(),
    );
    assert!(with.truth_dir().is_some());
    assert!(without.truth_dir().is_none());
    assert_eq!(with.manifest.source["truth"], true);
    assert_eq!(without.manifest.source["truth"], false);
    assert!(!dir.path().join("without/pose00/truth").exists());
    let frames = with.manifest.plan.len() as u32;
    assert!(frames > 40);
    for i in 0..frames {
        assert!(
            with.read_frame(i).unwrap() == without.read_frame(i).unwrap(),
            "frame {i}"
        );
    }
}

/// `--inner-band-px` sets the subsurface kernel's innermost band, which the capture records
/// beside the other simulation settings; the quick booth's default is 3 px. Wider bands sum more
/// of the light pixel by pixel: the global light of a uniformly lit plane (a response's total,
/// whatever the bands) stays the same within the kernel's error.
#[test]
fn the_inner_band_width_is_a_recorded_setting() {
    let narrow_dir = TestDir::new("inner-band-default");
    let wide_dir = TestDir::new("inner-band-4");
    let (narrow, wide) = (narrow_dir.path(), wide_dir.path());
    simulate(narrow, 8, &["--subject", "plane", "--no-maps"]);
    simulate(
        wide,
        8,
        &["--subject", "plane", "--no-maps", "--inner-band-px", "4"],
    );
    // The recorded band and the true global light at the centre pixel (far from the plane's
    // edges) of the white.
    let read = |root: &Path| {
        let cap = Capture::open(root).unwrap();
        assert_eq!(
            cap.manifest.source["truth"], true,
            "a scan's truth is recorded"
        );
        let img = read_exr_rgb(&truth::global(
            &cap.truth_dir().unwrap(),
            0,
            &Pattern::White,
        ))
        .unwrap();
        (
            cap.manifest.source["inner_band_px"].clone(),
            img.get_pixel(img.width() / 2, img.height() / 2).0,
        )
    };
    let ((narrow_band, a), (wide_band, b)) = (read(narrow), read(wide));
    assert_eq!(narrow_band, 3.0, "the quick booth's default");
    assert_eq!(wide_band, 4.0);
    for c in 0..3 {
        assert!(
            (a[c] / b[c] - 1.0).abs() < 0.01,
            "channel {c}: 3 px {} against 4 px {}",
            a[c],
            b[c]
        );
    }
}

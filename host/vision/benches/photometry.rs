//! Benchmarks of direct/global separation and 4-light photometric stereo on full-size camera
//! frames (1379x1029 RGB), and, in the same run, the numpy implementation of the same formulas in
//! `photometry_numpy.py` (skipped with a note when python3/numpy are missing).
//!
//! Run: `cargo bench -p mlsss-vision --bench photometry` (`separation_kernel_aware` races the
//! kernel-aware separation, slit-sweep leak included, against the Nayar variants;
//! `normal_fusion` is what the normals stage adds to the robust solve by default).

use std::process::Command;

use criterion::{Criterion, criterion_group};
use image::Rgb32FImage;
use mlsss_vision::geometry::point_normals::{PointNormalParams, fit_point_normals};
use mlsss_vision::photometry::dichromatic::dichromatic_direct;
use mlsss_vision::photometry::kernel_leak::{
    LeakParams, colourless_smoothed_direct, separate_with_leak,
};
use mlsss_vision::photometry::normal_fusion::{
    FusionParams, fuse_normals, photometric_noise_proxy,
};
use mlsss_vision::photometry::photometric_stereo::{
    DirectionalLights, LightSample, Method, PsParams, solve_images,
};
use mlsss_vision::photometry::separation::{SeparationParams, separate};
use mlsss_vision::photometry::slit_leak::{LeakReading, SweepGeometry, leak_from_slits};
use nalgebra::{Point3, Vector3};

const WIDTH: u32 = 1379;
const HEIGHT: u32 = 1029;

/// Six stripe frames of a smoothly varying scene (deterministic, no RNG needed).
fn stripe_frames() -> Vec<Rgb32FImage> {
    (0..6u32)
        .map(|s| {
            Rgb32FImage::from_fn(WIDTH, HEIGHT, |x, y| {
                let lit = (x + 6 - s) % 6 < 3;
                let direct = 0.3 + 0.1 * ((x as f32) * 0.01).sin();
                let global = 0.2 + 0.05 * ((y as f32) * 0.013).cos();
                let b = 0.02;
                let e = if lit { 1.0 } else { b };
                let v = direct * e + global * (1.0 + b) / 2.0;
                image::Rgb([v, 0.8 * v, 0.6 * v])
            })
        })
        .collect()
}

/// Ten 3-px slit frames every 30 px (the full-size sweep along x) of the same kind of scene: a
/// Gaussian kernel of sigma 2 px around the lit columns, sampled at the pixel's column.
fn slit_frames() -> Vec<Vec<[f32; 3]>> {
    (0..10u32)
        .map(|j| {
            (0..WIDTH * HEIGHT)
                .map(|i| {
                    let x = (i % WIDTH) as f32;
                    let d = (x - 3.0 * j as f32 - 1.0).rem_euclid(30.0);
                    let d = d.min(30.0 - d);
                    let v = 0.02 + 0.3 * (-d * d / 8.0).exp();
                    [v, 0.8 * v, 0.6 * v]
                })
                .collect()
        })
        .collect()
}

fn booth_lights() -> Vec<LightSample> {
    [(-1.0, 1.0), (1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)]
        .iter()
        .map(|&(x, y)| LightSample {
            direction: Vector3::new(0.45 * x, 0.45 * y, 0.77).normalize(),
            irradiance: [1.0; 3],
        })
        .collect()
}

/// Four images of a hemisphere-like normal field under the booth lights.
fn ps_frames(lights: &[LightSample]) -> Vec<Rgb32FImage> {
    lights
        .iter()
        .map(|l| {
            Rgb32FImage::from_fn(WIDTH, HEIGHT, |x, y| {
                let nx = (x as f64 / WIDTH as f64 - 0.5) * 1.2;
                let ny = (y as f64 / HEIGHT as f64 - 0.5) * 1.2;
                let n = Vector3::new(nx, ny, 1.0).normalize();
                let v = (0.6 * n.dot(&l.direction).max(0.0)) as f32;
                image::Rgb([v, 0.7 * v, 0.5 * v])
            })
        })
        .collect()
}

/// A full-size point map of a gently curved surface 500 mm in front of a camera at the origin.
fn surface_points() -> Vec<[f32; 3]> {
    let f = 2000.0;
    (0..HEIGHT)
        .flat_map(|y| (0..WIDTH).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (u, v) = (
                (f64::from(x) - f64::from(WIDTH) / 2.0) / f,
                (f64::from(y) - f64::from(HEIGHT) / 2.0) / f,
            );
            let depth = 500.0 + 40.0 * (u * u + v * v);
            [(u * depth) as f32, (v * depth) as f32, depth as f32]
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let frames = stripe_frames();
    let refs: Vec<&Rgb32FImage> = frames.iter().collect();
    let mut group = c.benchmark_group("photometry_full_frame");
    group.sample_size(10);
    let nayar = SeparationParams {
        black_level: 0.02,
        ..Default::default()
    };
    group.bench_function("separation_nayar", |b| {
        b.iter(|| separate(&refs, &nayar).map(|s| s.stats))
    });
    let blur = SeparationParams {
        blur_px: 0.6,
        ..nayar
    };
    group.bench_function("separation_blur_corrected", |b| {
        b.iter(|| separate(&refs, &blur).map(|s| s.stats))
    });
    // The kernel-aware separation races the baseline: leak from the slit sweep, split, and the
    // colourless smoothed direct part, as the separate stage runs it (frame reading excluded).
    let slits = slit_frames();
    let slit_refs: Vec<&[[f32; 3]]> = slits.iter().map(|s| s.as_slice()).collect();
    let white: Vec<[f32; 3]> = frames[0].pixels().map(|p| p.0.map(|v| 2.0 * v)).collect();
    let geometry = SweepGeometry {
        slit_width_px: 3,
        stripe_px: 3,
        black_level: 0.02,
        blur_px: 0.6,
    };
    let leak_params = LeakParams {
        black_level: 0.02,
        blur_px: 0.6,
        ..Default::default()
    };
    group.bench_function("separation_kernel_aware", |b| {
        b.iter(|| {
            let (leak, _) = leak_from_slits(&slit_refs, &white, &geometry, LeakReading::Cosine);
            separate_with_leak(&refs, &leak, &leak_params).map(|mut s| {
                colourless_smoothed_direct(&mut s, 1.0);
                s.stats
            })
        })
    });
    // The separate stage's default since version 5: harmonics reading, dichromatic direct part.
    group.bench_function("separation_kernel_dichromatic", |b| {
        b.iter(|| {
            let (leak, _) = leak_from_slits(&slit_refs, &white, &geometry, LeakReading::Harmonics);
            separate_with_leak(&refs, &leak, &leak_params).map(|mut s| {
                dichromatic_direct(&mut s, 1.0);
                s.stats
            })
        })
    });
    let lights = booth_lights();
    let images = ps_frames(&lights);
    let refs: Vec<&Rgb32FImage> = images.iter().collect();
    let model = DirectionalLights {
        lights,
        view: Vector3::z(),
    };
    for (name, method) in [
        ("ps4_least_squares", Method::LeastSquares),
        ("ps4_robust", Method::Robust),
    ] {
        let params = PsParams {
            method,
            ..PsParams::default()
        };
        group.bench_function(name, |b| {
            b.iter(|| solve_images(&refs, &model, None, &params).map(|m| m.pixels.len()))
        });
    }
    let Ok(map) = solve_images(&refs, &model, None, &PsParams::default()) else {
        panic!("the benchmark's frames are solvable");
    };
    let points = surface_points();
    group.bench_function("normal_fusion", |b| {
        b.iter(|| {
            let geometry = fit_point_normals(
                &points,
                WIDTH,
                HEIGHT,
                Point3::origin(),
                &PointNormalParams::default(),
            );
            let photometric: Vec<[f32; 3]> = map.pixels.iter().map(|p| p.normal).collect();
            let noise = photometric_noise_proxy(&map, &model);
            fuse_normals(&photometric, &noise, &geometry, &FusionParams::default())
                .map(|f| f.summary.fused)
        })
    });
    group.finish();
}

criterion_group!(benches, bench);

fn numpy_peer() {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/photometry_numpy.py");
    match Command::new("python3").arg(script).output() {
        Ok(out) if out.status.success() => {
            println!("numpy peer (same formulas, same frame size):");
            print!("{}", String::from_utf8_lossy(&out.stdout));
        }
        Ok(out) => println!(
            "numpy peer skipped: {}",
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ),
        Err(e) => println!("numpy peer skipped: python3 not runnable ({e})"),
    }
}

fn main() {
    benches();
    numpy_peer();
    Criterion::default().configure_from_args().final_summary();
}

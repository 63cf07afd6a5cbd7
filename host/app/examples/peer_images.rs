//! Our separation and photometric stereo on synthetic full-size inputs (the booth camera's
//! 1379x1029), for `scripts/peers.py`, which runs the numpy peers on the same arrays in the same
//! run. Writes the inputs, the truth and our outputs as `.npy` into DIR and prints our timings
//! (best and median wall seconds, mean CPU seconds of all threads, over the repeats) and outcome counts as JSON.
//!
//! `peer_images separation DIR [REPEATS]`: Nayar's max/min separation (6 shifted 3-px stripe
//! frames, no blur correction) of a known direct and global image with noise.
//! `peer_images ps DIR [REPEATS]`: 4-light least-squares photometric stereo of `ps_scene` spheres
//! (Lambertian, noise 0.002).

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail};
use image::Rgb32FImage;
use mlsss::photometry::photometric_stereo::{
    self as ps, DirectionalLights, LightSample, Method, PsParams,
};
use mlsss::photometry::ps_scene::{self, SceneParams};
use mlsss::photometry::separation::{SeparationParams, separate};
use mlsss::resources::cpu_seconds;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

const WIDTH: u32 = 1379;
const HEIGHT: u32 = 1029;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(kind), Some(dir)) = (args.get(1), args.get(2)) else {
        bail!("usage: peer_images separation|ps DIR [REPEATS]");
    };
    let repeats: usize = args.get(3).map_or(Ok(5), |r| r.parse())?;
    let dir = Path::new(dir);
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let report = match kind.as_str() {
        "separation" => separation(dir, repeats)?,
        "ps" => photometric_stereo(dir, repeats)?,
        other => bail!("unknown kernel `{other}` (separation or ps)"),
    };
    println!("{report}");
    Ok(())
}

/// Best and median wall times and mean CPU seconds (all threads; `/proc/self/stat`, 10 ms ticks,
/// hence the mean over the repeats) of `repeats` runs of `run`, and its last result.
struct Timed<T> {
    best_s: f64,
    median_s: f64,
    cpu_mean_s: Option<f64>,
    result: T,
}

fn timed<T>(
    repeats: usize,
    mut run: impl FnMut() -> anyhow::Result<T>,
) -> anyhow::Result<Timed<T>> {
    let mut times = Vec::new();
    let mut last = None;
    let cpu_start = cpu_seconds();
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        last = Some(run()?);
        times.push(start.elapsed().as_secs_f64());
    }
    let cpu_mean_s = cpu_start
        .zip(cpu_seconds())
        .map(|(a, b)| (b - a) / times.len() as f64);
    times.sort_by(f64::total_cmp);
    Ok(Timed {
        best_s: times[0],
        median_s: times[times.len() / 2],
        cpu_mean_s,
        result: last.context("no run")?,
    })
}

fn separation(dir: &Path, repeats: usize) -> anyhow::Result<serde_json::Value> {
    let params = SeparationParams::default();
    let shifts = 2 * params.stripe_px as usize;
    let n = (WIDTH * HEIGHT) as usize;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(19);
    // Smooth-ish truth: direct and global vary over the image, per channel.
    let mut direct = vec![0f32; n * 3];
    let mut global = vec![0f32; n * 3];
    for p in 0..n {
        let (x, y) = ((p % WIDTH as usize) as f32, (p / WIDTH as usize) as f32);
        for c in 0..3 {
            direct[p * 3 + c] = 0.15 + 0.25 * (0.5 + 0.5 * (x * 0.01 + c as f32).sin());
            global[p * 3 + c] = 0.1 + 0.3 * (0.5 + 0.5 * (y * 0.013 + 2.0 * c as f32).cos());
        }
    }
    let frames: Vec<Rgb32FImage> = (0..shifts)
        .map(|s| {
            let mut data = vec![0f32; n * 3];
            for p in 0..n {
                let x = p % WIDTH as usize;
                // Pixel x is lit in shift s when it falls in an on-stripe of the shifted pattern.
                let lit = ((x + s) / params.stripe_px as usize).is_multiple_of(2);
                for c in 0..3 {
                    let i = p * 3 + c;
                    let clean = if lit { direct[i] } else { 0.0 } + 0.5 * global[i];
                    data[i] = clean + 0.002 * (rng.r#gen::<f32>() - 0.5) * 3.464;
                }
            }
            Rgb32FImage::from_raw(WIDTH, HEIGHT, data).context("frame size")
        })
        .collect::<anyhow::Result<_>>()?;
    let refs: Vec<&Rgb32FImage> = frames.iter().collect();
    let Timed {
        best_s,
        median_s,
        cpu_mean_s,
        result,
    } = timed(repeats, || Ok(separate(&refs, &params)?))?;
    write_npy(
        &dir.join("frames.npy"),
        &[shifts, HEIGHT as usize, WIDTH as usize, 3],
        &{
            let mut all = Vec::with_capacity(n * 3 * shifts);
            for f in &frames {
                all.extend_from_slice(f.as_raw());
            }
            all
        },
    )?;
    let shape = [HEIGHT as usize, WIDTH as usize, 3];
    write_npy(&dir.join("direct_truth.npy"), &shape, &direct)?;
    write_npy(&dir.join("global_truth.npy"), &shape, &global)?;
    write_npy(&dir.join("direct_ours.npy"), &shape, result.direct.as_raw())?;
    write_npy(&dir.join("global_ours.npy"), &shape, result.global.as_raw())?;
    Ok(serde_json::json!({
        "kernel": "separation",
        "size": [WIDTH, HEIGHT],
        "frames": shifts,
        "threads": rayon::current_num_threads(),
        "best_s": best_s,
        "median_s": median_s,
        "cpu_mean_s": cpu_mean_s,
        "stats": result.stats,
    }))
}

fn photometric_stereo(dir: &Path, repeats: usize) -> anyhow::Result<serde_json::Value> {
    let scene = ps_scene::render(&SceneParams {
        width: WIDTH,
        height: HEIGHT,
        lights: 4,
        seed: 19,
        specular: 0.0,
        noise: 0.002,
    });
    let lights = DirectionalLights {
        lights: scene
            .directions
            .iter()
            .zip(&scene.intensities)
            .map(|(&direction, &irradiance)| LightSample {
                direction,
                irradiance,
            })
            .collect(),
        view: Vector3::z(),
    };
    let params = PsParams {
        method: Method::LeastSquares,
        ..PsParams::default()
    };
    let refs: Vec<&Rgb32FImage> = scene.images.iter().collect();
    // The normal image is inside the timed region: it is what the numpy peer returns (and what
    // the normals stage writes).
    let Timed {
        best_s,
        median_s,
        cpu_mean_s,
        result: (map, normals),
    } = timed(repeats, || {
        let map = ps::solve_images(&refs, &lights, Some(&scene.mask), &params)?;
        let normals = map.normal_image();
        Ok((map, normals))
    })?;
    let n = (WIDTH * HEIGHT) as usize;
    let mut all = Vec::with_capacity(n * 3 * refs.len());
    for im in &scene.images {
        all.extend_from_slice(im.as_raw());
    }
    let shape = [HEIGHT as usize, WIDTH as usize, 3];
    write_npy(
        &dir.join("images.npy"),
        &[refs.len(), HEIGHT as usize, WIDTH as usize, 3],
        &all,
    )?;
    write_npy(
        &dir.join("normals_truth.npy"),
        &shape,
        scene.normals.as_raw(),
    )?;
    write_npy(&dir.join("normals_ours.npy"), &shape, normals.as_raw())?;
    let mask: Vec<f32> = scene.mask.iter().map(|&m| f32::from(u8::from(m))).collect();
    write_npy(
        &dir.join("mask.npy"),
        &[HEIGHT as usize, WIDTH as usize],
        &mask,
    )?;
    let table: Vec<f32> = lights
        .lights
        .iter()
        .flat_map(|l| {
            [l.direction.x, l.direction.y, l.direction.z]
                .into_iter()
                .chain(l.irradiance)
                .map(|v| v as f32)
        })
        .collect();
    write_npy(&dir.join("lights.npy"), &[lights.lights.len(), 6], &table)?;
    Ok(serde_json::json!({
        "kernel": "ps",
        "size": [WIDTH, HEIGHT],
        "lights": refs.len(),
        "threads": rayon::current_num_threads(),
        "best_s": best_s,
        "median_s": median_s,
        "cpu_mean_s": cpu_mean_s,
        "stats": map.stats(),
    }))
}

/// A little-endian f32 array in numpy's `.npy` format (version 1.0).
fn write_npy(path: &Path, shape: &[usize], data: &[f32]) -> anyhow::Result<()> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let tuple = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {tuple}, }}");
    // Magic (6) + version (2) + length (2) + header + newline, padded to a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut file = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    file.write_all(b"\x93NUMPY\x01\x00")?;
    file.write_all(&(header.len() as u16).to_le_bytes())?;
    file.write_all(header.as_bytes())?;
    for v in data {
        file.write_all(&v.to_le_bytes())?;
    }
    file.flush()?;
    Ok(())
}

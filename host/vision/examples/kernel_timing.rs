//! Wall and CPU time of the full-size separation and distant least-squares photometric stereo
//! kernels, on the same synthetic inputs as `peer_images` (for quick iteration without the app).
//!
//! `cargo run --release -p mlsss-vision --example kernel_timing -- [separation|ps|decode] [REPEATS]`
//! (decode: the procam capture in `DECODE_DIR`, default capture_0 of the shared sample data).

use std::time::Instant;

use image::Rgb32FImage;
use mlsss_vision::photometry::photometric_stereo::{
    self as ps, DirectionalLights, LightSample, Method, PsParams,
};
use mlsss_vision::photometry::ps_scene::{self, SceneParams};
use mlsss_vision::photometry::separation::{SeparationParams, separate};

const WIDTH: u32 = 1379;
const HEIGHT: u32 = 1029;

fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = stat.rsplit(')').next().unwrap_or("");
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (tick(11) + tick(12)) / 100.0
}

fn time(label: &str, repeats: usize, mut run: impl FnMut()) {
    let mut times = Vec::new();
    let cpu0 = cpu_seconds();
    for _ in 0..repeats {
        let t = Instant::now();
        run();
        times.push(t.elapsed().as_secs_f64());
    }
    let cpu = (cpu_seconds() - cpu0) / repeats as f64;
    times.sort_by(f64::total_cmp);
    println!(
        "{label}: best {:.4} s, median {:.4} s, cpu mean {:.4} s",
        times[0],
        times[times.len() / 2],
        cpu
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = args.get(1).map_or("ps", |s| s.as_str());
    let repeats: usize = args.get(2).and_then(|r| r.parse().ok()).unwrap_or(20);
    if kind == "decode" {
        use mlsss_vision::geometry::code_frames;
        use mlsss_vision::geometry::gray_code::{DecodeParams, DecodePhases, decode_timed};
        let dir = std::env::var("DECODE_DIR")
            .unwrap_or_else(|_| "../shared/data/procam-calibration/sample_data/capture_0".into());
        let size = (1024, 768);
        let frames = code_frames::from_opencv_dir(std::path::Path::new(&dir), size).unwrap();
        let params = DecodeParams::for_8_bit();
        let mut last = None;
        // The phases of the best run (wall seconds of the decoder's steps).
        let mut best: Option<(f64, DecodePhases)> = None;
        time("decode", repeats, || {
            let t = Instant::now();
            let (d, phases) = decode_timed(&frames, size, &params).unwrap();
            let wall = t.elapsed().as_secs_f64();
            if best.is_none_or(|(b, _)| wall < b) {
                best = Some((wall, phases));
            }
            last = Some(d);
        });
        if let Some((_, p)) = best {
            println!(
                "phases of the best run: bits {:.4} s, repair {:.4} s, check {:.4} s",
                p.bits_s, p.repair_s, p.check_s
            );
        }
        let Some(d) = last else { return };
        // A fingerprint of every output, to tell a bit-identical change from one that is not.
        use std::hash::{Hash, Hasher};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        for axis in [&d.u, &d.v] {
            axis.code.hash(&mut h);
            axis.status.hash(&mut h);
            axis.coord.iter().for_each(|c| c.to_bits().hash(&mut h));
        }
        d.confidence.iter().for_each(|c| c.to_bits().hash(&mut h));
        println!("{:?} fingerprint {:016x}", d.summary(), h.finish());
    } else if kind == "ps" {
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
            view: nalgebra::Vector3::z(),
        };
        let params = PsParams {
            method: Method::LeastSquares,
            ..PsParams::default()
        };
        let refs: Vec<&Rgb32FImage> = scene.images.iter().collect();
        let mut solved = 0;
        time("ps", repeats, || {
            let map = ps::solve_images(&refs, &lights, Some(&scene.mask), &params).unwrap();
            std::hint::black_box(map.normal_image());
            solved = map.pixels.len();
        });
        println!("solved {solved}");
    } else {
        let frames: Vec<Rgb32FImage> = (0..6u32)
            .map(|s| {
                Rgb32FImage::from_fn(WIDTH, HEIGHT, |x, y| {
                    let lit = ((x + s) / 3) % 2 == 0;
                    let v =
                        if lit { 0.3 } else { 0.0 } + 0.1 + 0.001 * ((x * 7 + y * 13) % 17) as f32;
                    image::Rgb([v, 0.8 * v, 0.6 * v])
                })
            })
            .collect();
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let params = SeparationParams::default();
        time("separation", repeats, || {
            let s = separate(&refs, &params).unwrap();
            std::hint::black_box(&s);
        });
    }
}

//! Decode throughput on a full-size booth capture: 4 projectors x 40 Gray-code frames at
//! 1379x1029 (synthetic frames with a known mapping, lens blur and sensor noise), in frames per
//! second, and in the same run a straightforward numpy vectorised decode of the same frames
//! (`benches/decode_numpy.py`, skipped with a note when python3/numpy are missing).
//!
//!     cargo bench -p mlsss-vision --bench decode
//!
//! A booth capture takes 53.6 s (268 frames at 5 fps); decoding its 160 Gray-code frames must take
//! a small part of that.

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use mlsss_vision::geometry::gray_code::{DecodeParams, GrayCodeFrames, decode};
use mlsss_vision::geometry::synthetic::SyntheticGrayScene;

const CAMERA: (u32, u32) = (1379, 1029);
const PROJECTOR: (u32, u32) = (1024, 768);
const PROJECTORS: usize = 4;

fn full_size_frames() -> GrayCodeFrames {
    let mut scene = SyntheticGrayScene::new(CAMERA, PROJECTOR);
    // About 2 camera pixels per projector pixel, as in the booth; some subsurface blur.
    scene.u = [200.3, 0.47, 0.03];
    scene.v = [150.6, -0.02, 0.5];
    scene.direct_fraction = 0.3;
    scene.global_blur_px = 2.0;
    scene.render()
}

fn write_raw(frames: &GrayCodeFrames, path: &Path) -> std::io::Result<()> {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
    let all: Vec<&Vec<f32>> = frames
        .white
        .iter()
        .chain(frames.black.iter())
        .chain(frames.x.iter().flat_map(|p| [&p.pattern, &p.inverse]))
        .chain(frames.y.iter().flat_map(|p| [&p.pattern, &p.inverse]))
        .collect();
    for v in [frames.width, frames.height, all.len() as u32] {
        out.write_all(&v.to_le_bytes())?;
    }
    for f in all {
        for v in f {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()
}

fn numpy_peer(frames: &GrayCodeFrames) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/decode_numpy.py");
    let raw = std::env::temp_dir().join(format!("mlsss-decode-bench-{}.f32", std::process::id()));
    if let Err(e) = write_raw(frames, &raw) {
        eprintln!("numpy peer skipped: cannot write {}: {e}", raw.display());
        return;
    }
    match std::process::Command::new("python3")
        .arg(&script)
        .arg(&raw)
        .output()
    {
        Ok(out) if out.status.success() => {
            println!(
                "numpy peer: {}",
                String::from_utf8_lossy(&out.stdout).trim()
            );
        }
        Ok(out) => eprintln!(
            "numpy peer skipped: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        ),
        Err(e) => eprintln!("numpy peer skipped: python3: {e}"),
    }
    let _ = std::fs::remove_file(&raw);
}

fn bench_decode(c: &mut Criterion) {
    let start = Instant::now();
    let frames = full_size_frames();
    eprintln!("rendered frames in {:.1} s", start.elapsed().as_secs_f64());
    let params = DecodeParams::default();
    let code_frames = (frames.x.len() + frames.y.len()) * 2;

    let mut group = c.benchmark_group("decode");
    group.sample_size(10);
    group.throughput(Throughput::Elements((code_frames * PROJECTORS) as u64));
    group.bench_function("booth_capture_4x40_frames_1379x1029", |b| {
        b.iter(|| {
            for _ in 0..PROJECTORS {
                let d = decode(&frames, PROJECTOR, &params).expect("synthetic frames decode");
                std::hint::black_box(&d);
            }
        })
    });
    group.finish();

    let start = Instant::now();
    let d = decode(&frames, PROJECTOR, &params).expect("synthetic frames decode");
    let seconds = start.elapsed().as_secs_f64();
    println!(
        "mlsss decode: {:.3} s per projector, {:.0} frames/s, valid fraction {:.3}, {:.1} s per \
         4-projector capture (capture takes 53.6 s)",
        seconds,
        code_frames as f64 / seconds,
        d.summary().valid_fraction(),
        seconds * PROJECTORS as f64
    );
    numpy_peer(&frames);
}

criterion_group!(benches, bench_decode);
criterion_main!(benches);

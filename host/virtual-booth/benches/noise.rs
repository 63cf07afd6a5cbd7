//! Camera noise per frame value, single-threaded: `CameraModel::add_noise_with_gain` (f32
//! Box-Muller over SIMD lanes, `mlsss_mc::NormalStream`) against the generator it replaced
//! (`rand_distr`'s ziggurat `StandardNormal` on a `Pcg64` seeded per frame, f64 square root),
//! kept here as the reference; and the deviates alone from each generator.
//!
//!     cargo bench -p mlsss-virtual-booth --bench noise
//!
//! One quick-booth frame (460 x 343 pixels, RGB) per iteration; criterion reports values per
//! second (throughput in "elements").

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use mlsss_core::booth::Booth;
use mlsss_mc::NormalStream;
use mlsss_virtual_booth::camera::CameraModel;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64;

const VALUES: usize = 460 * 343 * 3;

/// The noise as `add_noise_with_gain` computed it before `NormalStream` (full well and read
/// noise of the quick booth: 12000 e-, 2 DN of 4095).
fn ziggurat_noise(values: &mut [f32], gain: f64, rng: &mut Pcg64) {
    let shot = gain / 12_000.0;
    let read = (2.0f64 / 4095.0).powi(2);
    for v in values.iter_mut() {
        let sigma = (f64::from(*v).max(0.0) * shot + read).sqrt();
        *v = (f64::from(*v) + sigma * rng.sample::<f64, _>(StandardNormal)) as f32;
    }
}

fn frame_noise(c: &mut Criterion) {
    let camera = CameraModel::new(&Booth::builtin(true));
    // A frame of mid-grey with some spread, so no branch is always taken.
    let clean: Vec<f32> = (0..VALUES)
        .map(|i| 0.05 + 0.9 * ((i * 7919) % 1000) as f32 / 1000.0)
        .collect();
    let mut values = clean.clone();
    let mut group = c.benchmark_group("frame_noise");
    group.throughput(Throughput::Elements(VALUES as u64));
    group.sample_size(30);
    let mut frame = 0u64;
    group.bench_function("ziggurat_pcg64_f64", |b| {
        b.iter(|| {
            values.copy_from_slice(&clean);
            frame += 1;
            let mut rng = Pcg64::seed_from_u64(frame << 8);
            ziggurat_noise(&mut values, 1.5, &mut rng);
        })
    });
    group.bench_function("box_muller_lanes_f32", |b| {
        b.iter(|| {
            values.copy_from_slice(&clean);
            frame += 1;
            let mut normals = NormalStream::new(1, frame);
            camera.add_noise_with_gain(&mut values, 1.5, &mut normals);
        })
    });
    group.bench_function("deviates_ziggurat_pcg64_f64", |b| {
        b.iter(|| {
            frame += 1;
            let mut rng = Pcg64::seed_from_u64(frame << 8);
            for v in values.iter_mut() {
                *v = rng.sample::<f64, _>(StandardNormal) as f32;
            }
        })
    });
    group.bench_function("deviates_box_muller_lanes_f32", |b| {
        b.iter(|| {
            frame += 1;
            NormalStream::new(1, frame).fill(&mut values);
        })
    });
    group.finish();
}

criterion_group!(benches, frame_noise);
criterion_main!(benches);

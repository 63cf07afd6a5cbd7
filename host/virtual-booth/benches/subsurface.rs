//! The subsurface gather (`SubsurfaceOperator::apply`): one projector's batch of frames on a
//! quick-booth-sized view (460 x 343 pixels of 0.35 mm on a plane, light at 40 degrees), three
//! basis materials mixed per pixel (six table taps), the quick booth's four tabulated angles and
//! response grid (cells of a third of a pixel out to +-10 mm). The scan's frames cost this per
//! projector and batch; on the quick demo it was ~30 % of the CPU time.
//!
//!     cargo bench -p mlsss-virtual-booth --bench subsurface

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};

use mlsss_virtual_booth::subsurface_transport::{
    EntrySample, INNER_BAND_PIXELS, ResponseGrid, ResponseSet, SubsurfaceKernel, SubsurfaceOperator,
};

const WIDTH: usize = 460;
const HEIGHT: usize = 343;
const PIXEL_MM: f64 = 0.35;
const FRAMES: usize = 16;

/// A forward-shifted Gaussian response of per-channel widths (mm), unit total per channel.
fn response(cell_mm: f64, cells: usize, sigma: [f64; 3], shift: f64) -> ResponseGrid {
    let centre = (cells as f64 - 1.0) / 2.0;
    let values = (0..cells * cells)
        .map(|i| {
            let x = ((i % cells) as f64 - centre) * cell_mm;
            let y = ((i / cells) as f64 - centre) * cell_mm;
            std::array::from_fn(|c| {
                let s2 = sigma[c] * sigma[c];
                ((-((x - shift).powi(2) + y * y) / (2.0 * s2)).exp()
                    / (2.0 * std::f64::consts::PI * s2)) as f32
            })
        })
        .collect();
    ResponseGrid {
        cell_mm,
        cells,
        values,
    }
}

fn responses() -> ResponseSet {
    let cell_mm = (PIXEL_MM / 3.0 * 1000.0).round() / 1000.0;
    let cells = (20.0 / cell_mm).round() as usize | 1;
    let angles_deg = vec![0.0, 30.0, 55.0, 80.0];
    let grids = (0..4)
        .map(|m| {
            angles_deg
                .iter()
                .map(|a: &f64| {
                    let k = 1.0 + 0.1 * m as f64;
                    response(cell_mm, cells, [1.5 * k, 0.8 * k, 0.4 * k], a / 200.0)
                })
                .collect()
        })
        .collect();
    ResponseSet { angles_deg, grids }
}

fn entries() -> Vec<Option<EntrySample>> {
    let light = Vector3::new(40f64.to_radians().sin(), 0.0, -40f64.to_radians().cos());
    (0..WIDTH * HEIGHT)
        .map(|i| {
            let (x, y) = ((i % WIDTH) as f64, (i / WIDTH) as f64);
            let melanin = 0.2 * (0.5 + 0.5 * (x / 23.0).sin());
            let blood = 0.1 * (0.5 + 0.5 * (y / 17.0).cos());
            Some(EntrySample {
                point: Point3::new(x * PIXEL_MM, y * PIXEL_MM, 0.0),
                normal: -Vector3::z(),
                to_light: light,
                area_mm2: PIXEL_MM * PIXEL_MM,
                materials: [1.0 - melanin - blood, melanin, blood, 0.0].map(|v| v as f32),
            })
        })
        .collect()
}

/// Stripes of several widths, one per frame (`flux[pixel * FRAMES + f]`).
fn flux() -> Vec<f32> {
    (0..WIDTH * HEIGHT)
        .flat_map(|i| {
            let x = i % WIDTH;
            (0..FRAMES).map(move |f| {
                let period = 2 << (f % 6);
                if (x / period + f / 6).is_multiple_of(2) {
                    0.12
                } else {
                    0.0
                }
            })
        })
        .collect()
}

/// The operator at the full-size booth's innermost band (4 px) and the small booths' (3 px).
fn gather(c: &mut Criterion) {
    let responses = responses();
    let entries = entries();
    let flux = flux();
    let mut group = c.benchmark_group("subsurface");
    group.sample_size(10);
    for (label, inner_band_px) in [("", INNER_BAND_PIXELS), ("_inner_3px", 3.0)] {
        let kernel = SubsurfaceKernel::new(
            &responses,
            PIXEL_MM,
            PIXEL_MM,
            WIDTH.max(HEIGHT),
            inner_band_px,
        );
        group.bench_function(format!("operator_new{label}"), |b| {
            b.iter(|| SubsurfaceOperator::new(&kernel, WIDTH, HEIGHT, &entries))
        });
        let operator = SubsurfaceOperator::new(&kernel, WIDTH, HEIGHT, &entries);
        group.bench_function(format!("apply_16_frames{label}"), |b| {
            b.iter(|| operator.apply(&flux, FRAMES))
        });
    }
    group.finish();
}

criterion_group!(benches, gather);
criterion_main!(benches);

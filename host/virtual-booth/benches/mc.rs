//! Monte Carlo photon throughput, single-threaded (per core), on the media the virtual booth
//! actually tabulates: the light-skin base material (epidermis over dermis, layered, n 1.4) at
//! each channel, 30 degrees incidence, with the quick booth's exit grid (cells of a third of a
//! pixel out to +-10 mm), the semi-infinite skin of `mlsss mc bench` for comparison, and MCML's own
//! 7-layer skin at 600 nm (`host/monte-carlo/data/mcml-7layer-skin-600nm.toml`, normal incidence,
//! the input `host/monte-carlo/benches/mcml_race.py` races against MCML).
//!
//!     cargo bench -p mlsss-virtual-booth --bench mc
//!
//! Criterion reports time per batch of photons and photons per second (throughput in
//! "elements"). The quick booth traces 20 000 photons per material, angle and channel.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use mlsss_core::booth::Booth;
use mlsss_mc::{GridSpec, Layer, LayersFile, McConfig, Medium, run};
use mlsss_virtual_booth::response_cache::material_medium;
use mlsss_virtual_booth::{SimulationOptions, SkinPreset, SubjectKind};

const PHOTONS: u64 = 20_000;

/// Jensen et al. 2001 "Skin1", green channel, as in `mlsss mc bench`.
fn semi_infinite_skin() -> Medium {
    let g = 0.8;
    let layer = Layer {
        thickness_mm: f64::INFINITY,
        mu_a: 0.17,
        mu_s: 0.88 / (1.0 - g),
        g,
        n: 1.4,
    };
    Medium::slab(layer, 1.0, 1.0)
}

fn photon_throughput(c: &mut Criterion) {
    let booth = Booth::builtin(true);
    let opts = SimulationOptions::for_booth(&booth, SubjectKind::Head, SkinPreset::LIGHT, 1);
    let grid = GridSpec {
        cell_mm: opts.mc.cell_mm,
        cells: opts.mc.cells,
    };
    let base = &SkinPreset::LIGHT.materials()[0];
    let mut cases: Vec<(String, Medium, Option<GridSpec>)> = ["red", "green", "blue"]
        .iter()
        .enumerate()
        .map(|(channel, name)| {
            (
                format!("light_skin_base_{name}_grid"),
                material_medium(base, channel),
                Some(grid),
            )
        })
        .collect();
    cases.push((
        "semi_infinite_skin1_green".into(),
        semi_infinite_skin(),
        None,
    ));
    let mcml_input = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../monte-carlo/data/mcml-7layer-skin-600nm.toml");
    let seven_layers = LayersFile::read(&mcml_input).expect("the MCML 7-layer input");

    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a one-thread rayon pool");
    let mut group = c.benchmark_group("mc_photons_one_core");
    group.sample_size(10);
    let mut runs: Vec<(String, Medium, McConfig)> = cases
        .into_iter()
        .map(|(name, medium, grid)| {
            let cfg = McConfig {
                incidence_deg: 30.0,
                grid,
                ..McConfig::new(PHOTONS, 1)
            };
            (name, medium, cfg)
        })
        .collect();
    // Photons live ~7x longer there (1,260 interactions each): fewer of them.
    runs.push((
        "mcml_seven_layer_skin_600nm".into(),
        seven_layers.medium(),
        McConfig::new(PHOTONS / 4, 1),
    ));
    for (name, medium, cfg) in &runs {
        group.throughput(Throughput::Elements(cfg.photons));
        group.bench_with_input(BenchmarkId::from_parameter(name), cfg, |b, cfg| {
            b.iter(|| pool.install(|| run(medium, cfg).expect("valid medium")))
        });
    }
    group.finish();
}

criterion_group!(benches, photon_throughput);
criterion_main!(benches);

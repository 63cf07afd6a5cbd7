//! Times `mlsss_mc::run` on MCML's 7-layer skin (the race input) in this process, one thread:
//! `cargo run --release -p mlsss-mc --example seven_layer -- [PHOTONS] [SEED]` (`MC_FILE=x.toml`
//! for another layers file). Prints the result and photons per CPU second of this process (CPU
//! time from Linux's /proc/self/stat): a quick A/B tool; the race against MCML is
//! `benches/mcml_race.py`.

use std::path::Path;

fn cpu_seconds() -> f64 {
    // user + system time of this process, from /proc/self/stat (fields 14 and 15, in ticks).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let fields: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (ticks(11) + ticks(12)) / 100.0
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let photons: u64 = args.get(1).map_or(Ok(100_000), |s| s.parse())?;
    let seed: u64 = args.get(2).map_or(Ok(201), |s| s.parse())?;
    let file = std::env::var("MC_FILE")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|_| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("data/mcml-7layer-skin-600nm.toml")
        });
    let medium = mlsss_mc::LayersFile::read(&file)?.medium();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let cpu0 = cpu_seconds();
    let r = pool.install(|| mlsss_mc::run(&medium, &mlsss_mc::McConfig::new(photons, seed)))?;
    let cpu = cpu_seconds() - cpu0;
    println!(
        "simd {} Rd {:.5} +- {:.5} T {:.6} +- {:.6} A {:?}",
        r.simd,
        r.diffuse_reflectance,
        r.diffuse_reflectance_se,
        r.total_transmittance,
        r.total_transmittance_se,
        r.absorbed
            .iter()
            .map(|a| format!("{a:.5}"))
            .collect::<Vec<_>>()
    );
    println!(
        "interactions/photon {:.1}  photons/CPU-s {:.4e}  interactions/CPU-s {:.4e}  (cpu {cpu:.2} s)",
        r.interactions_per_photon,
        photons as f64 / cpu,
        r.interactions_per_photon * photons as f64 / cpu
    );
    Ok(())
}

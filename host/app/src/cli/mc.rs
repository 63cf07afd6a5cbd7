//! `mlsss mc`: Monte Carlo light transport in a planar multi-layer medium (MCML physics).

use std::path::PathBuf;

use anyhow::Context;
use mlsss::mc::{self, Layer, LayersFile, McConfig, McResult, Medium};
use mlsss_core::resources::cpu_seconds;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: McCommand,
}

#[derive(Debug, clap::Subcommand)]
enum McCommand {
    /// A single homogeneous slab given by albedo and optical thickness (mu_t = 1/mm, so lengths
    /// are in mean free paths).
    Slab(SlabArgs),
    /// A layered medium described in a TOML file (format: host/monte-carlo/src/layers_file.rs).
    Layers(LayersArgs),
    /// Measure photons per second per core for a semi-infinite skin layer (use a release build).
    Bench(BenchArgs),
}

/// Settings shared by every run.
#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Number of photons to launch.
    #[arg(long, default_value_t = 1_000_000)]
    photons: u64,
    /// Seed of the random streams; the same seed gives the same result on any number of threads.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Angle of incidence of the pencil beam, degrees from the surface normal, in [0, 90).
    #[arg(long, default_value_t = 0.0)]
    angle: f64,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, clap::Args)]
struct SlabArgs {
    /// Single-scattering albedo mu_s / (mu_a + mu_s), in [0, 1].
    #[arg(long)]
    albedo: f64,
    /// Optical thickness (mu_a + mu_s) d; `inf` for a semi-infinite medium.
    #[arg(long)]
    tau: f64,
    /// Henyey-Greenstein anisotropy g, in (-1, 1).
    #[arg(long, default_value_t = 0.0)]
    g: f64,
    /// Refractive index of the slab.
    #[arg(long, default_value_t = 1.0)]
    n: f64,
    /// Refractive index above the slab (the light comes from there).
    #[arg(long, default_value_t = 1.0)]
    n_above: f64,
    /// Refractive index below the slab.
    #[arg(long, default_value_t = 1.0)]
    n_below: f64,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Debug, clap::Args)]
struct LayersArgs {
    /// Layers file (TOML), e.g. host/monte-carlo/data/skin-layers.toml.
    #[arg(long)]
    file: PathBuf,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Debug, clap::Args)]
struct BenchArgs {
    /// Number of photons to launch.
    #[arg(long, default_value_t = 200_000)]
    photons: u64,
    /// Worker threads (the figure reported is per core, i.e. per thread).
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.command {
        McCommand::Slab(a) => run_slab(a),
        McCommand::Layers(a) => run_layers(a),
        McCommand::Bench(a) => run_bench(a),
    }
}

fn run_slab(args: SlabArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        (0.0..=1.0).contains(&args.albedo),
        "--albedo {} is outside [0, 1]",
        args.albedo
    );
    let layer = Layer::from_albedo(args.albedo, args.tau, args.g, args.n);
    let medium = Medium::slab(layer, args.n_above, args.n_below);
    simulate_and_print(&medium, &args.run)
}

fn run_layers(args: LayersArgs) -> anyhow::Result<()> {
    let file = LayersFile::read(&args.file)
        .with_context(|| format!("loading layers file {}", args.file.display()))?;
    simulate_and_print(&file.medium(), &args.run)
}

fn simulate_and_print(medium: &Medium, run: &RunArgs) -> anyhow::Result<()> {
    let cfg = McConfig {
        incidence_deg: run.angle,
        ..McConfig::new(run.photons, run.seed)
    };
    eprintln!(
        "mc: {} photons, {} layer(s), incidence {} deg",
        run.photons,
        medium.layers.len(),
        run.angle
    );
    let result = mc::run(medium, &cfg).context("Monte Carlo run")?;
    let missing = unaccounted_energy(&result);
    anyhow::ensure!(
        missing.abs() <= MAX_UNACCOUNTED_ENERGY,
        "the tallies miss {:.3} % of the light: photons that stay in the medium for more than a \
         million scattering events are dropped. Lower mu_s or raise mu_a (this medium scatters \
         {:.3e} times per photon)",
        100.0 * missing,
        result.interactions_per_photon
    );
    if run.json {
        println!("{}", result_json(&result));
    } else {
        print_human(&result);
    }
    Ok(())
}

/// Largest share of the light the tallies may miss: roulette keeps the balance exact on average,
/// so more than this means photons were dropped (trapped past the event cap).
const MAX_UNACCOUNTED_ENERGY: f64 = 1e-3;

/// 1 minus everything tallied (specular, diffuse reflectance, transmittance, absorption).
fn unaccounted_energy(r: &McResult) -> f64 {
    1.0 - r.specular
        - r.diffuse_reflectance
        - r.total_transmittance
        - r.absorbed.iter().sum::<f64>()
}

fn result_json(r: &McResult) -> serde_json::Value {
    serde_json::json!({
        "specular": r.specular,
        "diffuse_reflectance": r.diffuse_reflectance,
        "diffuse_reflectance_se": r.diffuse_reflectance_se,
        "total_transmittance": r.total_transmittance,
        "total_transmittance_se": r.total_transmittance_se,
        "absorbed": r.absorbed,
        "absorbed_se": r.absorbed_se,
        "exit_centroid_mm": r.exit_centroid_mm,
        "photons": r.photons,
        "photons_per_second": r.photons_per_second,
        "interactions_per_second": r.interactions_per_second,
        "threads": r.threads,
        "simd": r.simd,
        "interactions_per_photon": r.interactions_per_photon,
        "unaccounted_energy": unaccounted_energy(r),
    })
}

fn print_human(r: &McResult) {
    println!("specular             {:.6}", r.specular);
    println!(
        "diffuse reflectance  {:.6} +- {:.6}",
        r.diffuse_reflectance, r.diffuse_reflectance_se
    );
    println!(
        "total transmittance  {:.6} +- {:.6}",
        r.total_transmittance, r.total_transmittance_se
    );
    for (i, (a, se)) in r.absorbed.iter().zip(&r.absorbed_se).enumerate() {
        println!("absorbed, layer {i}    {a:.6} +- {se:.6}");
    }
    println!(
        "exit centroid        ({:.4}, {:.4}) mm",
        r.exit_centroid_mm[0], r.exit_centroid_mm[1]
    );
    println!(
        "{} photons, {:.0} photons/s ({:.3e} interactions/s) on {} thread(s), {} lanes",
        r.photons, r.photons_per_second, r.interactions_per_second, r.threads, r.simd
    );
}

/// Semi-infinite skin: Jensen et al. 2001 "Skin1", green channel (mu_s' 0.88/mm, mu_a 0.17/mm),
/// with g = 0.8 so mu_s = 4.4/mm, and n = 1.4 under air.
fn bench_skin() -> Medium {
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

fn run_bench(args: BenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.threads >= 1, "--threads must be at least 1");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()
        .context("building the thread pool")?;
    let medium = bench_skin();
    let cfg = McConfig::new(args.photons, 1);
    // Warm the pool's threads (start-up cost is not the bench's).
    pool.install(|| mc::run(&medium, &McConfig::new(1000, 0)))
        .context("Monte Carlo warm-up")?;
    let cpu_before = cpu_seconds();
    let result = pool
        .install(|| mc::run(&medium, &cfg))
        .context("Monte Carlo run")?;
    let cpu_used = cpu_before
        .zip(cpu_seconds())
        .map(|(before, after)| after - before);
    drop(pool);
    let per_core = result.photons_per_second / args.threads as f64;
    // On a shared machine wall-clock throughput understates the code's speed; photons per CPU
    // second is what one uncontended core would do.
    let per_cpu_second = cpu_used
        .filter(|&s| s > 0.0)
        .map(|s| result.photons as f64 / s);
    if cfg!(debug_assertions) {
        eprintln!("mc bench: warning: this is a debug build; use `cargo run --release`");
    }
    if args.json {
        let value = serde_json::json!({
            "medium": "semi-infinite skin (Jensen 2001 Skin1 green: mu_a 0.17/mm, mu_s' 0.88/mm, g 0.8, n 1.4)",
            "photons": result.photons,
            "threads": args.threads,
            "photons_per_second": result.photons_per_second,
            "photons_per_second_per_core": per_core,
            "photons_per_cpu_second": per_cpu_second,
            "cpu_seconds": cpu_used,
            "diffuse_reflectance": result.diffuse_reflectance,
            "interactions_per_photon": result.interactions_per_photon,
            "interactions_per_second": result.interactions_per_second,
            "simd": result.simd,
        });
        println!("{value}");
    } else {
        println!(
            "semi-infinite skin (mu_a 0.17/mm, mu_s' 0.88/mm, g 0.8, n 1.4): {:.3e} photons/s per core ({} photons, {} thread(s), R_d {:.4})",
            per_core, result.photons, args.threads, result.diffuse_reflectance
        );
        if let Some(p) = per_cpu_second {
            println!(
                "{p:.3e} photons per CPU second (independent of other load on the machine), {:.1} interactions per photon",
                result.interactions_per_photon
            );
        }
    }
    Ok(())
}

//! `mlsss ps-scene`: renders a photometric-stereo test set with known normals (spheres with cast
//! shadows, highlights and saturation under distant lights) in the layout `mlsss normals` reads.

use std::path::PathBuf;

use anyhow::bail;
use mlsss::photometry::ps_scene::{self, SceneParams};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output folder (created; must not exist yet).
    #[arg(long)]
    out: PathBuf,
    /// Number of lights (images).
    #[arg(long, default_value_t = 12)]
    lights: usize,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 128)]
    size: u32,
    /// Blinn-Phong specular weight (0: purely Lambertian).
    #[arg(long, default_value_t = 0.8, value_parser = super::number_arg::non_negative_finite)]
    specular: f64,
    /// Standard deviation of the additive noise, linear units.
    #[arg(long, default_value_t = 0.002, value_parser = super::number_arg::non_negative_finite)]
    noise: f64,
    /// Random seed (noise and light intensities).
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.out.exists() {
        bail!(
            "{} exists already; remove it or choose another --out",
            args.out.display()
        );
    }
    if !(3..=128).contains(&args.lights) || args.size < 8 {
        bail!("--lights must be 3..=128 and --size at least 8");
    }
    let scene = ps_scene::render(&SceneParams {
        width: args.size,
        height: args.size,
        lights: args.lights,
        seed: args.seed,
        specular: args.specular,
        noise: args.noise,
    });
    ps_scene::write_folder(&scene, &args.out)?;
    eprintln!(
        "wrote {} images, lights, mask and truth (normal.exr, normal.png, Normal_gt.mat) to {}",
        args.lights,
        args.out.display()
    );
    Ok(())
}

//! `mlsss normals`: directional-light photometric stereo on any image set (e.g. DiLiGenT).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use image::Rgb32FImage;
use mlsss::photometry::image_set;
use mlsss::photometry::photometric_stereo::{
    self as ps, DirectionalLights, LightSample, Method, PsParams,
};
use nalgebra::Vector3;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Folder of 8/16-bit linear PNG images, in the order of `filenames.txt` if present, else
    /// sorted by name (mask*.png and normal*.png are left out).
    #[arg(long)]
    images: PathBuf,
    /// Light directions, one `x y z` per image (surface to light, in the normals' frame).
    #[arg(long)]
    lights: PathBuf,
    /// Per-image RGB light intensities, one `r g b` per image (default: all 1).
    #[arg(long)]
    intensities: Option<PathBuf>,
    /// Mask PNG: only non-zero pixels are solved (default: every pixel).
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Use only these images: 1-based indices and ranges, e.g. `1,5,9-12`.
    #[arg(long)]
    select: Option<String>,
    /// Output normal map (RGB float EXR; zero where a pixel is masked or flagged).
    #[arg(long)]
    out: PathBuf,
    /// Also write the RGB albedo as an EXR.
    #[arg(long)]
    albedo: Option<PathBuf>,
    /// Ground-truth normals (EXR, PNG as 0.5 n + 0.5, or .mat with `Normal_gt`) for the errors.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Solver: robust (shadow and highlight rejection) or the least-squares baseline.
    #[arg(long, value_enum, default_value = "robust")]
    method: Method,
    /// Direction to the camera, `x,y,z` (used to judge highlights and back-facing normals).
    #[arg(long, default_value = "0,0,1", value_parser = parse_vector)]
    view: Vector3<f64>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

fn parse_vector(text: &str) -> Result<Vector3<f64>, String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>().map_err(|e| format!("'{s}': {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, z] => Vector3::new(x, y, z)
            .try_normalize(1e-12)
            .ok_or_else(|| "the view direction must not be zero".into()),
        _ => Err("expected three comma-separated numbers x,y,z".into()),
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let files = image_set::image_files(&args.images)?;
    refuse_overwriting_inputs(&args, &files)?;
    let light_table = read_light_table(&args, files.len())?;
    let selected = match &args.select {
        Some(text) => image_set::parse_selection(text, files.len())?,
        None => (0..files.len()).collect(),
    };
    let images = read_images(&files, &selected)?;
    let (width, height) = images
        .first()
        .map(|im| im.dimensions())
        .context("no images selected")?;
    let mask = read_mask(args.mask.as_deref(), (width, height))?;
    let lights = DirectionalLights {
        lights: selected.iter().map(|&i| light_table[i]).collect(),
        view: args.view,
    };
    let params = PsParams {
        method: args.method,
        ..PsParams::default()
    };
    let refs: Vec<_> = images.iter().collect();
    let map = ps::solve_images(&refs, &lights, mask.as_deref(), &params)?;
    let normals = map.normal_image();
    mlsss::imageio::write_exr_rgb(&args.out, &normals)?;
    if let Some(path) = &args.albedo {
        mlsss::imageio::write_exr_rgb(path, &map.albedo_image())?;
    }
    let stats = map.stats();
    let mut report = stats.report_json();
    report["method"] = serde_json::json!(args.method);
    report["images"] = selected.len().into();
    report["out"] = serde_json::json!(args.out);
    if let Some(path) = &args.truth {
        add_truth_errors(&mut report, path, &normals, mask.as_deref())?;
    }
    if args.json {
        println!("{report}");
    } else {
        eprintln!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(())
}

/// Refuses `--out` and `--albedo` paths that are an input image, table or mask, or each other.
fn refuse_overwriting_inputs(args: &Args, files: &[PathBuf]) -> anyhow::Result<()> {
    let mut inputs: Vec<(&str, &Path)> = files
        .iter()
        .map(|f| ("an input image", f.as_path()))
        .collect();
    inputs.push(("--lights", &args.lights));
    for (flag, path) in [
        ("--intensities", &args.intensities),
        ("--mask", &args.mask),
        ("--truth", &args.truth),
    ] {
        if let Some(p) = path {
            inputs.push((flag, p));
        }
    }
    let mut outputs: Vec<(&str, &Path)> = vec![("--out", &args.out)];
    if let Some(albedo) = &args.albedo {
        outputs.push(("--albedo", albedo));
    }
    super::output_paths::refuse_overlaps(&inputs, &outputs)
}

/// Every image's light: its direction and RGB intensity (all 1 without `--intensities`), checked
/// to be one per image.
fn read_light_table(args: &Args, images: usize) -> anyhow::Result<Vec<LightSample>> {
    let directions = image_set::read_directions(&args.lights)?;
    if directions.len() != images {
        bail!(
            "{} has {} light directions but {} lists {} images; give one direction per image",
            args.lights.display(),
            directions.len(),
            args.images.display(),
            images
        );
    }
    let intensities = match &args.intensities {
        Some(path) => {
            let rows = image_set::read_intensities(path)?;
            if rows.len() != images {
                bail!(
                    "{} has {} rows but there are {} images",
                    path.display(),
                    rows.len(),
                    images
                );
            }
            rows
        }
        None => vec![[1.0; 3]; images],
    };
    Ok(directions
        .into_iter()
        .zip(intensities)
        .map(|(direction, irradiance)| LightSample {
            direction,
            irradiance,
        })
        .collect())
}

/// The `selected` images of `files`, with a progress bar.
fn read_images(files: &[PathBuf], selected: &[usize]) -> anyhow::Result<Vec<Rgb32FImage>> {
    let progress =
        indicatif::ProgressBar::new(selected.len() as u64).with_message("reading images");
    let images = selected
        .iter()
        .map(|&i| {
            progress.inc(1);
            image_set::read_linear_png(&files[i])
        })
        .collect::<Result<Vec<_>, _>>()?;
    progress.finish_and_clear();
    Ok(images)
}

/// The `--mask`, if given, checked to be the images' `size`.
fn read_mask(
    path: Option<&Path>,
    (width, height): (u32, u32),
) -> anyhow::Result<Option<Vec<bool>>> {
    let Some(path) = path else {
        return Ok(None);
    };
    let (w, h, m) = image_set::read_mask(path)?;
    if (w, h) != (width, height) {
        bail!(
            "mask {} is {w}x{h} but the images are {width}x{height}",
            path.display()
        );
    }
    Ok(Some(m))
}

/// Adds the angular errors of `normals` against the true normals at `path` to `report`.
fn add_truth_errors(
    report: &mut serde_json::Value,
    path: &Path,
    normals: &Rgb32FImage,
    mask: Option<&[bool]>,
) -> anyhow::Result<()> {
    let (width, height) = normals.dimensions();
    let truth = image_set::read_truth_normals(path)?;
    if truth.dimensions() != (width, height) {
        bail!(
            "truth {} is {:?} but the images are {width}x{height}",
            path.display(),
            truth.dimensions()
        );
    }
    // Errors over the pixels that have a truth normal and are in the mask; flagged pixels
    // count separately (as `solved` < `pixels`), not as zero error.
    let errors = ps::angular_errors(normals, &truth, mask)
        .context("no pixel has both an estimated and a true normal")?;
    report["mean_angular_error_deg"] = errors.mean_deg.into();
    report["median_angular_error_deg"] = errors.median_deg.into();
    report["p95_angular_error_deg"] = errors.p95_deg.into();
    report["compared_pixels"] = errors.pixels.into();
    Ok(())
}

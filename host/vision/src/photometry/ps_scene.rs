//! A rendered photometric-stereo test scene with known normals: a large sphere and a small sphere
//! floating in front of it (which casts shadows on it), coloured Lambertian albedo plus a strong
//! Blinn-Phong highlight, distant lights of slightly different colours, noise and 16-bit
//! quantisation, saturation at 1. It has every failure mode robust photometric stereo must handle:
//! attached and cast shadows, highlights, saturated pixels.
//!
//! Conventions (those of DiLiGenT, so the same reader works on both)
//! - Orthographic camera looking along -z; frame: x right, y up, z towards the camera.
//! - Pixel (px, py), origin top-left, row py going down: x = (px - cx) / scale, y = (cy - py) / scale.
//! - Light directions point from the surface to the light; normals point out of the surface.

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

use super::mat_file::{self, MatArray};

/// Errors writing a scene folder.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    /// A file could not be written.
    #[error("{path}: {reason}")]
    Write { path: PathBuf, reason: String },
}

/// What to render.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneParams {
    pub width: u32,
    pub height: u32,
    pub lights: usize,
    pub seed: u64,
    /// Blinn-Phong specular weight (0 for a purely Lambertian scene).
    pub specular: f64,
    /// Standard deviation of additive Gaussian noise (linear units).
    pub noise: f64,
}

impl Default for SceneParams {
    fn default() -> Self {
        Self {
            width: 128,
            height: 128,
            lights: 12,
            seed: 1,
            specular: 0.8,
            noise: 0.002,
        }
    }
}

/// A rendered scene and its truth.
#[derive(Debug, Clone)]
pub struct Scene {
    /// One linear image per light, values in [0, 1].
    pub images: Vec<Rgb32FImage>,
    /// Unit light directions.
    pub directions: Vec<Vector3<f64>>,
    /// Per-light RGB intensities.
    pub intensities: Vec<[f64; 3]>,
    /// True unit normals (zero off the objects).
    pub normals: Rgb32FImage,
    /// True RGB albedo (zero off the objects).
    pub albedo: Rgb32FImage,
    /// Row-major: pixel on an object.
    pub mask: Vec<bool>,
}

struct Sphere {
    centre: Vector3<f64>,
    radius: f64,
}

impl Sphere {
    /// Nearest-to-camera hit of the vertical ray through (x, y), as the hit's z.
    fn hit_from_camera(&self, x: f64, y: f64) -> Option<f64> {
        let d2 = (x - self.centre.x).powi(2) + (y - self.centre.y).powi(2);
        let r2 = self.radius * self.radius;
        (d2 < r2).then(|| self.centre.z + (r2 - d2).sqrt())
    }

    /// Whether the ray from `origin` along unit `dir` hits the sphere in front of the origin.
    fn blocks(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> bool {
        let oc = origin - self.centre;
        let b = oc.dot(dir);
        let c = oc.norm_squared() - self.radius * self.radius;
        let disc = b * b - c;
        disc > 0.0 && -b + disc.sqrt() > 1e-6 && (-b - disc.sqrt() > 1e-6 || c < 0.0)
    }
}

/// Light directions spread over a cone of 15-55 degrees around the view axis, golden-angle
/// azimuths; intensities within +-20% per channel.
fn lights<R: Rng>(count: usize, rng: &mut R) -> (Vec<Vector3<f64>>, Vec<[f64; 3]>) {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut dirs = Vec::with_capacity(count);
    let mut intens = Vec::with_capacity(count);
    for i in 0..count {
        let t = (i as f64 + 0.5) / count as f64;
        let polar = (15.0 + 40.0 * t).to_radians();
        let azimuth = golden * i as f64;
        dirs.push(Vector3::new(
            polar.sin() * azimuth.cos(),
            polar.sin() * azimuth.sin(),
            polar.cos(),
        ));
        intens.push([0; 3].map(|_| rng.gen_range(0.8..1.2)));
    }
    (dirs, intens)
}

/// Renders the scene.
pub fn render(params: &SceneParams) -> Scene {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(params.seed);
    let (directions, intensities) = lights(params.lights, &mut rng);
    let (w, h) = (params.width, params.height);
    let scale = 0.45 * w.min(h) as f64;
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let big = Sphere {
        centre: Vector3::zeros(),
        radius: 1.0,
    };
    let small = Sphere {
        centre: Vector3::new(0.45, 0.4, 1.3),
        radius: 0.28,
    };
    let n = (w * h) as usize;
    let mut normals = vec![0f32; n * 3];
    let mut albedos = vec![0f32; n * 3];
    let mut mask = vec![false; n];
    let mut images = vec![vec![0f32; n * 3]; params.lights];
    for p in 0..n {
        let (px, py) = ((p % w as usize) as f64, (p / w as usize) as f64);
        let (x, y) = ((px - cx) / scale, (cy - py) / scale);
        let hits = [(&big, &small), (&small, &big)]
            .into_iter()
            .filter_map(|(on, other)| on.hit_from_camera(x, y).map(|z| (z, on, other)))
            .max_by(|a, b| a.0.total_cmp(&b.0));
        let Some((z, on, other)) = hits else {
            continue;
        };
        let point = Vector3::new(x, y, z);
        let normal = (point - on.centre) / on.radius;
        // Smoothly varying coloured albedo (skin-like on the big sphere, bluish on the small one).
        let base = if std::ptr::eq(on, &big) {
            [0.75, 0.5, 0.4]
        } else {
            [0.35, 0.45, 0.6]
        };
        let texture = 0.8 + 0.2 * (6.0 * x).sin() * (5.0 * y).cos();
        let albedo = base.map(|b| b * texture);
        mask[p] = true;
        for c in 0..3 {
            normals[p * 3 + c] = normal[c] as f32;
            albedos[p * 3 + c] = albedo[c] as f32;
        }
        let view = Vector3::z();
        for (k, (dir, inten)) in directions.iter().zip(&intensities).enumerate() {
            let cosine = normal.dot(dir);
            if cosine <= 0.0 || other.blocks(&point, dir) {
                continue;
            }
            let half = (dir + view).normalize();
            let specular = params.specular * normal.dot(&half).max(0.0).powi(80);
            for c in 0..3 {
                images[k][p * 3 + c] = (inten[c] * (albedo[c] * cosine + specular)) as f32;
            }
        }
    }
    let images = images
        .into_iter()
        .map(|mut data| {
            for v in &mut data {
                let noisy = *v as f64 + params.noise * gaussian(&mut rng);
                // 16-bit quantisation and saturation.
                *v = ((noisy.clamp(0.0, 1.0) * 65535.0).round() / 65535.0) as f32;
            }
            Rgb32FImage::from_raw(w, h, data).unwrap_or_else(|| Rgb32FImage::new(w, h))
        })
        .collect();
    let image = |data| Rgb32FImage::from_raw(w, h, data).unwrap_or_else(|| Rgb32FImage::new(w, h));
    Scene {
        images,
        directions,
        intensities,
        normals: image(normals),
        albedo: image(albedos),
        mask,
    }
}

fn gaussian<R: Rng>(rng: &mut R) -> f64 {
    // Box-Muller.
    let u1: f64 = rng.gen_range(f64::EPSILON..1.0);
    let u2: f64 = rng.r#gen();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Writes the scene as an image-set folder that `mlsss normals` reads: `NNN.png` (16-bit RGB),
/// `filenames.txt`, `light_directions.txt`, `light_intensities.txt`, `mask.png`, and the truth as
/// `normal.exr`, `normal.png` (0.5 n + 0.5, 16-bit) and `Normal_gt.mat`.
pub fn write_folder(scene: &Scene, dir: &Path) -> Result<(), SceneError> {
    let fail = |path: &Path, reason: String| SceneError::Write {
        path: path.to_owned(),
        reason,
    };
    std::fs::create_dir_all(dir).map_err(|e| fail(dir, e.to_string()))?;
    let mut names = String::new();
    for (k, img) in scene.images.iter().enumerate() {
        let name = format!("{:03}.png", k + 1);
        let path = dir.join(&name);
        write_png16(&path, img, |v| v).map_err(|e| fail(&path, e))?;
        names.push_str(&name);
        names.push('\n');
    }
    let text = |path: PathBuf, body: String| {
        std::fs::write(&path, body).map_err(|e| fail(&path, e.to_string()))
    };
    text(dir.join("filenames.txt"), names)?;
    let rows = |v: &mut dyn Iterator<Item = [f64; 3]>| {
        v.map(|r| format!("{} {} {}\n", r[0], r[1], r[2]))
            .collect::<String>()
    };
    text(
        dir.join("light_directions.txt"),
        rows(&mut scene.directions.iter().map(|d| [d.x, d.y, d.z])),
    )?;
    text(
        dir.join("light_intensities.txt"),
        rows(&mut scene.intensities.iter().copied()),
    )?;
    let (w, h) = scene.normals.dimensions();
    let mask_path = dir.join("mask.png");
    image::GrayImage::from_fn(w, h, |x, y| {
        image::Luma([if scene.mask[(y * w + x) as usize] {
            255
        } else {
            0
        }])
    })
    .save(&mask_path)
    .map_err(|e| fail(&mask_path, e.to_string()))?;
    let exr = dir.join("normal.exr");
    mlsss_core::imageio::write_exr_rgb(&exr, &scene.normals)
        .map_err(|e| fail(&exr, e.to_string()))?;
    let png = dir.join("normal.png");
    write_png16(&png, &scene.normals, |v| 0.5 * v + 0.5).map_err(|e| fail(&png, e))?;
    let mat = dir.join("Normal_gt.mat");
    mat_file::write_double(&mat, &normals_as_mat(&scene.normals), true)
        .map_err(|e| fail(&mat, e.to_string()))
}

/// The normal image as MATLAB's `H x W x 3` column-major array.
pub fn normals_as_mat(normals: &Rgb32FImage) -> MatArray {
    let (w, h) = normals.dimensions();
    let mut data = vec![0.0; (w * h * 3) as usize];
    for (x, y, p) in normals.enumerate_pixels() {
        for c in 0..3 {
            data[(y + h * x + h * w * c as u32) as usize] = p.0[c] as f64;
        }
    }
    MatArray {
        name: "Normal_gt".into(),
        dims: vec![h as usize, w as usize, 3],
        data,
    }
}

fn write_png16(path: &Path, img: &Rgb32FImage, map: impl Fn(f32) -> f32) -> Result<(), String> {
    let (w, h) = img.dimensions();
    let out: image::ImageBuffer<image::Rgb<u16>, Vec<u16>> =
        image::ImageBuffer::from_fn(w, h, |x, y| {
            image::Rgb(
                img.get_pixel(x, y)
                    .0
                    .map(|v| (map(v).clamp(0.0, 1.0) * 65535.0).round() as u16),
            )
        });
    out.save(path).map_err(|e| e.to_string())
}

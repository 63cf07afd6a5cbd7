//! Normals from photometric stereo combined with the normals of the measured geometry (after
//! Nehab et al. 2005, "Efficiently combining positions and normals for precise 3D geometry"):
//! the geometry carries the low spatial frequencies, photometric stereo the detail.
//!
//! Why: photometric stereo's errors on skin are low-frequency biases (subsurface light that does
//! not follow the cosine law, the specular lobe, the lights' calibration) and, on dark skin,
//! noise; the triangulated points of the Gray-code geometry have neither, but cannot resolve
//! detail finer than the plane-fit window ([`crate::geometry::point_normals`]). So, per pixel,
//!
//! `n = normalise(low(n_geometry) + w (n_ps - low(n_ps)))`,
//!
//! `low` a normalised Gaussian average of the unit normals over the plane-fit window (the
//! crossover: finer than it the points are noise, coarser photometric stereo is biased), and
//! `w` the Wiener weight of the photometric detail, `w = t^2 / (t^2 + v)`: `t^2` the variance of
//! the surface's true detail, `v` the pixel's photometric noise. Neither is known beforehand, so
//! both come from the image (empirical Bayes): the detail's squared size `|n_ps - low(n_ps)|^2`
//! is regressed on a per-pixel noise proxy `q` ([`photometric_noise_proxy`]: the solve's residual
//! carried through its light geometry) as `t^2 + k q`; the intercept is `t^2`, and `v = k q`.
//! A face with pores and wrinkles keeps its detail where the noise allows; a surface with no
//! detail finer than the window (the virtual booth's head) takes the geometry's normals.
//! Where the plane fit is unreliable (silhouettes, depth steps) the pixel keeps its photometric
//! normal; where photometric stereo flagged the pixel (too few lights at grazing incidence) and
//! the fit is reliable, it takes the geometry's normal.
//!
//! Conventions: unit normals in one frame (the world's), row-major per camera pixel, zero where
//! unknown.

use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d_mapped};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::photometric_stereo::{LightModel, LightSample, NormalMap, indices};
use crate::geometry::point_normals::PointNormals;

/// How the two kinds of normals are combined.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FusionParams {
    /// Crossover, camera pixels: frequencies below it come from the geometry. The plane fit's
    /// own window is the natural choice.
    pub crossover_sigma_px: f64,
}

impl Default for FusionParams {
    fn default() -> Self {
        Self {
            crossover_sigma_px: 1.5,
        }
    }
}

/// Where the fused normals came from, and the detail model fitted to the image.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct FusionSummary {
    /// Geometry's low frequencies with weighted photometric detail.
    pub fused: u64,
    /// Photometric normal kept (the plane fit was unreliable).
    pub photometric_only: u64,
    /// Geometry's normal where photometric stereo flagged the pixel.
    pub filled_from_geometry: u64,
    /// RMS of the surface's detail finer than the crossover, degrees (the regression's `t`;
    /// null when the image could not tell detail from noise and kept all of it).
    pub detail_rms_deg: Option<f64>,
    /// Mean Wiener weight of the photometric detail over the fused pixels.
    pub detail_weight_mean: f64,
}

/// The fused normals and where they came from.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedNormals {
    pub normals: Vec<[f32; 3]>,
    pub summary: FusionSummary,
}

/// Errors of the fusion.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FusionError {
    /// The photometric normals, their noise proxies and the geometry's normals differ in size.
    #[error("{what} holds {got} pixels, the geometry's normals {expected}")]
    Size {
        what: &'static str,
        got: usize,
        expected: usize,
    },
}

/// Fuses photometric normals `photometric` (with each pixel's noise proxy `noise`,
/// [`photometric_noise_proxy`]) with the geometry's normals `geometry`, all of one camera image.
pub fn fuse_normals(
    photometric: &[[f32; 3]],
    noise: &[f64],
    geometry: &PointNormals,
    params: &FusionParams,
) -> Result<FusedNormals, FusionError> {
    let expected = geometry.normals.len();
    for (what, got) in [
        ("the photometric normal map", photometric.len()),
        ("the noise proxies", noise.len()),
    ] {
        if got != expected {
            return Err(FusionError::Size {
                what,
                got,
                expected,
            });
        }
    }
    let (w, h) = (geometry.width as usize, geometry.height as usize);
    let low_ps = low_pass(photometric, w, h, params.crossover_sigma_px);
    let low_geometry = low_pass(&geometry.normals, w, h, params.crossover_sigma_px);
    let fused_pixel =
        |i: usize| is_normal(photometric[i]) && geometry.reliable[i] && !noise[i].is_nan();
    let detail: Vec<(f64, f64)> = (0..expected)
        .filter(|&i| fused_pixel(i) && noise[i].is_finite())
        .map(|i| (noise[i], squared_distance(photometric[i], low_ps[i])))
        .collect();
    let model = DetailModel::fit(&detail);
    let mut summary = FusionSummary {
        detail_rms_deg: model
            .detail_variance
            .is_finite()
            .then(|| model.detail_variance.sqrt().to_degrees()),
        ..FusionSummary::default()
    };
    let mut weight_sum = 0.0;
    let normals = (0..expected)
        .map(|i| {
            let ps = photometric[i];
            if fused_pixel(i) {
                let weight = model.weight(noise[i]);
                weight_sum += weight;
                summary.fused += 1;
                add_detail(low_geometry[i], ps, low_ps[i], weight)
            } else if is_normal(ps) {
                summary.photometric_only += 1;
                ps
            } else if geometry.reliable[i] {
                summary.filled_from_geometry += 1;
                geometry.normals[i]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    summary.detail_weight_mean = weight_sum / summary.fused.max(1) as f64;
    Ok(FusedNormals { normals, summary })
}

/// Photometric detail as true detail plus noise: `E|detail|^2 = t^2 + k q` over pixels of noise
/// proxy `q`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DetailModel {
    /// `t^2`, rad^2 (infinite: detail could not be told from noise, all of it is kept).
    detail_variance: f64,
    /// `k`: noise variance per unit of the proxy.
    noise_per_proxy: f64,
}

/// Noise-proxy bins of the detail regression (equal pixel counts).
const DETAIL_BINS: usize = 10;

impl DetailModel {
    /// Keeps all photometric detail, as photometric stereo alone would.
    const KEEP_ALL: Self = Self {
        detail_variance: f64::INFINITY,
        noise_per_proxy: 0.0,
    };

    /// The least-squares line through the mean squared detail of [`DETAIL_BINS`] bins of equal
    /// pixel count ordered by noise proxy (binning keeps the few noisiest pixels from steering
    /// the line). Without spread in the proxy the noise cannot be told from detail: all detail
    /// is kept.
    fn fit(samples: &[(f64, f64)]) -> Self {
        if samples.len() < 2 * DETAIL_BINS {
            return Self::KEEP_ALL;
        }
        let mut sorted = samples.to_vec();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
        let bins: Vec<(f64, f64)> = sorted
            .chunks(sorted.len().div_ceil(DETAIL_BINS))
            .map(|bin| {
                let n = bin.len() as f64;
                (
                    bin.iter().map(|s| s.0).sum::<f64>() / n,
                    bin.iter().map(|s| s.1).sum::<f64>() / n,
                )
            })
            .collect();
        let n = bins.len() as f64;
        let mean_q = bins.iter().map(|b| b.0).sum::<f64>() / n;
        let mean_d = bins.iter().map(|b| b.1).sum::<f64>() / n;
        let spread: f64 = bins.iter().map(|b| (b.0 - mean_q).powi(2)).sum();
        if !(spread > 1e-12 * mean_q * mean_q && spread.is_finite()) {
            return Self::KEEP_ALL;
        }
        let slope = bins
            .iter()
            .map(|b| (b.0 - mean_q) * (b.1 - mean_d))
            .sum::<f64>()
            / spread;
        let noise_per_proxy = slope.max(0.0);
        Self {
            detail_variance: (mean_d - noise_per_proxy * mean_q).max(0.0),
            noise_per_proxy,
        }
    }

    /// The Wiener weight of the detail at a pixel of noise proxy `q`.
    fn weight(&self, q: f64) -> f64 {
        let noise = self.noise_per_proxy * q.max(0.0);
        if self.detail_variance.is_infinite() || noise <= 0.0 {
            return if self.detail_variance > 0.0 { 1.0 } else { 0.0 };
        }
        self.detail_variance / (self.detail_variance + noise)
    }
}

/// Lights a photometric solve must have used for its residual to say anything about its error.
/// With 3 lights (9 readings for 6 unknowns) it fits almost any reading, a shadowed or specular
/// one included: on a type VI head (seed 81) its pixels erred by 9.3 deg on average against 3.7
/// with 4 lights, at no higher residual. Its detail is not kept (infinite noise proxy).
pub const MIN_LIGHTS_FOR_DETAIL: u32 = 4;

/// Each photometric normal's noise proxy (a variance up to a scale common to the image, rad^2;
/// NaN where photometric stereo flagged the pixel, infinite where it used fewer than
/// [`MIN_LIGHTS_FOR_DETAIL`] lights): the solve's relative RMS residual, corrected
/// for the unknowns it fitted, carried through the used lights' geometry as in least squares,
/// `q = r^2 m / (m - p) (max_k E_k n.l_k)^2 tr((A^T A)^-1)`, with `A` the rows `E_k l_k` of the
/// used lights (green irradiance), `m` the readings (3 per light) and `p` = 6 unknowns (normal,
/// RGB albedo, specular weight). The residual holds the camera's noise and the model's misfit
/// alike; the scale between `q` and a variance is fitted per image ([`fuse_normals`]).
pub fn photometric_noise_proxy(map: &NormalMap, lights: &dyn LightModel) -> Vec<f64> {
    const UNKNOWNS: f64 = 6.0;
    let blank = LightSample {
        direction: Vector3::zeros(),
        irradiance: [0.0; 3],
    };
    let width = map.width.max(1) as usize;
    map.pixels
        .par_iter()
        .enumerate()
        .map_init(
            || vec![blank; lights.count()],
            |samples, (i, p)| {
                let n = Vector3::from(p.normal.map(f64::from));
                let (x, y) = ((i % width) as u32, (i / width) as u32);
                if n == Vector3::zeros() || lights.at(x, y, samples).is_none() {
                    return f64::NAN;
                }
                let mut normal_matrix = Matrix3::zeros();
                let mut brightest: f64 = 0.0;
                for sample in indices(p.used).filter_map(|k| samples.get(k)) {
                    let row = sample.direction * sample.irradiance[1];
                    normal_matrix += row * row.transpose();
                    brightest = brightest.max(row.dot(&n));
                }
                let Some(inverse) = normal_matrix.try_inverse() else {
                    return f64::NAN;
                };
                if p.lights_used() < MIN_LIGHTS_FOR_DETAIL {
                    return f64::INFINITY;
                }
                let readings = 3.0 * f64::from(p.lights_used());
                let residual = f64::from(p.residual);
                residual * residual * readings / (readings - UNKNOWNS).max(1.0)
                    * brightest
                    * brightest
                    * inverse.trace()
            },
        )
        .collect()
}

/// `|a - b|^2`.
fn squared_distance(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3)
        .map(|c| (f64::from(a[c]) - f64::from(b[c])).powi(2))
        .sum()
}

fn is_normal(n: [f32; 3]) -> bool {
    n.iter().all(|v| v.is_finite()) && n.iter().any(|v| *v != 0.0)
}

/// `normalise(base + weight (n - low))`, or `base` if that vanishes.
fn add_detail(base: [f32; 3], n: [f32; 3], low: [f32; 3], weight: f64) -> [f32; 3] {
    let v: [f64; 3] = std::array::from_fn(|c| {
        f64::from(base[c]) + weight * (f64::from(n[c]) - f64::from(low[c]))
    });
    normalise(v).unwrap_or(base)
}

fn normalise(v: [f64; 3]) -> Option<[f32; 3]> {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (len > 1e-12 && len.is_finite()).then(|| v.map(|c| (c / len) as f32))
}

/// The Gaussian average of the known unit normals around each pixel (unknown ones carry no
/// weight), normalised; zero where no normal is within reach.
fn low_pass(normals: &[[f32; 3]], width: usize, height: usize, sigma: f64) -> Vec<[f32; 3]> {
    if normals.len() != width * height {
        return vec![[0.0; 3]; normals.len()];
    }
    let sums = |i: usize| {
        let n = normals[i];
        if is_normal(n) {
            [n[0].into(), n[1].into(), n[2].into(), 1.0]
        } else {
            [0.0; 4]
        }
    };
    let kernel = GaussianKernel::new(sigma, 3.0, Normalisation::Weights);
    // On every core, band by band (the same numbers as on one thread): it was the fusion's
    // serial stretch, and the whole field of sums fresh memory.
    blur_2d_mapped(
        width,
        height,
        &kernel,
        Border::Zero,
        sums,
        |_, s: [f64; 4]| normalise([s[0], s[1], s[2]]).unwrap_or([0.0; 3]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    const W: usize = 48;
    const H: usize = 32;

    fn unit(v: [f64; 3]) -> [f32; 3] {
        normalise(v).expect("non-zero")
    }

    fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
        let d: f64 = (0..3).map(|c| f64::from(a[c]) * f64::from(b[c])).sum();
        d.clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// The slow tilt across x the geometry sees.
    fn slow(u: usize) -> f64 {
        0.4 * (u as f64 / W as f64 - 0.5)
    }

    /// A surface with the slow tilt and a fine ripple along y of amplitude `ripple` (rad) and a
    /// 4-pixel period: detail no 1.5-px plane fit resolves.
    fn truth(u: usize, v: usize, ripple: f64) -> [f32; 3] {
        let r = ripple * (std::f64::consts::TAU * v as f64 / 4.0).sin();
        unit([slow(u), r, 1.0])
    }

    fn pixels() -> impl Iterator<Item = (usize, usize)> {
        (0..H).flat_map(|v| (0..W).map(move |u| (u, v)))
    }

    fn geometry(reliable: impl Fn(usize, usize) -> bool) -> PointNormals {
        // The geometry sees the slow tilt exactly and none of the ripple.
        PointNormals {
            width: W as u32,
            height: H as u32,
            normals: pixels().map(|(u, _)| unit([slow(u), 0.0, 1.0])).collect(),
            reliable: pixels().map(|(u, v)| reliable(u, v)).collect(),
        }
    }

    /// A noise proxy that varies over the image (0.2-2 x `scale`), as a real solve's does.
    fn noise_proxy(scale: f64) -> Vec<f64> {
        pixels()
            .map(|(u, v)| scale * (0.2 + 1.8 * ((u * 7 + v * 13) % 10) as f64 / 9.0))
            .collect()
    }

    /// Photometric normals: the truth tilted by a constant `bias` (rad) about the y axis, plus,
    /// per pixel, noise of variance `q` (rad^2) from `proxy` when `noisy`.
    fn photometric(ripple: f64, bias: f64, proxy: &[f64], noisy: bool) -> Vec<[f32; 3]> {
        let mut rng = Pcg64::seed_from_u64(7);
        pixels()
            .zip(proxy)
            .map(|((u, v), q)| {
                let t = truth(u, v, ripple);
                let (s, c) = bias.sin_cos();
                let (x, z) = (f64::from(t[0]), f64::from(t[2]));
                let mut n = [c * x + s * z, f64::from(t[1]), -s * x + c * z];
                if noisy {
                    // Gaussian noise (Box-Muller) of variance q/2 per tangent axis.
                    for axis in [0, 1] {
                        let (a, b): (f64, f64) = (rng.r#gen(), rng.r#gen());
                        let g = (-2.0 * (1.0 - a).ln()).sqrt() * (std::f64::consts::TAU * b).cos();
                        n[axis] += g * (q / 2.0).sqrt();
                    }
                }
                unit(n)
            })
            .collect()
    }

    fn mean_error(normals: &[[f32; 3]], ripple: f64) -> f64 {
        let inside: Vec<f64> = pixels()
            .filter(|&(u, v)| (6..W - 6).contains(&u) && (6..H - 6).contains(&v))
            .map(|(u, v)| angle_deg(normals[v * W + u], truth(u, v, ripple)))
            .collect();
        inside.iter().sum::<f64>() / inside.len() as f64
    }

    #[test]
    fn a_photometric_bias_is_removed_and_clean_detail_kept() {
        let (ripple, proxy) = (0.08, noise_proxy(1e-4));
        let ps = photometric(ripple, 5f64.to_radians(), &proxy, false);
        let geo = geometry(|_, _| true);
        let fused = fuse_normals(&ps, &proxy, &geo, &FusionParams::default()).expect("same sizes");
        let before = mean_error(&ps, ripple);
        let geometry_alone = mean_error(&geo.normals, ripple);
        let after = mean_error(&fused.normals, ripple);
        // The 5-degree bias is the photometric error, the missing ripple (up to 4.6 deg) the
        // geometry's; noiseless detail is kept whole.
        assert!((before - 5.0).abs() < 0.1, "photometric {before}");
        assert!(geometry_alone > 2.0, "geometry {geometry_alone}");
        assert!(
            after < 0.5 * geometry_alone,
            "fused {after}, geometry {geometry_alone}"
        );
        assert!(
            fused.summary.detail_weight_mean > 0.99,
            "{:?}",
            fused.summary
        );
        assert_eq!(fused.summary.fused, (W * H) as u64);
    }

    #[test]
    fn noise_without_detail_is_dropped_and_its_size_read_from_the_image() {
        let proxy = noise_proxy(1e-4);
        // Noise of 0.6 deg RMS on average, no true detail.
        let ps = photometric(0.0, 5f64.to_radians(), &proxy, true);
        let geo = geometry(|_, _| true);
        let fused = fuse_normals(&ps, &proxy, &geo, &FusionParams::default()).expect("same sizes");
        let (before, after) = (mean_error(&ps, 0.0), mean_error(&fused.normals, 0.0));
        assert!(before > 4.5, "photometric {before}");
        assert!(after < 0.15, "fused {after}");
        let s = fused.summary;
        assert!(s.detail_rms_deg.is_some_and(|t| t < 0.2), "{s:?}");
        assert!(s.detail_weight_mean < 0.1, "{s:?}");
    }

    #[test]
    fn detail_under_noise_is_weighted_by_the_pixels_noise() {
        // Ripple of 1.6 deg RMS under noise of 0.5-1.6 deg RMS: neither source alone is right.
        let (ripple, proxy) = (0.04, noise_proxy(4e-4));
        let ps = photometric(ripple, 0.0, &proxy, true);
        let geo = geometry(|_, _| true);
        let fused = fuse_normals(&ps, &proxy, &geo, &FusionParams::default()).expect("same sizes");
        let (photometric_alone, geometry_alone) =
            (mean_error(&ps, ripple), mean_error(&geo.normals, ripple));
        let after = mean_error(&fused.normals, ripple);
        assert!(
            after < 0.9 * photometric_alone.min(geometry_alone),
            "fused {after}, photometric {photometric_alone}, geometry {geometry_alone}"
        );
        // The ripple's RMS over the 4-pixel period: 0.04 / sqrt(2) rad, 1.6 deg (read after
        // the crossover's low-pass, which keeps 94 % of it).
        let t = fused.summary.detail_rms_deg.expect("a detail size");
        assert!((t - 1.55).abs() < 0.3, "{:?}", fused.summary);
    }

    #[test]
    fn each_pixel_takes_the_source_its_flags_allow() {
        let proxy = noise_proxy(1e-4);
        let mut ps = photometric(0.0, 5f64.to_radians(), &proxy, false);
        // Column 10: photometric stereo flagged; column 30: the plane fit is unreliable there.
        for v in 0..H {
            ps[v * W + 10] = [0.0; 3];
        }
        let geo = geometry(|u, _| u != 30);
        let fused = fuse_normals(&ps, &proxy, &geo, &FusionParams::default()).expect("same sizes");
        for v in 0..H {
            assert_eq!(fused.normals[v * W + 10], geo.normals[v * W + 10]);
            assert_eq!(fused.normals[v * W + 30], ps[v * W + 30]);
        }
        let s = fused.summary;
        assert_eq!(s.filled_from_geometry, H as u64);
        assert_eq!(s.photometric_only, H as u64);
        assert_eq!(s.fused, (W * H - 2 * H) as u64);
    }

    #[test]
    fn maps_of_different_sizes_are_refused() {
        let geo = geometry(|_, _| true);
        let err = fuse_normals(&[[0.0; 3]; 3], &[1e-4; 3], &geo, &FusionParams::default());
        assert!(matches!(err, Err(FusionError::Size { got: 3, .. })));
    }
}

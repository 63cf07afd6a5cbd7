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
//! crossover: finer than it the points are noise, coarser photometric stereo is biased), `w` 1
//! where the photometric solve had a light to spare (at least [`FusionParams::min_detail_lights`]
//! used; with fewer it could not reject a shadowed or specular reading, and its detail is mostly
//! noise) and 0 otherwise. Where the plane fit is unreliable (silhouettes, depth steps) the pixel
//! keeps its photometric normal; where photometric stereo flagged the pixel (too few lights at
//! grazing incidence) and the fit is reliable, it takes the geometry's normal.
//!
//! Conventions: unit normals in one frame (the world's), row-major per camera pixel, zero where
//! unknown.

use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d};

use crate::geometry::point_normals::PointNormals;

/// How the two kinds of normals are combined.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FusionParams {
    /// Crossover, camera pixels: frequencies below it come from the geometry. The plane fit's
    /// own window is the natural choice.
    pub crossover_sigma_px: f64,
    /// Lights a photometric solve must have used for its detail to be kept.
    pub min_detail_lights: u32,
}

impl Default for FusionParams {
    fn default() -> Self {
        Self {
            crossover_sigma_px: 1.5,
            min_detail_lights: 4,
        }
    }
}

/// Where each fused normal came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct FusionCounts {
    /// Geometry's low frequencies with photometric detail.
    pub fused_with_detail: u64,
    /// Geometry's low frequencies alone (the photometric solve had no light to spare).
    pub geometry_smoothed: u64,
    /// Photometric normal kept (the plane fit was unreliable).
    pub photometric_only: u64,
    /// Geometry's normal where photometric stereo flagged the pixel.
    pub filled_from_geometry: u64,
}

/// The fused normals and where they came from.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedNormals {
    pub normals: Vec<[f32; 3]>,
    pub counts: FusionCounts,
}

/// Errors of the fusion.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FusionError {
    /// The photometric normals, their light counts and the geometry's normals differ in size.
    #[error("{what} holds {got} pixels, the geometry's normals {expected}")]
    Size {
        what: &'static str,
        got: usize,
        expected: usize,
    },
}

/// Fuses photometric normals `photometric` (with the number of lights each used,
/// `lights_used`) with the geometry's normals `geometry`, all of one camera image.
pub fn fuse_normals(
    photometric: &[[f32; 3]],
    lights_used: &[u32],
    geometry: &PointNormals,
    params: &FusionParams,
) -> Result<FusedNormals, FusionError> {
    let expected = geometry.normals.len();
    for (what, got) in [
        ("the photometric normal map", photometric.len()),
        ("the light counts", lights_used.len()),
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
    let mut counts = FusionCounts::default();
    let normals = (0..expected)
        .map(|i| {
            let ps = photometric[i];
            let solved = is_normal(ps);
            let (fused, source) = match (solved, geometry.reliable[i]) {
                (true, true) if lights_used[i] >= params.min_detail_lights => (
                    add_detail(low_geometry[i], ps, low_ps[i]),
                    &mut counts.fused_with_detail,
                ),
                (true, true) => (low_geometry[i], &mut counts.geometry_smoothed),
                (true, false) => (ps, &mut counts.photometric_only),
                (false, true) => (geometry.normals[i], &mut counts.filled_from_geometry),
                (false, false) => return [0.0; 3],
            };
            *source += 1;
            fused
        })
        .collect();
    Ok(FusedNormals { normals, counts })
}

fn is_normal(n: [f32; 3]) -> bool {
    n.iter().all(|v| v.is_finite()) && n.iter().any(|v| *v != 0.0)
}

/// `normalise(base + (n - low))`, or `base` if that vanishes.
fn add_detail(base: [f32; 3], n: [f32; 3], low: [f32; 3]) -> [f32; 3] {
    let v: [f64; 3] =
        std::array::from_fn(|c| f64::from(base[c]) + f64::from(n[c]) - f64::from(low[c]));
    normalise(v).unwrap_or(base)
}

fn normalise(v: [f64; 3]) -> Option<[f32; 3]> {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (len > 1e-12 && len.is_finite()).then(|| v.map(|c| (c / len) as f32))
}

/// The Gaussian average of the known unit normals around each pixel (unknown ones carry no
/// weight), normalised; zero where no normal is within reach.
fn low_pass(normals: &[[f32; 3]], width: usize, height: usize, sigma: f64) -> Vec<[f32; 3]> {
    let mut sums: Vec<[f64; 4]> = normals
        .iter()
        .map(|n| {
            if is_normal(*n) {
                [n[0].into(), n[1].into(), n[2].into(), 1.0]
            } else {
                [0.0; 4]
            }
        })
        .collect();
    let kernel = GaussianKernel::new(sigma, 3.0, Normalisation::Weights);
    if blur_2d(&mut sums, width, height, &kernel, Border::Zero).is_err() {
        return vec![[0.0; 3]; normals.len()];
    }
    sums.iter()
        .map(|s| normalise([s[0], s[1], s[2]]).unwrap_or([0.0; 3]))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 48;
    const H: usize = 32;

    fn unit(v: [f64; 3]) -> [f32; 3] {
        normalise(v).expect("non-zero")
    }

    fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
        let d: f64 = (0..3).map(|c| f64::from(a[c]) * f64::from(b[c])).sum();
        d.clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// A surface whose normal tilts slowly across x (low frequency) with a fine ripple along
    /// y (a 4-pixel period: detail no 1.5-px plane fit resolves).
    fn truth(u: usize, v: usize) -> [f32; 3] {
        let slow = 0.4 * (u as f64 / W as f64 - 0.5);
        let ripple = 0.08 * (std::f64::consts::TAU * v as f64 / 4.0).sin();
        unit([slow, ripple, 1.0])
    }

    fn geometry(reliable: impl Fn(usize, usize) -> bool) -> PointNormals {
        // The geometry sees the slow tilt exactly and none of the ripple.
        let mut normals = Vec::new();
        let mut flags = Vec::new();
        for v in 0..H {
            for u in 0..W {
                normals.push(unit([0.4 * (u as f64 / W as f64 - 0.5), 0.0, 1.0]));
                flags.push(reliable(u, v));
            }
        }
        PointNormals {
            width: W as u32,
            height: H as u32,
            normals,
            reliable: flags,
        }
    }

    /// Photometric normals: the truth tilted by a constant bias of `bias` about the y axis.
    fn photometric(bias: f64) -> Vec<[f32; 3]> {
        (0..H)
            .flat_map(|v| (0..W).map(move |u| (u, v)))
            .map(|(u, v)| {
                let t = truth(u, v);
                let (s, c) = bias.sin_cos();
                let (x, z) = (f64::from(t[0]), f64::from(t[2]));
                unit([c * x + s * z, f64::from(t[1]), -s * x + c * z])
            })
            .collect()
    }

    fn mean_error(normals: &[[f32; 3]], pixels: impl Iterator<Item = (usize, usize)>) -> f64 {
        let errors: Vec<f64> = pixels
            .map(|(u, v)| angle_deg(normals[v * W + u], truth(u, v)))
            .collect();
        errors.iter().sum::<f64>() / errors.len() as f64
    }

    fn interior() -> impl Iterator<Item = (usize, usize)> {
        (6..H - 6).flat_map(|v| (6..W - 6).map(move |u| (u, v)))
    }

    #[test]
    fn a_photometric_bias_is_removed_and_its_detail_kept() {
        let bias = 5f64.to_radians();
        let ps = photometric(bias);
        let geo = geometry(|_, _| true);
        let fused =
            fuse_normals(&ps, &vec![4; W * H], &geo, &FusionParams::default()).expect("same sizes");
        let before = mean_error(&ps, interior());
        let geometry_alone = mean_error(&geo.normals, interior());
        let after = mean_error(&fused.normals, interior());
        // The 5-degree bias is the photometric error, the missing ripple (up to 4.6 deg) the
        // geometry's; the fusion keeps the ripple's part above the crossover.
        assert!((before - 5.0).abs() < 0.1, "photometric {before}");
        assert!(geometry_alone > 2.0, "geometry {geometry_alone}");
        assert!(
            after < 0.5 * geometry_alone,
            "fused {after}, geometry {geometry_alone}"
        );
        assert_eq!(fused.counts.fused_with_detail, (W * H) as u64);
    }

    #[test]
    fn each_pixel_takes_the_source_its_flags_allow() {
        let ps_bias = 5f64.to_radians();
        let mut ps = photometric(ps_bias);
        let mut lights = vec![4u32; W * H];
        // Column 10: photometric stereo flagged; column 20: only 3 lights; column 30: the
        // plane fit is unreliable there.
        for v in 0..H {
            ps[v * W + 10] = [0.0; 3];
            lights[v * W + 10] = 0;
            lights[v * W + 20] = 3;
        }
        let geo = geometry(|u, _| u != 30);
        let fused = fuse_normals(&ps, &lights, &geo, &FusionParams::default()).expect("same sizes");
        for v in 6..H - 6 {
            assert_eq!(fused.normals[v * W + 10], geo.normals[v * W + 10]);
            assert_eq!(fused.normals[v * W + 30], ps[v * W + 30]);
            // Only 3 lights: the geometry's low frequencies, no photometric bias.
            let e = angle_deg(fused.normals[v * W + 20], geo.normals[v * W + 20]);
            assert!(e < 0.5, "row {v}: {e} deg from the geometry's");
        }
        let c = fused.counts;
        assert_eq!(c.filled_from_geometry, H as u64);
        assert_eq!(c.photometric_only, H as u64);
        assert_eq!(c.geometry_smoothed, H as u64);
        assert_eq!(c.fused_with_detail, (W * H - 3 * H) as u64);
    }

    #[test]
    fn maps_of_different_sizes_are_refused() {
        let geo = geometry(|_, _| true);
        let err = fuse_normals(&[[0.0; 3]; 3], &[4; 3], &geo, &FusionParams::default());
        assert!(matches!(err, Err(FusionError::Size { got: 3, .. })));
    }
}

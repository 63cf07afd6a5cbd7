//! Relighting under a projector (held out or not): the irradiance of its pattern on the surface,
//! the direct part from a per-pixel direct albedo, and the subsurface part from the layer model.
//!
//! Conventions as in [`super::profiles`] (irradiance units, projector coordinates).

use nalgebra::Vector3;
use rayon::prelude::*;

use super::profiles::{ProjectorIllumination, irradiance};
use super::render::{LayerModel, RenderError, RenderOptions, render_global_many};
use super::surface::{Surface, ViewRay, shift_per_depth};
use mlsss_core::capture::{Axis, Pattern};

/// Pattern level seen at projector coordinate `(u, v)`: the pattern's pixels (boxes centred at
/// integers) integrated against a Gaussian of `blur_px` (projector defocus and the camera pixel's
/// footprint); with no blur, the pattern at the nearest projector pixel.
pub fn pattern_level(pattern: &Pattern, u: f32, v: f32, blur_px: f32) -> f32 {
    let at = |pu: i64, pv: i64| pattern.value(pu.max(0) as u32, pv.max(0) as u32);
    let (ru, rv) = (u.round() as i64, v.round() as i64);
    if blur_px <= 1e-3 {
        return at(ru, rv);
    }
    // Every pattern varies along one axis at most: integrate along that axis only.
    let along_u = match *pattern {
        Pattern::White | Pattern::Black | Pattern::Grey { .. } => return at(ru, rv),
        Pattern::Gray { axis, .. } | Pattern::Slit { axis, .. } => axis == Axis::X,
        Pattern::HighFrequency { .. } => true,
    };
    let (c, centre) = if along_u { (u, ru) } else { (v, rv) };
    let value = |j: i64| if along_u { at(j, rv) } else { at(ru, j) };
    let radius = (3.0 * blur_px).ceil() as i64 + 1;
    let pixels = centre - radius..=centre + radius;
    // Dark across the blur's reach (most pixels under a slit): the sum below would be zero.
    if pixels.clone().all(|j| value(j) == 0.0) {
        return 0.0;
    }
    let sigma = f64::from(blur_px) * std::f64::consts::SQRT_2;
    // Pixel j's weight is the Gaussian's mass over [j - 1/2, j + 1/2], half the difference of
    // erf at its edges; neighbours share an edge, whose erf is computed once.
    let edge = |j: i64| mlsss_core::special::erf((j as f64 - 0.5 - f64::from(c)) / sigma);
    let mut below = edge(centre - radius);
    let mut level = 0.0f64;
    for j in pixels {
        let above = edge(j + 1);
        level += 0.5 * (above - below) * f64::from(value(j));
        below = above;
    }
    level as f32
}

/// Per-pixel irradiance of `view` showing `pattern` (0 where the projector does not reach), with
/// the projector's response: `black + (1 - black) * level` (levels are linear after photometric
/// calibration), the level blurred by `blur_px` (see [`pattern_level`]).
pub fn pattern_irradiance(
    surface: &Surface,
    view: &ProjectorIllumination,
    pattern: &Pattern,
    black_level: f32,
    blur_px: f32,
) -> Vec<f32> {
    // Pixels are independent: split them across threads (same values as in sequence).
    (0..surface.len())
        .into_par_iter()
        .map(|i| {
            let Some((u, v)) = view.coords[i] else {
                return 0.0;
            };
            if !surface.mask[i] {
                return 0.0;
            }
            let level = black_level + (1.0 - black_level) * pattern_level(pattern, u, v, blur_px);
            let e = irradiance(
                &surface.points[i],
                &surface.normals[i],
                &view.centre,
                &view.falloff,
            );
            (f64::from(level) * e) as f32
        })
        .collect()
}

/// `t_i + t_o` per pixel for a light at `centre`.
pub fn shifts(
    surface: &Surface,
    centre: &Vector3<f64>,
    eta: f64,
    view_ray: ViewRay,
) -> Vec<Option<Vector3<f64>>> {
    (0..surface.len())
        .into_par_iter()
        .map(|i| {
            if !surface.mask[i] {
                return None;
            }
            shift_per_depth(
                &surface.points[i],
                &surface.normals[i],
                centre,
                &surface.camera_centre,
                eta,
                view_ray,
            )
        })
        .collect()
}

/// Albedo per pixel and channel of a light component `l` (the direct part, or all light) under
/// white: the least-squares `a` of `l_k = a e_k` over the training projectors `k`, with `e_k` the
/// projector's irradiance, i.e. `sum(l e) / sum(e^2)`; 0 where no projector lights the pixel.
///
/// Why least squares and not the median of the ratios `l_k / e_k` (before): a projector that
/// grazes the surface has an irradiance near zero while its separated direct light (mostly
/// leaked subsurface light) is not, so its ratio is huge; relit under a projector that lights
/// the pixel head-on, such ratios made direct renders several times brighter than the frame
/// (PSNR -11.5 dB on the quick light head, seed 41, with `--direct auto`; 40 dB without a
/// direct part). Least squares weights each projector by its irradiance.
pub fn direct_albedo(white_irradiance: &[Vec<f32>], direct_white: &[&[[f32; 3]]]) -> Vec<[f32; 3]> {
    let n = white_irradiance.first().map_or(0, Vec::len);
    (0..n)
        .map(|i| {
            let mut light_times_irradiance = [0.0f64; 3];
            let mut irradiance_squared = 0.0f64;
            for (e, l) in white_irradiance.iter().zip(direct_white) {
                let e = f64::from(e[i]);
                if !(e > 0.0 && l[i].iter().all(|v| v.is_finite())) {
                    continue;
                }
                irradiance_squared += e * e;
                for (sum, v) in light_times_irradiance.iter_mut().zip(l[i]) {
                    *sum += f64::from(v) * e;
                }
            }
            if irradiance_squared < 1e-12 {
                return [0.0; 3];
            }
            light_times_irradiance.map(|s| (s / irradiance_squared) as f32)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::capture::Axis;

    #[test]
    fn albedo_is_the_least_squares_slope_and_a_grazing_projector_does_not_blow_it_up() {
        // Pixel 0: light 0.2 e exactly. Pixel 1: projector 1 grazes (e = 1e-4) but its
        // separated light is 0.01 (leaked subsurface light): the ratio would be 100.
        let irradiance = vec![vec![1.0, 1.0], vec![0.5, 1e-4], vec![0.25, 0.8]];
        let light: Vec<Vec<[f32; 3]>> = vec![
            vec![[0.2; 3], [0.1; 3]],
            vec![[0.1; 3], [0.01; 3]],
            vec![[0.05; 3], [0.08; 3]],
        ];
        let refs: Vec<&[[f32; 3]]> = light.iter().map(Vec::as_slice).collect();
        let albedo = direct_albedo(&irradiance, &refs);
        assert!((albedo[0][0] - 0.2).abs() < 1e-6, "{:?}", albedo[0]);
        // (0.1 * 1 + 0.01 * 1e-4 + 0.08 * 0.8) / (1 + 1e-8 + 0.64), by hand.
        let expected = (0.1 + 0.01 * 1e-4 + 0.08 * 0.8) / (1.0 + 1e-8 + 0.64);
        assert!(
            (f64::from(albedo[1][2]) - expected).abs() < 1e-6,
            "{:?}",
            albedo[1]
        );
        let unlit = direct_albedo(&[vec![0.0]], &[&[[1.0; 3]]]);
        assert_eq!(unlit, vec![[0.0; 3]]);
    }

    #[test]
    fn blurred_pattern_level_is_the_box_against_a_gaussian() {
        let slit = Pattern::Slit {
            axis: Axis::X,
            width: 3,
            period: 30,
            offset: 10,
        };
        // Unblurred: nearest pixel. Slit on columns 10..=12, edges at 9.5 and 12.5.
        assert_eq!(pattern_level(&slit, 9.6, 0.0, 0.0), 1.0);
        assert_eq!(pattern_level(&slit, 9.4, 0.0, 0.0), 0.0);
        // Blurred: Phi((12.5 - u) / s) - Phi((9.5 - u) / s), exactly (the erf terms telescope).
        for (u, blur) in [(11.0f32, 0.7f32), (9.5, 0.5), (13.2, 1.1)] {
            let phi = |t: f64| 0.5 * (1.0 + libm::erf(t / (f64::from(blur) * 2f64.sqrt())));
            let want = phi(12.5 - f64::from(u)) - phi(9.5 - f64::from(u));
            let got = f64::from(pattern_level(&slit, u, 50.0, blur));
            assert!(
                (got - want).abs() < 1e-5,
                "u {u} blur {blur}: {got} vs {want}"
            );
        }
        // Along y the x coordinate does not matter; white ignores the blur.
        let rows = Pattern::Slit {
            axis: Axis::Y,
            width: 3,
            period: 30,
            offset: 0,
        };
        assert_eq!(
            pattern_level(&rows, 3.0, 1.0, 0.6),
            pattern_level(&rows, 40.0, 1.0, 0.6)
        );
        assert_eq!(pattern_level(&Pattern::White, 3.3, 1.0, 2.0), 1.0);
    }

    /// The pattern level as first written: every pixel's weight from its own two erf values.
    fn pattern_level_reference(pattern: &Pattern, u: f32, v: f32, blur_px: f32) -> f32 {
        let at = |pu: i64, pv: i64| pattern.value(pu.max(0) as u32, pv.max(0) as u32);
        let (ru, rv) = (u.round() as i64, v.round() as i64);
        if blur_px <= 1e-3 {
            return at(ru, rv);
        }
        let radius = (3.0 * blur_px).ceil() as i64 + 1;
        let sigma = f64::from(blur_px) * std::f64::consts::SQRT_2;
        let weights = |c: f32, centre: i64| -> Vec<(i64, f64)> {
            (centre - radius..=centre + radius)
                .map(|j| {
                    let lo = (j as f64 - 0.5 - f64::from(c)) / sigma;
                    let hi = (j as f64 + 0.5 - f64::from(c)) / sigma;
                    let erf = mlsss_core::special::erf;
                    (j, 0.5 * (erf(hi) - erf(lo)))
                })
                .collect()
        };
        let along_u = match *pattern {
            Pattern::White | Pattern::Black | Pattern::Grey { .. } => return at(ru, rv),
            Pattern::Gray { axis, .. } | Pattern::Slit { axis, .. } => axis == Axis::X,
            Pattern::HighFrequency { .. } => true,
        };
        let mut level = 0.0f64;
        if along_u {
            for (j, w) in weights(u, ru) {
                level += w * f64::from(at(j, rv));
            }
        } else {
            for (j, w) in weights(v, rv) {
                level += w * f64::from(at(ru, j));
            }
        }
        level as f32
    }

    /// Shared edges and the dark-window shortcut give the per-pixel weights' level bit for bit,
    /// over every pattern kind, both axes, sub-pixel positions and blurs from none to 3 pixels.
    #[test]
    fn pattern_level_equals_the_per_pixel_weights_bit_for_bit() {
        let mut patterns = vec![Pattern::White, Pattern::Grey { level_milli: 250 }];
        for axis in [Axis::X, Axis::Y] {
            for bit in 0..8 {
                patterns.push(Pattern::Gray {
                    axis,
                    bit,
                    inverted: bit % 2 == 1,
                });
                patterns.push(Pattern::Slit {
                    axis,
                    width: 1 + bit,
                    period: 24,
                    offset: bit,
                });
            }
        }
        patterns.extend((1..5).map(|stripe| Pattern::HighFrequency { stripe, shift: 1 }));
        for pattern in &patterns {
            for i in 0..400 {
                // Positions spread over 200 projector pixels on both axes, blurs over [0, 3).
                let (u, v) = (i as f32 * 0.4993, (400 - i) as f32 * 0.5011);
                let blur = (i % 31) as f32 * 0.097;
                assert_eq!(
                    pattern_level(pattern, u, v, blur).to_bits(),
                    pattern_level_reference(pattern, u, v, blur).to_bits(),
                    "{pattern:?} at ({u}, {v}), blur {blur}"
                );
            }
        }
    }

    /// A uniform plane lit by one slit from a distant projector at 40 degrees, camera overhead:
    /// the rendered profile across the slit is, by hand, the layer mixture convolved with the
    /// slit's box, each layer shifted by `z_l tan(theta_t)`:
    /// `L(x) = E sum_l w_l [Phi((x - c - mu_l + W/2) / s_l) - Phi((x - c - mu_l - W/2) / s_l)]`.
    #[test]
    fn a_uniform_plane_lit_by_a_line_gives_the_boxed_mixture() {
        use super::super::profiles::Falloff;
        use super::super::render::{LayerModel, RenderOptions, SplatLayer, render_global};
        // Tall enough that the deep layer's Gaussian along the slit (+-4 sigma) stays on the plane.
        let (w, h, pitch) = (160usize, 71usize, 0.1f64);
        let far = 1e5;
        let centre = Vector3::new(w as f64 * pitch / 2.0, h as f64 * pitch / 2.0, 0.0);
        let surface = Surface::flat(w, h, pitch, centre + Vector3::new(0.0, 0.0, far));
        let theta = 40f64.to_radians();
        let light = centre + far * Vector3::new(-theta.sin(), 0.0, theta.cos());
        // One projector pixel per camera pixel along x.
        let coords: Vec<Option<(f32, f32)>> = (0..w * h)
            .map(|i| Some(((i % w) as f32, (i / w) as f32)))
            .collect();
        let view = ProjectorIllumination {
            centre: light,
            falloff: Falloff::Isotropic,
            coords: &coords,
        };
        // Slit on columns 50..=52: centre at x = 5.1 mm, width 0.3 mm.
        let slit = Pattern::Slit {
            axis: mlsss_core::capture::Axis::X,
            width: 3,
            period: 1000,
            offset: 50,
        };
        let layers = [(0.2f32, 0.3f32, 0.2f32), (0.1, 0.8, 1.0)]; // weight, sigma, depth (mm)
        let model = LayerModel::from_fn(w, h, |_, _| {
            layers
                .iter()
                .enumerate()
                .map(|(k, &(weight, sigma_mm, depth_mm))| SplatLayer {
                    index: k as u16,
                    weight,
                    sigma_mm,
                    depth_mm,
                })
                .collect::<Vec<_>>()
        });
        let e = pattern_irradiance(&surface, &view, &slit, 0.0, 0.0);
        let shift = shifts(&surface, &light, 1.4, ViewRay::Refracted);
        let opts = RenderOptions {
            sigma_bin_ratio: 1.02,
            min_sigma_px: 0.05,
            truncate_sigmas: 5.0,
            ..RenderOptions::default()
        };
        let out = render_global(&surface, &e, &shift, &model, &opts).unwrap();
        let e0 = irradiance(
            &surface.points[0],
            &Vector3::z(),
            &light,
            &Falloff::Isotropic,
        );
        let tan_t = (theta.sin() / 1.4).asin().tan();
        let phi = |t: f64| 0.5 * (1.0 + libm::erf(t / 2f64.sqrt()));
        let (c, width) = (5.1, 0.3);
        let row = h / 2;
        let mut peak = 0.0f64;
        let mut worst = 0.0f64;
        for x in 20..w - 20 {
            let xm = x as f64 * pitch;
            let want: f64 = layers
                .iter()
                .map(|&(wl, s, z)| {
                    let (s, mu) = (f64::from(s), f64::from(z) * tan_t);
                    f64::from(wl)
                        * (phi((xm - c - mu + width / 2.0) / s)
                            - phi((xm - c - mu - width / 2.0) / s))
                })
                .sum::<f64>()
                * e0;
            let got = f64::from(out[row * w + x][0]);
            peak = peak.max(want);
            worst = worst.max((got - want).abs());
        }
        // Discrete sources (0.1 mm) and sigma bins 2 % apart: within 1.5 % of the peak.
        assert!(worst < 0.015 * peak, "worst {worst} vs peak {peak}");
        // The deep layer's shift is visible: the profile's centroid lies downstream of the slit.
        let (m0, m1) = (20..w - 20).fold((0.0, 0.0), |(a, b), x| {
            let v = f64::from(out[row * w + x][0]);
            (a + v, b + v * x as f64 * pitch)
        });
        let centroid = m1 / m0 - c;
        let want = (0.2 * 0.2 + 0.1 * 1.0) / 0.3 * tan_t;
        assert!(
            (centroid - want).abs() < 0.02,
            "centroid {centroid} vs {want}"
        );
    }
}

/// A relit image split in its parts.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Relit {
    pub direct: Vec<[f32; 3]>,
    pub global: Vec<[f32; 3]>,
}

impl Relit {
    /// Direct plus global.
    pub fn total(&self) -> Vec<[f32; 3]> {
        self.direct
            .iter()
            .zip(&self.global)
            .map(|(d, g)| [d[0] + g[0], d[1] + g[1], d[2] + g[2]])
            .collect()
    }
}

/// A light's patterns made ready for any model: their irradiance and the light's shifts, which
/// every model's render of them shares (so several baselines need them found once).
pub struct LitPatterns {
    irradiances: Vec<Vec<f32>>,
    shift: Vec<Option<Vector3<f64>>>,
}

impl LitPatterns {
    /// The irradiance of `view` showing each of `patterns` on `surface`, and its shifts.
    pub fn new(
        surface: &Surface,
        view: &ProjectorIllumination,
        patterns: &[Pattern],
        black_level: f32,
        blur_px: f32,
        eta: f64,
        view_ray: ViewRay,
    ) -> Self {
        Self {
            irradiances: patterns
                .iter()
                .map(|p| pattern_irradiance(surface, view, p, black_level, blur_px))
                .collect(),
            shift: shifts(surface, &view.centre, eta, view_ray),
        }
    }

    /// Every pattern rendered with `model` (global) and `albedo` (direct), each frame exactly
    /// as it renders alone (the splats are found once per source: see [`render_global_many`]).
    pub fn relight(
        &self,
        surface: &Surface,
        model: &LayerModel,
        albedo: &[[f32; 3]],
        opts: &RenderOptions,
    ) -> Result<Vec<Relit>, RenderError> {
        let refs: Vec<&[f32]> = self.irradiances.iter().map(Vec::as_slice).collect();
        let globals = render_global_many(surface, &refs, &self.shift, model, opts)?;
        Ok(self
            .irradiances
            .iter()
            .zip(globals)
            .map(|(e, global)| Relit {
                direct: e
                    .iter()
                    .zip(albedo)
                    .map(|(&e, a)| [a[0] * e, a[1] * e, a[2] * e])
                    .collect(),
                global,
            })
            .collect())
    }
}

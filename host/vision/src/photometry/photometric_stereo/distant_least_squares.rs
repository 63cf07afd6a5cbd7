//! Least-squares photometric stereo under distant lights (the textbook baseline, and the case
//! `scripts/peers.py` races against numpy's pseudo-inverse): [`super::solve_pixel`] with
//! [`Method::LeastSquares`](super::Method::LeastSquares), with what every pixel shares computed
//! once and the per-pixel arithmetic in f32.
//!
//! Why: with distant lights every pixel with finite readings uses every light, so `g = albedo *
//! n` is a fixed linear map of its readings: the pseudo-inverse of the light matrix, computed once
//! in f64, replaces the per-pixel normal equations, and multiplications by each channel's weight
//! replace the per-reading divisions by the light's colour (a 4-light full-size solve was
//! division-bound). f32 keeps 7 significant digits, beyond the frames' own precision (12-bit or
//! noisier); normals agree with the general solver's to about 1e-6 rad (test). Pixels with a
//! non-finite reading, whose light set is smaller, go to the general solver.

use nalgebra::{Matrix3xX, Vector3};

use super::{LightSample, PixelSolution, PixelStatus, PsParams, normal_factor_of, solve_pixel};

/// A light's terms shared by every pixel, f32.
#[derive(Debug, Clone, Copy)]
struct LightTerms {
    /// `grey = weight . rgb`: the reading with the light's colour divided out, averaged over the
    /// channels (`1 / (3 relative_c)`, 0 for a channel the light does not emit).
    weight: [f32; 3],
    /// Direction times mean irradiance: `grey = albedo_grey * (vector . n)`.
    vector: [f32; 3],
    /// Column of the pseudo-inverse: `g = sum_i pinv_i * grey_i`.
    pinv: [f32; 3],
    direction: [f32; 3],
    irradiance: [f32; 3],
}

/// Distant lights prepared for the least-squares solve of every pixel.
pub(super) struct DistantLeastSquares<'a> {
    lights: &'a [LightSample],
    view: Vector3<f64>,
    view_f32: [f32; 3],
    terms: Vec<LightTerms>,
    /// Every light's bit.
    set: u128,
    /// The light matrix is too ill-conditioned (or singular): every lit pixel is flagged.
    ill_conditioned: bool,
    params: &'a PsParams,
}

impl<'a> DistantLeastSquares<'a> {
    /// `None` when a light is unusable at every pixel (non-positive or non-finite irradiance,
    /// non-finite direction) or there are not 3 to 128 lights: the general solver handles those.
    pub(super) fn new(
        lights: &'a [LightSample],
        view: Vector3<f64>,
        params: &'a PsParams,
    ) -> Option<Self> {
        if !(3..=super::MAX_LIGHTS).contains(&lights.len()) {
            return None;
        }
        let scales: Vec<f64> = lights
            .iter()
            .map(|light| {
                let scale = light.irradiance.iter().sum::<f64>() / 3.0;
                let usable = scale > 0.0
                    && scale.is_finite()
                    && light.direction.iter().all(|v| v.is_finite());
                usable.then_some(scale)
            })
            .collect::<Option<_>>()?;
        let vectors: Vec<Vector3<f64>> = lights
            .iter()
            .zip(&scales)
            .map(|(light, scale)| light.direction * *scale)
            .collect();
        let factor = normal_factor_of(vectors.iter().map(|v| Some(*v)));
        let (pinv, ill_conditioned) = match factor {
            Some((cholesky, condition)) => {
                // (A^T A)^-1 A^T, column i for light i.
                let at = Matrix3xX::from_columns(&vectors);
                (
                    cholesky.solve(&at),
                    !condition.at_most(params.max_condition),
                )
            }
            None => (Matrix3xX::zeros(lights.len()), true),
        };
        let to_f32 = |v: &Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
        let terms = lights
            .iter()
            .zip(&scales)
            .enumerate()
            .map(|(i, (light, scale))| LightTerms {
                weight: light.irradiance.map(|e| {
                    let relative = e / scale;
                    if relative > 0.0 {
                        (1.0 / (3.0 * relative)) as f32
                    } else {
                        0.0
                    }
                }),
                vector: to_f32(&vectors[i]),
                pinv: to_f32(&pinv.column(i).into_owned()),
                direction: to_f32(&light.direction),
                irradiance: light.irradiance.map(|e| e as f32),
            })
            .collect();
        Some(Self {
            lights,
            view,
            view_f32: to_f32(&view),
            terms,
            set: if lights.len() == 128 {
                u128::MAX
            } else {
                (1u128 << lights.len()) - 1
            },
            ill_conditioned,
            params,
        })
    }

    /// Solves one pixel; `rgb(i)` is its reading under light `i`.
    pub(super) fn solve(&self, rgb: impl Fn(usize) -> [f32; 3]) -> PixelSolution {
        let mut g = [0.0f32; 3];
        let mut brightest = 0.0f32;
        let mut finite = true;
        for (i, t) in self.terms.iter().enumerate() {
            let reading = rgb(i);
            let grey = dot(&t.weight, &reading);
            finite &= grey.is_finite();
            brightest = brightest.max(grey);
            for (gk, pk) in g.iter_mut().zip(&t.pinv) {
                *gk += pk * grey;
            }
        }
        if !finite {
            return self.general(&rgb);
        }
        if f64::from(brightest) <= self.params.noise_floor {
            return PixelSolution::flagged(PixelStatus::NoSignal, 0);
        }
        if self.ill_conditioned {
            return PixelSolution::flagged(PixelStatus::IllConditioned, self.set);
        }
        let length = dot(&g, &g).sqrt();
        if length.is_nan() || length <= 0.0 {
            return PixelSolution::flagged(PixelStatus::NoSignal, self.set);
        }
        let normal = g.map(|v| v / length);
        if dot(&normal, &self.view_f32) <= 0.0 {
            return PixelSolution::flagged(PixelStatus::BackFacing, self.set);
        }
        let (mut num, mut den) = ([0.0f32; 3], [0.0f32; 3]);
        let mut squares = 0.0f32;
        for (i, t) in self.terms.iter().enumerate() {
            let reading = rgb(i);
            let cosine = dot(&t.direction, &normal).max(0.0);
            for c in 0..3 {
                let a = t.irradiance[c] * cosine;
                num[c] += reading[c] * a;
                den[c] += a * a;
            }
            let residual = dot(&t.weight, &reading) - dot(&t.vector, &g);
            squares += residual * residual;
        }
        let albedo = [0, 1, 2].map(|c| if den[c] > 0.0 { num[c] / den[c] } else { 0.0 });
        PixelSolution {
            normal,
            albedo,
            residual: (squares / self.terms.len() as f32).sqrt() / brightest,
            used: self.set,
            status: PixelStatus::Ok,
        }
    }

    /// Solves the [`BLOCK`] pixels from `first` (all inside the images): [`Self::solve`] of each,
    /// bit for bit (same operations in the same order per pixel; test), but one light at a time
    /// over the block with the readings de-interleaved, loops the compiler turns into SIMD.
    /// Pixels outside `mask` are [`PixelStatus::Masked`]; a block wholly outside is not read.
    // Lane loops index several per-lane arrays at once, which the vectoriser handles best.
    #[allow(clippy::needless_range_loop)]
    pub(super) fn solve_block(
        &self,
        raws: &[&[f32]],
        mask: Option<&[bool]>,
        first: usize,
    ) -> [PixelSolution; BLOCK] {
        let mut out = [PixelSolution::flagged(PixelStatus::Masked, 0); BLOCK];
        let inside: [bool; BLOCK] = std::array::from_fn(|l| {
            mask.is_none_or(|m| m.get(first + l).copied().unwrap_or(false))
        });
        if !inside.iter().any(|&i| i) {
            return out;
        }
        let values = first * 3..(first + BLOCK) * 3;
        let mut g = [[0.0f32; BLOCK]; 3];
        let mut brightest = [0.0f32; BLOCK];
        let mut finite = [true; BLOCK];
        for (t, raw) in self.terms.iter().zip(raws) {
            let rgb = channels(&raw[values.clone()]);
            for l in 0..BLOCK {
                let grey =
                    t.weight[0] * rgb[0][l] + t.weight[1] * rgb[1][l] + t.weight[2] * rgb[2][l];
                finite[l] &= grey.is_finite();
                brightest[l] = brightest[l].max(grey);
                for k in 0..3 {
                    g[k][l] += t.pinv[k] * grey;
                }
            }
        }
        let mut length = [0.0f32; BLOCK];
        let mut normal = [[0.0f32; BLOCK]; 3];
        let mut facing = [0.0f32; BLOCK];
        for l in 0..BLOCK {
            length[l] = (g[0][l] * g[0][l] + g[1][l] * g[1][l] + g[2][l] * g[2][l]).sqrt();
            for k in 0..3 {
                normal[k][l] = g[k][l] / length[l];
            }
            facing[l] = normal[0][l] * self.view_f32[0]
                + normal[1][l] * self.view_f32[1]
                + normal[2][l] * self.view_f32[2];
        }
        let (mut num, mut den) = ([[0.0f32; BLOCK]; 3], [[0.0f32; BLOCK]; 3]);
        let mut squares = [0.0f32; BLOCK];
        for (t, raw) in self.terms.iter().zip(raws) {
            let rgb = channels(&raw[values.clone()]);
            for l in 0..BLOCK {
                let cosine = (t.direction[0] * normal[0][l]
                    + t.direction[1] * normal[1][l]
                    + t.direction[2] * normal[2][l])
                    .max(0.0);
                for c in 0..3 {
                    let a = t.irradiance[c] * cosine;
                    num[c][l] += rgb[c][l] * a;
                    den[c][l] += a * a;
                }
                let residual =
                    (t.weight[0] * rgb[0][l] + t.weight[1] * rgb[1][l] + t.weight[2] * rgb[2][l])
                        - (t.vector[0] * g[0][l] + t.vector[1] * g[1][l] + t.vector[2] * g[2][l]);
                squares[l] += residual * residual;
            }
        }
        // Albedos and residuals of every lane, vectorised; the flags below pick what is kept.
        let lights = self.terms.len() as f32;
        let mut albedo = [[0.0f32; BLOCK]; 3];
        let mut residual = [0.0f32; BLOCK];
        for l in 0..BLOCK {
            for c in 0..3 {
                albedo[c][l] = if den[c][l] > 0.0 {
                    num[c][l] / den[c][l]
                } else {
                    0.0
                };
            }
            residual[l] = (squares[l] / lights).sqrt() / brightest[l];
        }
        for (l, pixel) in out.iter_mut().enumerate() {
            if !inside[l] {
                continue;
            }
            // Fields set one by one on the pixel in place: a whole `PixelSolution` built aside
            // and copied in stalled on the copy (store forwarding), a fifth of the block's time.
            let status = if !finite[l] {
                let p = first + l;
                *pixel = self.general(&|i: usize| {
                    let raw = raws[i];
                    [raw[p * 3], raw[p * 3 + 1], raw[p * 3 + 2]]
                });
                continue;
            } else if f64::from(brightest[l]) <= self.params.noise_floor {
                pixel.status = PixelStatus::NoSignal;
                continue;
            } else if self.ill_conditioned {
                PixelStatus::IllConditioned
            } else if length[l].is_nan() || length[l] <= 0.0 {
                PixelStatus::NoSignal
            } else if facing[l] <= 0.0 {
                PixelStatus::BackFacing
            } else {
                PixelStatus::Ok
            };
            pixel.status = status;
            pixel.used = self.set;
            if status == PixelStatus::Ok {
                pixel.normal = [normal[0][l], normal[1][l], normal[2][l]];
                pixel.albedo = [albedo[0][l], albedo[1][l], albedo[2][l]];
                pixel.residual = residual[l];
            }
        }
        out
    }

    /// A pixel with a non-finite reading: the general solver drops that light.
    #[cold]
    fn general(&self, rgb: &impl Fn(usize) -> [f32; 3]) -> PixelSolution {
        let readings: Vec<[f32; 3]> = (0..self.terms.len()).map(rgb).collect();
        solve_pixel(&readings, self.lights, &self.view, self.params)
    }
}

/// Pixels solved together by [`DistantLeastSquares::solve_block`].
pub(super) const BLOCK: usize = 8;

/// The red, green and blue values of [`BLOCK`] interleaved RGB pixels.
fn channels(interleaved: &[f32]) -> [[f32; BLOCK]; 3] {
    let mut out = [[0.0f32; BLOCK]; 3];
    for (l, rgb) in interleaved.chunks_exact(3).take(BLOCK).enumerate() {
        for c in 0..3 {
            out[c][l] = rgb[c];
        }
    }
    out
}

fn dot(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use super::super::{DirectionalLights, Method, solve_images};
    use super::*;
    use image::Rgb32FImage;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    /// `lights` lights spread around the view axis (azimuths evenly spaced, each moved by up to
    /// `azimuth_jitter` rad), tilted 0.4 rad to `max_tilt` from it, each channel's irradiance
    /// 0.3 to 2: a rig the solver can use. Random lights can be too ill-conditioned: with 3
    /// lights, tilts near 0.3 rad and one light 40x dimmer than the others exceed
    /// `max_condition` and every pixel is flagged (seed 212841 of the block test drew such a rig;
    /// the coplanar test covers that case).
    fn usable_rig(
        rng: &mut rand_pcg::Pcg64,
        lights: usize,
        azimuth_jitter: f64,
        max_tilt: f64,
    ) -> Vec<LightSample> {
        (0..lights)
            .map(|k| {
                let mut azimuth = std::f64::consts::TAU * k as f64 / lights as f64;
                if azimuth_jitter > 0.0 {
                    azimuth += rng.gen_range(-azimuth_jitter..azimuth_jitter);
                }
                let tilt: f64 = rng.gen_range(0.4..max_tilt);
                LightSample {
                    direction: Vector3::new(
                        tilt.sin() * azimuth.cos(),
                        tilt.sin() * azimuth.sin(),
                        tilt.cos(),
                    ),
                    irradiance: [0, 1, 2].map(|_| rng.gen_range(0.3..2.0)),
                }
            })
            .collect()
    }

    /// Random lights around the view axis, random normals and albedos, with noise, some shadowed
    /// (zero) readings, dark pixels and a few non-finite readings: what `solve_images` gives
    /// (this path) against `solve_pixel` (the general f64 solver) for each pixel.
    fn compare(seed: u64, lights: usize, pixels: usize) -> Result<usize, TestCaseError> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let samples = usable_rig(&mut rng, lights, 0.3, 0.9);
        let view = Vector3::z();
        let mut images = vec![vec![0f32; pixels * 3]; lights];
        for p in 0..pixels {
            let normal =
                Vector3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), 0.3).normalize();
            let albedo: [f64; 3] = [0, 1, 2].map(|_| rng.gen_range(0.0..1.0));
            for (image, light) in images.iter_mut().zip(&samples) {
                let cosine = normal.dot(&light.direction).max(0.0);
                for c in 0..3 {
                    let noise = rng.gen_range(-0.003..0.003);
                    image[p * 3 + c] = (albedo[c] * light.irradiance[c] * cosine + noise) as f32;
                }
            }
            if rng.gen_bool(0.02) {
                images[rng.gen_range(0..lights)][p * 3 + rng.gen_range(0..3)] = f32::NAN;
            }
        }
        let frames: Vec<Rgb32FImage> = images
            .into_iter()
            .map(|data| Rgb32FImage::from_raw(pixels as u32, 1, data).unwrap())
            .collect();
        let refs: Vec<&Rgb32FImage> = frames.iter().collect();
        let params = PsParams {
            method: Method::LeastSquares,
            ..PsParams::default()
        };
        let distant = DirectionalLights {
            lights: samples.clone(),
            view,
        };
        let map = solve_images(&refs, &distant, None, &params).unwrap();
        let mut solved = 0;
        for (p, fast) in map.pixels.iter().enumerate() {
            let readings: Vec<[f32; 3]> = frames
                .iter()
                .map(|f| {
                    let raw = f.as_raw();
                    [raw[p * 3], raw[p * 3 + 1], raw[p * 3 + 2]]
                })
                .collect();
            let reference = solve_pixel(&readings, &samples, &view, &params);
            prop_assert_eq!(fast.status, reference.status, "pixel {}", p);
            prop_assert_eq!(fast.used, reference.used);
            if reference.status != PixelStatus::Ok {
                continue;
            }
            solved += 1;
            let scale = reference
                .albedo
                .iter()
                .fold(0.05f32, |m, &a| m.max(a.abs()));
            for c in 0..3 {
                prop_assert!(
                    (fast.normal[c] - reference.normal[c]).abs() < 2e-5,
                    "{fast:?} {reference:?}"
                );
                prop_assert!(
                    (fast.albedo[c] - reference.albedo[c]).abs() < 2e-5 * scale,
                    "{fast:?} {reference:?}"
                );
            }
            prop_assert!(
                (fast.residual - reference.residual).abs() < 1e-4 * reference.residual.max(0.1),
                "{fast:?} {reference:?}"
            );
        }
        Ok(solved)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// The f32 path gives the general solver's outcome on every pixel, and its normals,
        /// albedos and residuals to within f32 rounding.
        #[test]
        fn matches_the_general_solver(seed in 0u64..1_000_000, lights in 3usize..9) {
            let solved = compare(seed, lights, 300)?;
            prop_assert!(solved > 30, "{} pixels solved", solved);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        /// The block kernel gives the per-pixel path's solution bit for bit on every pixel: masked,
        /// dark, back-facing, non-finite (general solver) and solved ones alike.
        #[test]
        fn blocks_match_the_per_pixel_path_exactly(seed in 0u64..1_000_000, lights in 3usize..7) {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let samples = usable_rig(&mut rng, lights, 0.0, 1.0);
            let params = PsParams {
                method: Method::LeastSquares,
                ..PsParams::default()
            };
            let solver = DistantLeastSquares::new(&samples, Vector3::z(), &params).unwrap();
            let pixels = 4 * BLOCK;
            let images: Vec<Vec<f32>> = (0..lights)
                .map(|_| {
                    (0..pixels * 3)
                        .map(|_| match rng.gen_range(0..40) {
                            0 => f32::NAN,
                            1 => f32::INFINITY,
                            2 => 0.0,
                            3 => -0.5,
                            _ => rng.gen_range(0.0f32..1.0),
                        })
                        .collect()
                })
                .collect();
            let raws: Vec<&[f32]> = images.iter().map(|i| i.as_slice()).collect();
            let mask: Vec<bool> = (0..pixels).map(|p| p >= BLOCK && rng.gen_bool(0.8)).collect();
            let mut solved = 0;
            for first in (0..pixels).step_by(BLOCK) {
                let block = solver.solve_block(&raws, Some(&mask), first);
                for (l, fast) in block.iter().enumerate() {
                    let p = first + l;
                    if !mask[p] {
                        prop_assert_eq!(fast.status, PixelStatus::Masked);
                        prop_assert_eq!(fast.normal, [0.0; 3]);
                        continue;
                    }
                    let reference =
                        solver.solve(|i| [raws[i][p * 3], raws[i][p * 3 + 1], raws[i][p * 3 + 2]]);
                    prop_assert_eq!(fast.status, reference.status, "pixel {}", p);
                    prop_assert_eq!(fast.used, reference.used);
                    prop_assert_eq!(fast.normal.map(f32::to_bits), reference.normal.map(f32::to_bits));
                    prop_assert_eq!(fast.albedo.map(f32::to_bits), reference.albedo.map(f32::to_bits));
                    prop_assert_eq!(fast.residual.to_bits(), reference.residual.to_bits());
                    solved += usize::from(fast.status == PixelStatus::Ok);
                }
            }
            prop_assert!(solved > 0, "no pixel solved: the comparison would test flags only");
        }
    }

    #[test]
    fn coplanar_lights_flag_every_lit_pixel_as_the_general_solver_does() {
        let lights: Vec<LightSample> = (0..4)
            .map(|i| LightSample {
                // All in the plane y = 0: the normal matrix is singular.
                direction: Vector3::new(
                    (0.3 * i as f64 - 0.4).sin(),
                    0.0,
                    (0.3 * i as f64 - 0.4).cos(),
                ),
                irradiance: [1.0; 3],
            })
            .collect();
        let params = PsParams {
            method: Method::LeastSquares,
            ..PsParams::default()
        };
        let solver = DistantLeastSquares::new(&lights, Vector3::z(), &params).unwrap();
        let readings = [[0.5f32; 3]; 4];
        let fast = solver.solve(|i| readings[i]);
        let reference = solve_pixel(&readings, &lights, &Vector3::z(), &params);
        assert_eq!(fast.status, PixelStatus::IllConditioned);
        assert_eq!(fast, reference);
    }
}

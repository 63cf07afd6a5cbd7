//! Synthetic Gray-code frames with an exactly known camera-to-projector mapping, for decoder tests
//! and benchmarks (independent of the virtual booth: no geometry, no light transport, just a smooth
//! mapping, blur and sensor noise).
//!
//! Conventions: camera pixel `(x, y)` (centres at integers) sees projector position
//! `u = u[0] + u[1] x + u[2] y + bulge * ((x - w/2) / w)^2 * w`, `v = v[0] + v[1] x + v[2] y`,
//! in projector pixels with centres at integers (as `capture::patterns`). The frame value is
//! `black + albedo * (direct * blur(pattern, direct_blur) + (1 - direct) * blur(pattern, global_blur))`
//! plus Gaussian shot and read noise: `global_blur` stands for subsurface scattering, which washes
//! out fine stripes while the direct (surface) reflection keeps them.

use rand::SeedableRng;
use rand_pcg::Pcg64;

use super::gray_code::{BitPair, GrayCodeFrames, bits_for};
use mlsss_core::capture::{Axis, Pattern};
use mlsss_core::gaussian_blur::{GaussianKernel, Normalisation};

/// A synthetic view of a projector pattern sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntheticGrayScene {
    pub camera_size: (u32, u32),
    pub projector_size: (u32, u32),
    /// `u = u[0] + u[1] x + u[2] y` (plus the bulge).
    pub u: [f64; 3],
    /// `v = v[0] + v[1] x + v[2] y`.
    pub v: [f64; 3],
    /// Quadratic term of `u` along x, projector pixels at the image border.
    pub bulge: f64,
    /// A disc `(cx, cy, radius)` in camera pixels that the projector does not light.
    pub shadow_disc: Option<[f64; 3]>,
    pub albedo: f32,
    /// Light seen under a black pattern (ambient + projector black level).
    pub black_level: f32,
    /// Fraction of the light reflected at the surface (sharp); the rest is blurred by `global_blur_px`.
    pub direct_fraction: f32,
    /// Gaussian blur (standard deviation, projector pixels) of the direct light: lens defocus.
    pub direct_blur_px: f64,
    /// Gaussian blur of the rest: subsurface scattering.
    pub global_blur_px: f64,
    /// Shot noise variance per unit signal and read noise standard deviation (0 for none).
    pub shot_noise_gain: f32,
    pub read_noise: f32,
    pub seed: u64,
}

impl SyntheticGrayScene {
    /// A sharp, slightly tilted view filling most of a `camera_size` image with a 10-bit-sized
    /// projector, 12-bit-like noise.
    pub fn new(camera_size: (u32, u32), projector_size: (u32, u32)) -> Self {
        let (w, h) = (camera_size.0 as f64, camera_size.1 as f64);
        let (pw, ph) = (projector_size.0 as f64, projector_size.1 as f64);
        Self {
            camera_size,
            projector_size,
            u: [0.05 * pw, 0.9 * pw / w, 0.02 * pw / w],
            v: [0.05 * ph, -0.01 * ph / h, 0.9 * ph / h],
            bulge: 0.0,
            shadow_disc: None,
            albedo: 0.6,
            black_level: 0.02,
            direct_fraction: 1.0,
            direct_blur_px: 0.5,
            global_blur_px: 0.0,
            shot_noise_gain: 1.0 / 12_000.0,
            read_noise: 2.0 / 4095.0,
            seed: 1,
        }
    }

    /// The true projector position seen by camera pixel `(x, y)`, `None` where it is unlit.
    pub fn projector_coords(&self, x: u32, y: u32) -> Option<(f64, f64)> {
        let (xf, yf) = (x as f64, y as f64);
        if let Some([cx, cy, r]) = self.shadow_disc
            && (xf - cx).powi(2) + (yf - cy).powi(2) <= r * r
        {
            return None;
        }
        let w = self.camera_size.0 as f64;
        let t = (xf - w / 2.0) / w;
        let u = self.u[0] + self.u[1] * xf + self.u[2] * yf + self.bulge * t * t * w;
        let v = self.v[0] + self.v[1] * xf + self.v[2] * yf;
        let inside = |c: f64, size: u32| c >= -0.5 && c < size as f64 - 0.5;
        (inside(u, self.projector_size.0) && inside(v, self.projector_size.1)).then_some((u, v))
    }

    /// Renders white, black and every Gray-code pair (MSB first).
    pub fn render(&self) -> GrayCodeFrames {
        let mut rng = Pcg64::seed_from_u64(self.seed);
        let mut frame = |pattern: Option<Pattern>| self.render_frame(pattern, &mut rng);
        let white = frame(Some(Pattern::White));
        let black = frame(None);
        let mut axis_pairs = |axis: Axis, size: u32| {
            (0..bits_for(size))
                .rev()
                .map(|bit| {
                    let p = |inverted| Pattern::Gray {
                        axis,
                        bit,
                        inverted,
                    };
                    BitPair {
                        pattern: frame(Some(p(false))),
                        inverse: frame(Some(p(true))),
                    }
                })
                .collect::<Vec<_>>()
        };
        let x = axis_pairs(Axis::X, self.projector_size.0);
        let y = axis_pairs(Axis::Y, self.projector_size.1);
        GrayCodeFrames {
            width: self.camera_size.0,
            height: self.camera_size.1,
            white: Some(white),
            black: Some(black),
            x,
            y,
        }
    }

    /// One camera frame; `None` is the black pattern.
    fn render_frame(&self, pattern: Option<Pattern>, rng: &mut Pcg64) -> Vec<f32> {
        let (w, h) = self.camera_size;
        let direct_kernel = gaussian_kernel(self.direct_blur_px);
        let global_kernel = gaussian_kernel(self.global_blur_px);
        let mut out = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                let lit = match (pattern, self.projector_coords(x, y)) {
                    (Some(p), Some((u, v))) => {
                        let d = self.blurred(&p, u, v, &direct_kernel);
                        let g = self.blurred(&p, u, v, &global_kernel);
                        self.albedo * (self.direct_fraction * d + (1.0 - self.direct_fraction) * g)
                    }
                    _ => 0.0,
                };
                let signal = self.black_level + lit;
                out.push(self.add_noise(signal, rng));
            }
        }
        out
    }

    /// The pattern blurred along its coding axis (the patterns are constant along the other one).
    fn blurred(&self, pattern: &Pattern, u: f64, v: f64, kernel: &[(f64, f32)]) -> f32 {
        let axis_is_y = matches!(pattern, Pattern::Gray { axis: Axis::Y, .. });
        let (c, size) = if axis_is_y {
            (v, self.projector_size.1)
        } else {
            (u, self.projector_size.0)
        };
        kernel
            .iter()
            .map(|&(offset, weight)| {
                let p = (c + offset).round().clamp(0.0, size as f64 - 1.0) as u32;
                let value = if axis_is_y {
                    pattern.value(0, p)
                } else {
                    pattern.value(p, 0)
                };
                weight * value
            })
            .sum()
    }

    fn add_noise(&self, signal: f32, rng: &mut Pcg64) -> f32 {
        let var = self.shot_noise_gain * signal.max(0.0) + self.read_noise * self.read_noise;
        (signal + var.sqrt() * standard_normal(rng)).clamp(0.0, 1.0)
    }
}

/// Offsets (projector pixels) and weights of a sampled 1-D Gaussian; a single tap for sigma 0.
fn gaussian_kernel(sigma: f64) -> Vec<(f64, f32)> {
    // Quarter-pixel steps out to 3 sigma: fine enough to resolve 1-px stripes.
    let step = 0.25;
    GaussianKernel::new(sigma / step, 3.0, Normalisation::Weights)
        .to_f32()
        .taps()
        .map(|(k, w)| (k as f64 * step, w))
        .collect()
}

/// A standard normal sample (Box-Muller).
fn standard_normal(rng: &mut Pcg64) -> f32 {
    use rand::Rng;
    let u1: f64 = rng.gen_range(f64::EPSILON..1.0);
    let u2: f64 = rng.r#gen();
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

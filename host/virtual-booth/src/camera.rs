//! The camera model: pinhole rays with the booth's radial distortion, the radiometric gain, and
//! the sensor (shot noise from the full-well capacity, read noise, saturation and quantisation —
//! the last two happen when the frame is written as camera codes).
//!
//! Conventions
//! - Camera pixel (x, y): column, row, centres at integer coordinates (OpenCV), world rays from
//!   `calib::DeviceCalibration::ray` (distortion included).
//! - Linear camera value: 1 = saturation (full well, the largest code). `GAIN` converts radiance
//!   in the irradiance unit of `projector` per steradian into camera value.

use std::f64::consts::PI;

use mlsss_core::booth::Booth;
use mlsss_core::calibration::DeviceCalibration;
use mlsss_mc::NormalStream;

/// Camera value per unit radiance: a white Lambertian surface under unit irradiance (radiance
/// 1/pi) reads 0.85, leaving headroom below saturation for skin, not for strong highlights.
pub const GAIN: f64 = 0.85 * PI;

/// The booth camera.
#[derive(Debug, Clone)]
pub struct CameraModel {
    pub calib: DeviceCalibration,
    /// Electrons at saturation.
    full_well_e: f64,
    /// Read noise in camera value units.
    read_noise: f64,
}

impl CameraModel {
    pub fn new(booth: &Booth) -> Self {
        let c = &booth.camera;
        let max_code = ((1u64 << c.bit_depth) - 1) as f64;
        Self {
            calib: booth.camera_calibration(),
            full_well_e: c.full_well_e,
            read_noise: c.read_noise_dn / max_code,
        }
    }

    /// Adds photon shot noise and read noise to noise-free camera values, one deviate of
    /// `normals` per value in order. Poisson statistics are approximated by a Gaussian of the
    /// same variance (exact enough above ~20 electrons, and read noise dominates below).
    pub fn add_noise(&self, values: &mut [f32], normals: &mut NormalStream) {
        self.add_noise_with_gain(values, 1.0, normals);
    }

    /// [`Self::add_noise`] at analog gain `gain`: camera values are `gain` times the electrons'
    /// share of the full well, so the shot noise grows with the gain; the read noise (after the
    /// amplifier) does not.
    ///
    /// In f32, with f32 deviates (`NormalStream`: Box-Muller over SIMD lanes, within 2e-6 of
    /// exact; it replaced `rand_distr`'s ziggurat on a `Pcg64` with an f64 square root, see
    /// `benches/noise.rs`): the variance v shot + read is rounded to f32 (6e-8 relative, 3e-8 in
    /// the standard deviation) and v + sigma z to f32 in two roundings instead of one, an error
    /// below 2^-24 (|sigma z| + |v + sigma z|): 5e-4 of a 12-bit code even at saturation, and the
    /// value is stored in f32 anyway.
    pub fn add_noise_with_gain(&self, values: &mut [f32], gain: f64, normals: &mut NormalStream) {
        // Deviates a chunk at a time, into a buffer that stays in L1, so that the loop below
        // (square root, multiply-add) vectorises and the generator runs whole SIMD blocks.
        const CHUNK: usize = 1024;
        let shot = (gain / self.full_well_e) as f32;
        let read = self.read_noise.powi(2) as f32;
        let mut z = [0.0f32; CHUNK];
        for chunk in values.chunks_mut(CHUNK) {
            let z = &mut z[..chunk.len()];
            normals.fill(z);
            for (v, &z) in chunk.iter_mut().zip(z.iter()) {
                // No `mul_add`: the baseline x86-64 target has no FMA and would call libm's.
                let sigma = (v.max(0.0) * shot + read).sqrt();
                *v += sigma * z;
            }
        }
    }

    /// Standard deviation of the noise at camera value `v` (for tests and reports).
    pub fn noise_sigma(&self, v: f64) -> f64 {
        self.noise_sigma_with_gain(v, 1.0)
    }

    /// Standard deviation of the noise at camera value `v` and analog gain `gain`.
    pub fn noise_sigma_with_gain(&self, v: f64, gain: f64) -> f64 {
        (gain * v.max(0.0) / self.full_well_e + self.read_noise.powi(2)).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_has_the_shot_plus_read_variance() {
        let cam = CameraModel::new(&Booth::builtin(true));
        let mut rng = NormalStream::new(3, 0);
        let level = 0.4;
        let mut values = vec![level as f32; 200_000];
        cam.add_noise(&mut values, &mut rng);
        let n = values.len() as f64;
        let mean = values.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = values
            .iter()
            .map(|&v| (v as f64 - mean).powi(2))
            .sum::<f64>()
            / n;
        let expected = cam.noise_sigma(level);
        assert!((mean - level).abs() < 3.0 * expected / n.sqrt() + 1e-6);
        assert!(
            (var.sqrt() / expected - 1.0).abs() < 0.01,
            "{} {}",
            var.sqrt(),
            expected
        );
        // Neighbouring values must be uncorrelated (|r| < 4 / sqrt(n) for independent samples).
        let lag1 = values
            .chunks_exact(2)
            .map(|p| (p[0] as f64 - mean) * (p[1] as f64 - mean))
            .sum::<f64>()
            / (n / 2.0)
            / var;
        assert!(lag1.abs() < 4.0 / (n / 2.0).sqrt(), "correlation {lag1}");
    }
}

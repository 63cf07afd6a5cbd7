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

use rand::Rng;

use mlsss_core::booth::Booth;
use mlsss_core::calibration::DeviceCalibration;
use rand_distr::StandardNormal;

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

    /// Adds photon shot noise and read noise to noise-free camera values. Poisson statistics
    /// are approximated by a Gaussian of the same variance (exact enough above ~20 electrons,
    /// and read noise dominates below).
    pub fn add_noise<R: Rng>(&self, values: &mut [f32], rng: &mut R) {
        self.add_noise_with_gain(values, 1.0, rng);
    }

    /// [`Self::add_noise`] at analog gain `gain`: camera values are `gain` times the electrons'
    /// share of the full well, so the shot noise grows with the gain; the read noise (after the
    /// amplifier) does not.
    pub fn add_noise_with_gain<R: Rng>(&self, values: &mut [f32], gain: f64, rng: &mut R) {
        // rand_distr's ziggurat deviates: no logarithm or square root for almost every value
        // (the noise was a quarter of a calibration capture's CPU time with polar Box-Muller).
        // The shot term's division is taken out of the loop (it was a tenth of the frame
        // finishing's time): `v * (gain / full_well)` instead of `gain * v / full_well`, which
        // differ by at most one f64 ulp, far below the f32 the value is stored in.
        let shot = gain / self.full_well_e;
        let read = self.read_noise.powi(2);
        for v in values.iter_mut() {
            let sigma = (f64::from(*v).max(0.0) * shot + read).sqrt();
            *v = (f64::from(*v) + sigma * rng.sample::<f64, _>(StandardNormal)) as f32;
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
    use rand::SeedableRng;

    #[test]
    fn noise_has_the_shot_plus_read_variance() {
        let cam = CameraModel::new(&Booth::builtin(true));
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
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

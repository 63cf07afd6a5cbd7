//! Exposure per projector, chosen by a metering step before the scan (DESIGN section 3).
//!
//! A real booth meters the subject: it takes one white frame per projector at the booth's nominal
//! exposure (`timing.exposure_periods` refresh periods, analog gain 1) and chooses, per projector,
//! the exposure that brings a high percentile of the white to a target level below saturation.
//! Dark skin returns a tenth of the light of light skin; without metering most of a dark face
//! sits within a few read-noise steps of black.
//!
//! The exposure is a whole number of refresh periods (the controller's trigger, DESIGN section
//! 7), at most [`max_exposure_periods`] so the slot keeps its settle time and a host window of
//! [`MIN_HOST_WINDOW_PERIODS`]; beyond that the camera's analog gain makes up the rest, up to
//! `max_analog_gain`. Every frame of a projector is taken at its exposure; readers divide the
//! frames by [`ProjectorExposure::scale`] so all stages see values at the nominal exposure
//! (`Capture::read_frame` does it), and the noise model scales with it
//! ([`ProjectorExposure::noise_scale`]).

use serde::{Deserialize, Serialize};

use crate::booth::TimingSpec;

/// Refresh periods of a slot that the host keeps for showing the next pattern (67 ms at 60 Hz;
/// the host needs well under that, `hardware/timing.md`).
pub const MIN_HOST_WINDOW_PERIODS: u32 = 4;

/// The exposure one projector's frames were taken with.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProjectorExposure {
    pub projector: u8,
    /// Exposure time in refresh periods of the projector (the trigger's exposure).
    pub periods: u32,
    /// Camera analog gain (1 = the booth's nominal gain).
    pub analog_gain: f64,
    /// Signal relative to the nominal exposure: `periods / nominal_periods * analog_gain`.
    pub scale: f64,
}

impl ProjectorExposure {
    /// The booth's nominal exposure.
    pub fn nominal(projector: u8, timing: &TimingSpec) -> Self {
        Self {
            projector,
            periods: timing.exposure_periods,
            analog_gain: 1.0,
            scale: 1.0,
        }
    }

    /// Noise of a frame divided by [`Self::scale`], in nominal units: `(shot, read)` factors such
    /// that `variance = shot * value / full_well + (read * read_noise)^2` for a value at nominal
    /// exposure. Longer exposure collects more electrons (both terms shrink); analog gain
    /// amplifies the electrons' shot noise with the signal, so only the read term shrinks.
    pub fn noise_scale(&self) -> (f64, f64) {
        let scale = self.scale.max(f64::MIN_POSITIVE);
        (self.analog_gain / scale, 1.0 / scale)
    }
}

/// Camera noise of a frame value read back in nominal units (divided by its exposure's scale,
/// full scale 1): `variance = shot_gain * value + read_sigma^2`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameNoise {
    /// Shot-noise variance per unit of value (1 / electrons at full scale, scaled by exposure).
    pub shot_gain: f64,
    /// Read noise (standard deviation, nominal units).
    pub read_sigma: f64,
}

impl FrameNoise {
    /// The noise of a camera with `full_well_e` electrons at saturation and `read_noise_dn` codes
    /// of read noise at `bit_depth` bits, for frames taken at `exposure`.
    pub fn of_camera(
        full_well_e: f64,
        read_noise_dn: f64,
        bit_depth: u32,
        exposure: &ProjectorExposure,
    ) -> Self {
        let max_code = ((1u64 << bit_depth.min(32)) - 1).max(1) as f64;
        let (shot, read) = exposure.noise_scale();
        Self {
            shot_gain: shot / full_well_e.max(1.0),
            read_sigma: read * read_noise_dn / max_code,
        }
    }

    /// Variance of a value (negative values, from noise around black, count as black).
    pub fn variance(&self, value: f64) -> f64 {
        self.shot_gain * value.max(0.0) + self.read_sigma * self.read_sigma
    }
}

/// What metering aims at.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MeteringTarget {
    /// The percentile of the metered white (largest channel per pixel, pixels above the floor)
    /// brought to `level`: a high one, so only specular highlights may saturate.
    pub percentile: f64,
    /// Target camera value of that percentile (1 = saturation).
    pub level: f64,
    /// Largest analog gain the camera may use.
    pub max_analog_gain: f64,
    /// Camera values below this are background or shadow and do not count (nominal exposure).
    pub floor: f64,
}

impl Default for MeteringTarget {
    fn default() -> Self {
        Self {
            percentile: 0.99,
            level: 0.8,
            max_analog_gain: 4.0,
            floor: 0.002,
        }
    }
}

/// Longest exposure a slot allows: the slot's refresh periods minus settle and the host window.
pub fn max_exposure_periods(timing: &TimingSpec) -> u32 {
    let slot_periods = (timing.refresh_hz / timing.fps).floor() as u32;
    slot_periods
        .saturating_sub(timing.settle_vsyncs + MIN_HOST_WINDOW_PERIODS)
        .max(timing.exposure_periods)
}

/// Chooses projector `projector`'s exposure from its white frame metered at the nominal exposure
/// (`white_max_channel`: the largest channel of each pixel). Never shorter than nominal: metering
/// lifts dim subjects; a bright one keeps the booth's exposure (its headroom was chosen for skin).
pub fn meter(
    projector: u8,
    white_max_channel: &[f32],
    timing: &TimingSpec,
    target: &MeteringTarget,
) -> ProjectorExposure {
    let nominal = ProjectorExposure::nominal(projector, timing);
    let Some(reference) = percentile_above(white_max_channel, target.floor, target.percentile)
    else {
        return nominal;
    };
    let wanted = (target.level / reference).max(1.0);
    let nominal_periods = timing.exposure_periods.max(1);
    let periods = ((nominal_periods as f64 * wanted).floor() as u32)
        .clamp(nominal_periods, max_exposure_periods(timing));
    let time_scale = periods as f64 / nominal_periods as f64;
    let analog_gain = (wanted / time_scale).clamp(1.0, target.max_analog_gain.max(1.0));
    ProjectorExposure {
        projector,
        periods,
        analog_gain,
        scale: time_scale * analog_gain,
    }
}

/// The `p`-quantile of the values at or above `floor`, if any.
fn percentile_above(values: &[f32], floor: f64, p: f64) -> Option<f64> {
    let mut kept: Vec<f32> = values
        .iter()
        .copied()
        .filter(|v| v.is_finite() && *v as f64 >= floor)
        .collect();
    if kept.is_empty() {
        return None;
    }
    let rank = ((kept.len() - 1) as f64 * p.clamp(0.0, 1.0)).round() as usize;
    let (_, value, _) = kept.select_nth_unstable_by(rank, f32::total_cmp);
    Some(*value as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::booth::Booth;

    fn timing() -> TimingSpec {
        Booth::builtin(true).timing
    }

    #[test]
    fn the_slot_keeps_settle_and_host_window() {
        // 60 Hz at 5 fps: 12 periods, 2 settle, 4 for the host: 6 periods of exposure.
        let t = timing();
        assert_eq!(max_exposure_periods(&t), 6);
        assert!(
            (t.settle_vsyncs + max_exposure_periods(&t) + MIN_HOST_WINDOW_PERIODS) as f64
                <= t.refresh_hz / t.fps
        );
    }

    #[test]
    fn a_dim_subject_gets_longer_exposure_then_gain_and_a_bright_one_keeps_nominal() {
        let t = timing();
        let target = MeteringTarget::default();
        // Bright: 99th percentile above the 0.8 target -> nominal (never shorter).
        let bright: Vec<f32> = (0..1000).map(|i| 0.9 * i as f32 / 990.0).collect();
        assert_eq!(
            meter(0, &bright, &t, &target),
            ProjectorExposure::nominal(0, &t)
        );
        // 99th percentile at 0.4 -> wanted 2x: 4 periods, no gain.
        let medium: Vec<f32> = (0..1000).map(|i| 0.4 * i as f32 / 990.0).collect();
        let e = meter(1, &medium, &t, &target);
        assert_eq!(e.periods, 4);
        assert!((e.analog_gain - 1.0).abs() < 0.01, "{e:?}");
        assert!((e.scale - 2.0).abs() < 0.02, "{e:?}");
        // 99th percentile at 0.04 -> wanted 20x: 6 periods (3x) and gain capped at 4.
        let dim: Vec<f32> = (0..1000).map(|i| 0.04 * i as f32 / 990.0).collect();
        let e = meter(2, &dim, &t, &target);
        assert_eq!(e.periods, 6);
        assert_eq!(e.analog_gain, 4.0);
        assert!((e.scale - 12.0).abs() < 1e-9);
        // Nothing above the floor (all dark): nominal.
        assert_eq!(meter(3, &[0.0; 10], &t, &target).scale, 1.0);
        // A camera whose gain the rig cannot set (`rig run` with a U3V camera): time only.
        let time_only = MeteringTarget {
            max_analog_gain: 1.0,
            ..target
        };
        let e = meter(2, &dim, &t, &time_only);
        assert_eq!((e.periods, e.analog_gain, e.scale), (6, 1.0, 3.0));
    }

    #[test]
    fn noise_in_nominal_units_shrinks_with_time_and_only_read_noise_with_gain() {
        let t = timing();
        let time_only = ProjectorExposure {
            periods: 6,
            scale: 3.0,
            ..ProjectorExposure::nominal(0, &t)
        };
        let (shot, read) = time_only.noise_scale();
        assert!((shot - 1.0 / 3.0).abs() < 1e-12 && (read - 1.0 / 3.0).abs() < 1e-12);
        let gain_only = ProjectorExposure {
            analog_gain: 4.0,
            scale: 4.0,
            ..ProjectorExposure::nominal(0, &t)
        };
        let (shot, read) = gain_only.noise_scale();
        assert!((shot - 1.0).abs() < 1e-12 && (read - 0.25).abs() < 1e-12);
    }
}

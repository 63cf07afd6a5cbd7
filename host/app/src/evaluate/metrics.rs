//! Image error metrics of the held-out evaluation (DESIGN stage 9).
//!
//! Conventions
//! - Images are linear RGB in the camera's units (1.0 = saturation of the camera), row-major,
//!   one `[f32; 3]` per pixel; a mask selects the pixels that count (true = compared).
//! - RMSE is over every compared pixel and all three channels:
//!   `sqrt(sum (a - b)^2 / (3 n))`.
//! - PSNR is relative to a peak of 1.0 (the camera's saturation level, the largest value a frame
//!   can hold): `20 log10(1 / RMSE)`; identical images give +infinity.
//! - Relative RMSE divides by the reference's energy: `sqrt(sum (a - b)^2 / sum b^2)`; it is the
//!   measure for parts of an image (e.g. the subsurface component alone), whose scale varies.

use serde::Serialize;

/// Errors of the metrics.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum MetricsError {
    /// The two images (or the mask) have different pixel counts.
    #[error(
        "images differ in size: {rendered} rendered pixels, {reference} reference, {mask} mask"
    )]
    SizeMismatch {
        rendered: usize,
        reference: usize,
        mask: usize,
    },
    /// The mask selects no pixel with finite values in both images.
    #[error("no pixel to compare (empty mask, or only non-finite values under it)")]
    NothingToCompare,
    /// The reference is zero everywhere under the mask, so a relative error is undefined.
    #[error("the reference is zero under the mask: relative error undefined")]
    ZeroReference,
}

/// Errors of one rendered image against its reference.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ImageErrors {
    /// Compared pixels (each with 3 channels).
    pub pixels: usize,
    pub rmse: f64,
    pub psnr_db: f64,
    /// `sqrt(sum err^2 / sum ref^2)`.
    pub rel_rmse: f64,
}

/// Sums of squares of one comparison, to pool several images before taking roots.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SquaredErrors {
    /// Number of compared pixels.
    pub pixels: usize,
    /// `sum (a - b)^2` over pixels and channels.
    pub error: f64,
    /// `sum b^2` over pixels and channels.
    pub reference: f64,
}

impl SquaredErrors {
    /// Accumulates `rendered` against `reference` over `mask`. Pixels with a non-finite value in
    /// either image are skipped: they are flagged pixels of an upstream stage, not errors of the
    /// model.
    pub fn accumulate(
        rendered: &[[f32; 3]],
        reference: &[[f32; 3]],
        mask: &[bool],
    ) -> Result<Self, MetricsError> {
        if rendered.len() != reference.len() || mask.len() != reference.len() {
            return Err(MetricsError::SizeMismatch {
                rendered: rendered.len(),
                reference: reference.len(),
                mask: mask.len(),
            });
        }
        let mut sums = Self::default();
        for ((a, b), &m) in rendered.iter().zip(reference).zip(mask) {
            let finite = a.iter().chain(b).all(|v| v.is_finite());
            if !m || !finite {
                continue;
            }
            sums.pixels += 1;
            for c in 0..3 {
                let (a, b) = (f64::from(a[c]), f64::from(b[c]));
                sums.error += (a - b) * (a - b);
                sums.reference += b * b;
            }
        }
        Ok(sums)
    }

    /// Pools two sets of sums (e.g. several patterns of the held-out projector).
    pub fn pooled_with(self, other: Self) -> Self {
        Self {
            pixels: self.pixels + other.pixels,
            error: self.error + other.error,
            reference: self.reference + other.reference,
        }
    }

    /// RMSE, PSNR and relative RMSE of the pooled sums.
    pub fn errors(&self) -> Result<ImageErrors, MetricsError> {
        if self.pixels == 0 {
            return Err(MetricsError::NothingToCompare);
        }
        if self.reference <= 0.0 {
            return Err(MetricsError::ZeroReference);
        }
        let rmse = (self.error / (3 * self.pixels) as f64).sqrt();
        Ok(ImageErrors {
            pixels: self.pixels,
            rmse,
            psnr_db: psnr_db(rmse),
            rel_rmse: (self.error / self.reference).sqrt(),
        })
    }
}

/// PSNR in dB for a peak value of 1.0; +infinity for a zero error.
pub fn psnr_db(rmse: f64) -> f64 {
    -20.0 * rmse.log10()
}

/// Errors of `rendered` against `reference` over `mask`.
pub fn compare(
    rendered: &[[f32; 3]],
    reference: &[[f32; 3]],
    mask: &[bool],
) -> Result<ImageErrors, MetricsError> {
    SquaredErrors::accumulate(rendered, reference, mask)?.errors()
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn hand_derived_rmse_psnr_and_relative_error() {
        // Two compared pixels, one masked out (its huge error must not count).
        let reference = [[0.5, 0.5, 0.5], [0.2, 0.4, 0.0], [9.0, 9.0, 9.0]];
        let rendered = [[0.6, 0.5, 0.5], [0.2, 0.4, 0.3], [0.0, 0.0, 0.0]];
        let mask = [true, true, false];
        let e = compare(&rendered, &reference, &mask).unwrap();
        // Squared errors: 0.01 + 0.09 = 0.10 over 6 values.
        let rmse = (0.10f64 / 6.0).sqrt();
        assert_eq!(e.pixels, 2);
        assert_relative_eq!(e.rmse, rmse, max_relative = 1e-6);
        // PSNR = 20 log10(1 / 0.1291) = 17.78 dB.
        assert_relative_eq!(e.psnr_db, 17.781_512_5, max_relative = 1e-6);
        // Reference energy 0.75 + 0.04 + 0.16 = 0.95.
        assert_relative_eq!(e.rel_rmse, (0.10f64 / 0.95).sqrt(), max_relative = 1e-6);
    }

    #[test]
    fn a_tenfold_error_costs_twenty_decibels_and_identical_images_are_infinite() {
        let reference = vec![[0.3f32, 0.2, 0.1]; 10];
        let off = |d: f32| {
            reference
                .iter()
                .map(|p| p.map(|v| v + d))
                .collect::<Vec<_>>()
        };
        let mask = vec![true; 10];
        let a = compare(&off(0.001), &reference, &mask).unwrap();
        let b = compare(&off(0.01), &reference, &mask).unwrap();
        assert_relative_eq!(a.psnr_db - b.psnr_db, 20.0, max_relative = 1e-4);
        assert_relative_eq!(a.psnr_db, 60.0, max_relative = 1e-4);
        let same = compare(&reference, &reference, &mask).unwrap();
        assert_eq!(same.rmse, 0.0);
        assert!(same.psnr_db.is_infinite() && same.psnr_db > 0.0);
    }

    #[test]
    fn pooled_sums_equal_one_comparison_of_the_concatenation() {
        let r1 = [[0.1f32, 0.2, 0.3], [0.4, 0.5, 0.6]];
        let a1 = [[0.1f32, 0.25, 0.3], [0.4, 0.5, 0.7]];
        let r2 = [[0.9f32, 0.8, 0.7]];
        let a2 = [[0.8f32, 0.8, 0.7]];
        let pooled = SquaredErrors::accumulate(&a1, &r1, &[true; 2])
            .unwrap()
            .pooled_with(SquaredErrors::accumulate(&a2, &r2, &[true]).unwrap())
            .errors()
            .unwrap();
        let all_r: Vec<_> = r1.iter().chain(&r2).copied().collect();
        let all_a: Vec<_> = a1.iter().chain(&a2).copied().collect();
        let one = compare(&all_a, &all_r, &[true; 3]).unwrap();
        assert_relative_eq!(pooled.rmse, one.rmse, max_relative = 1e-12);
        assert_relative_eq!(pooled.rel_rmse, one.rel_rmse, max_relative = 1e-12);
        assert_eq!(pooled.pixels, 3);
    }

    #[test]
    fn non_finite_pixels_are_skipped_and_bad_inputs_are_errors() {
        let reference = [[0.5f32; 3], [f32::NAN, 0.0, 0.0]];
        let rendered = [[0.5f32; 3], [0.0; 3]];
        let e = compare(&rendered, &reference, &[true, true]).unwrap();
        assert_eq!(e.pixels, 1);
        assert_eq!(e.rmse, 0.0);
        assert_eq!(
            compare(&rendered, &reference, &[false, false]),
            Err(MetricsError::NothingToCompare)
        );
        assert!(matches!(
            compare(&rendered, &reference, &[true]),
            Err(MetricsError::SizeMismatch { .. })
        ));
        assert_eq!(
            compare(&[[1.0; 3]], &[[0.0; 3]], &[true]),
            Err(MetricsError::ZeroReference)
        );
    }
}

//! Projector pixel of a chessboard corner by a local homography (Moreno & Taubin 2012, "Simple,
//! accurate, and robust projector-camera calibration"): the decoded projector coordinates of the
//! camera pixels around the corner are fitted by a homography (the board is planar, so camera and
//! projector pixels of it are related by one exactly, up to lens distortion, which is negligible
//! over a small window), and the corner's camera position is mapped through it. The fit averages
//! the quantisation and noise of hundreds of decoded pixels; a second pass without the pixels far
//! from the first fit removes decoding errors (edges of the printed squares, glints).
//!
//! Conventions
//! - Camera and projector pixel coordinates as in [`mlsss_core::calibration`] (pixel centres at integers).
//! - `decoded(x, y)` returns the projector `(u, v)` decoded at camera pixel `(x, y)`, or `None`.

use nalgebra::Vector2;

use super::homography::{apply, fit_homography};

/// Window and acceptance of the local fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalHomographyOptions {
    /// Half size of the square camera window around the corner, pixels.
    pub half_window: i64,
    /// Fewest decoded pixels, as a fraction of the window's pixels.
    pub min_fraction: f64,
    /// Pixels farther than this from the first fit (projector pixels) are left out of the second.
    pub outlier_px: f64,
}

impl Default for LocalHomographyOptions {
    fn default() -> Self {
        Self {
            half_window: 15,
            min_fraction: 0.25,
            outlier_px: 1.5,
        }
    }
}

/// The projector pixel seen at camera position `corner`, or `None` when too few pixels around it
/// decoded (shadow, outside the projector's image) or the fit is degenerate.
pub fn projector_corner(
    corner: Vector2<f64>,
    decoded: impl Fn(i64, i64) -> Option<(f64, f64)>,
    options: &LocalHomographyOptions,
) -> Option<Vector2<f64>> {
    let (cx, cy) = (corner.x.round() as i64, corner.y.round() as i64);
    let h = options.half_window;
    let mut camera = Vec::new();
    let mut projector = Vec::new();
    for y in cy - h..=cy + h {
        for x in cx - h..=cx + h {
            if let Some((u, v)) = decoded(x, y) {
                camera.push(Vector2::new(x as f64, y as f64));
                projector.push(Vector2::new(u, v));
            }
        }
    }
    let window = ((2 * h + 1) * (2 * h + 1)) as f64;
    let min_points = (window * options.min_fraction).ceil().max(8.0) as usize;
    if camera.len() < min_points {
        return None;
    }
    let (camera, projector) = median_consistent(&camera, &projector);
    if camera.len() < min_points {
        return None;
    }
    let first = fit_homography(&camera, &projector).ok()?;
    let (inliers_cam, inliers_proj): (Vec<_>, Vec<_>) = camera
        .iter()
        .zip(&projector)
        .filter(|(c, p)| apply(&first, c).is_some_and(|q| (q - *p).norm() <= options.outlier_px))
        .map(|(c, p)| (*c, *p))
        .unzip();
    if inliers_cam.len() < min_points {
        return None;
    }
    let second = fit_homography(&inliers_cam, &inliers_proj).ok()?;
    apply(&second, &corner)
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(0.0)
}

/// Removes gross decoding errors before the least-squares fit (which they would ruin): a point is
/// kept when its distance from the window's median projector coordinate is consistent with its
/// camera distance from the median camera position at the window's median scale.
fn median_consistent(
    camera: &[Vector2<f64>],
    projector: &[Vector2<f64>],
) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
    let c_med = Vector2::new(
        median(camera.iter().map(|c| c.x).collect()),
        median(camera.iter().map(|c| c.y).collect()),
    );
    let p_med = Vector2::new(
        median(projector.iter().map(|p| p.x).collect()),
        median(projector.iter().map(|p| p.y).collect()),
    );
    let scale = median(
        camera
            .iter()
            .zip(projector)
            .filter(|(c, _)| (*c - c_med).norm() > 2.0)
            .map(|(c, p)| (p - p_med).norm() / (c - c_med).norm())
            .collect(),
    );
    camera
        .iter()
        .zip(projector)
        .filter(|(c, p)| (*p - p_med).norm() <= 2.0 * scale * (*c - c_med).norm() + 3.0)
        .map(|(c, p)| (*c, *p))
        .unzip()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    #[test]
    fn maps_a_corner_through_quantised_and_corrupted_codes() {
        // A board-induced camera -> projector homography, decoded with integer codes (as OpenCV's
        // decoder gives) and a few wildly wrong pixels.
        let h = Matrix3::new(1.12, 0.05, -80.0, -0.03, 1.08, 40.0, 2e-5, -1e-5, 1.0);
        let decoded = |x: i64, y: i64| {
            if (x * 7 + y * 13) % 41 == 0 {
                return Some((900.0, 10.0)); // decoding error
            }
            if x > 520 {
                return None; // shadow
            }
            let p = apply(&h, &Vector2::new(x as f64, y as f64))?;
            Some((p.x.round(), p.y.round()))
        };
        let corner = Vector2::new(500.3, 400.7);
        let truth = apply(&h, &corner).unwrap();
        let got = projector_corner(corner, decoded, &LocalHomographyOptions::default()).unwrap();
        assert!((got - truth).norm() < 0.05, "{got} vs {truth}");
        // Deep in the shadow nothing decodes: no corner rather than a guess.
        assert_eq!(
            projector_corner(
                Vector2::new(560.0, 400.0),
                decoded,
                &LocalHomographyOptions::default()
            ),
            None
        );
    }
}

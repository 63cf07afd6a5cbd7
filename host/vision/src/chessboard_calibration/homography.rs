//! Plane-to-image homographies by the normalised direct linear transform (Hartley 1997).
//!
//! Conventions
//! - A homography `H` maps homogeneous source points to destination points: `dst ~ H src`.
//! - Points are 2-D in whatever units the caller uses (board millimetres, camera or projector
//!   pixels); the normalisation makes the fit independent of those units.

use nalgebra::{DMatrix, Matrix3, Vector2, Vector3};

/// Why a homography could not be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum HomographyError {
    /// Fewer than four correspondences, or the two lists differ in length.
    #[error(
        "a homography needs at least 4 point pairs (got {src} source and {dst} destination points)"
    )]
    TooFewPoints { src: usize, dst: usize },
    /// The points are (nearly) collinear or coincident, so the homography is not determined.
    #[error("the points are degenerate (collinear or coincident); the homography is undetermined")]
    Degenerate,
}

/// Similarity that moves the points' centroid to the origin and their mean distance to sqrt(2).
fn normalising_transform(points: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let n = points.len() as f64;
    let centroid = points.iter().fold(Vector2::zeros(), |a, p| a + p) / n;
    let mean_distance = points.iter().map(|p| (p - centroid).norm()).sum::<f64>() / n;
    if mean_distance.is_nan() || mean_distance <= 1e-12 {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_distance;
    Some(Matrix3::new(
        s,
        0.0,
        -s * centroid.x,
        0.0,
        s,
        -s * centroid.y,
        0.0,
        0.0,
        1.0,
    ))
}

/// Applies `h` to a 2-D point (`None` at infinity).
pub fn apply(h: &Matrix3<f64>, p: &Vector2<f64>) -> Option<Vector2<f64>> {
    let q = h * Vector3::new(p.x, p.y, 1.0);
    (q.z.abs() > 1e-15).then(|| Vector2::new(q.x / q.z, q.y / q.z))
}

/// Least-squares homography `dst ~ H src` with optional per-pair weights (algebraic error after
/// normalisation). `H` is scaled so that `H[(2, 2)] = 1` when possible.
pub fn fit_homography_weighted(
    src: &[Vector2<f64>],
    dst: &[Vector2<f64>],
    weights: Option<&[f64]>,
) -> Result<Matrix3<f64>, HomographyError> {
    if src.len() < 4 || src.len() != dst.len() {
        return Err(HomographyError::TooFewPoints {
            src: src.len(),
            dst: dst.len(),
        });
    }
    let ts = normalising_transform(src).ok_or(HomographyError::Degenerate)?;
    let td = normalising_transform(dst).ok_or(HomographyError::Degenerate)?;
    let mut a = DMatrix::<f64>::zeros(2 * src.len(), 9);
    for (i, (s, d)) in src.iter().zip(dst).enumerate() {
        let w = weights.map_or(1.0, |w| w[i]).sqrt();
        let s = ts * Vector3::new(s.x, s.y, 1.0);
        let d = td * Vector3::new(d.x, d.y, 1.0);
        let (x, y, u, v) = (s.x, s.y, d.x, d.y);
        let r0 = [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u];
        let r1 = [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v];
        for k in 0..9 {
            a[(2 * i, k)] = w * r0[k];
            a[(2 * i + 1, k)] = w * r1[k];
        }
    }
    // The solution is the eigenvector of A^T A with the smallest eigenvalue.
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))
        .ok_or(HomographyError::Degenerate)?;
    let sorted: Vec<f64> = {
        let mut v: Vec<f64> = eig.eigenvalues.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        v
    };
    // A second (near-)zero eigenvalue means a family of solutions: degenerate configuration.
    if sorted[1] <= 1e-10 * sorted[8].max(1e-300) {
        return Err(HomographyError::Degenerate);
    }
    let h = eig.eigenvectors.column(imin);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let td_inv = td.try_inverse().ok_or(HomographyError::Degenerate)?;
    let h = td_inv * hn * ts;
    let scale = if h[(2, 2)].abs() > 1e-12 {
        h[(2, 2)]
    } else {
        h.norm()
    };
    Ok(h / scale)
}

/// Least-squares homography `dst ~ H src` (see [`fit_homography_weighted`]).
pub fn fit_homography(
    src: &[Vector2<f64>],
    dst: &[Vector2<f64>],
) -> Result<Matrix3<f64>, HomographyError> {
    fit_homography_weighted(src, dst, None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_an_exact_homography() {
        let h = Matrix3::new(2.0, 0.3, 100.0, -0.2, 1.8, 50.0, 1e-4, -2e-4, 1.0);
        let src: Vec<Vector2<f64>> = (0..20)
            .map(|i| Vector2::new((i % 5) as f64 * 30.0, (i / 5) as f64 * 25.0))
            .collect();
        let dst: Vec<Vector2<f64>> = src.iter().map(|p| apply(&h, p).unwrap()).collect();
        let fit = fit_homography(&src, &dst).unwrap();
        assert!((fit - h).norm() < 1e-9 * h.norm(), "{fit}");
    }

    #[test]
    fn collinear_points_are_degenerate() {
        let src: Vec<Vector2<f64>> = (0..6)
            .map(|i| Vector2::new(i as f64, 2.0 * i as f64))
            .collect();
        let dst = src.clone();
        assert_eq!(fit_homography(&src, &dst), Err(HomographyError::Degenerate));
        assert!(matches!(
            fit_homography(&src[..3], &dst[..3]),
            Err(HomographyError::TooFewPoints { .. })
        ));
    }
}

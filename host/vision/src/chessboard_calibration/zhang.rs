//! Zhang's closed-form initialisation (Zhang 2000, "A flexible new technique for camera
//! calibration"): pinhole intrinsics from the homographies of several views of a plane, then each
//! view's pose from its homography. The non-linear refinement (distortion included) lives in
//! [`super::bundle_adjustment`].
//!
//! Conventions
//! - The plane is the board's z = 0; homographies map board millimetres to pixels.
//! - Poses are board-to-device, OpenCV style: `x_device = R x_board + t`.
//! - Zero skew.

use nalgebra::{DMatrix, Matrix3, Rotation3, Vector3, Vector6};

/// Why the closed form failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ZhangError {
    /// Not enough views to determine the intrinsics.
    #[error("Zhang's method needs at least {needed} board views, got {got}")]
    TooFewViews { got: usize, needed: usize },
    /// The views do not determine a valid camera (e.g. all boards parallel to each other).
    #[error("the board views do not determine the intrinsics (boards too similar in orientation?)")]
    Degenerate,
}

/// Pinhole intrinsics without distortion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }
}

/// Zhang's `v_ij` row built from columns i and j of a homography.
fn v_row(h: &Matrix3<f64>, i: usize, j: usize) -> Vector6<f64> {
    let (hi, hj) = (h.column(i), h.column(j));
    Vector6::new(
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    )
}

/// Conditions homographies for the closed form: pixel coordinates are moved to the image centre
/// and scaled to about unit size, which keeps the 6x6 system well conditioned.
fn conditioning(width: u32, height: u32) -> Matrix3<f64> {
    let s = 2.0 / (width.max(height) as f64);
    Matrix3::new(
        s,
        0.0,
        -s * 0.5 * width as f64,
        0.0,
        s,
        -s * 0.5 * height as f64,
        0.0,
        0.0,
        1.0,
    )
}

/// Intrinsics from at least three homographies (board -> pixels). With only two, or when the full
/// solution is not a valid camera, the principal point is fixed at the image centre and only the
/// focal lengths are solved for.
pub fn intrinsics_from_homographies(
    homographies: &[Matrix3<f64>],
    width: u32,
    height: u32,
) -> Result<Pinhole, ZhangError> {
    if homographies.len() < 2 {
        return Err(ZhangError::TooFewViews {
            got: homographies.len(),
            needed: 2,
        });
    }
    let c = conditioning(width, height);
    let c_inv = c.try_inverse().ok_or(ZhangError::Degenerate)?;
    let hs: Vec<Matrix3<f64>> = homographies
        .iter()
        .map(|h| {
            let hc = c * h;
            hc / hc.norm()
        })
        .collect();
    let full = (hs.len() >= 3)
        .then(|| full_closed_form(&hs))
        .flatten()
        .or_else(|| centred_closed_form(&hs))
        .ok_or(ZhangError::Degenerate)?;
    // Undo the conditioning: K = C^-1 K_c.
    let k = c_inv * full.k_matrix();
    let pinhole = Pinhole {
        fx: k[(0, 0)],
        fy: k[(1, 1)],
        cx: k[(0, 2)],
        cy: k[(1, 2)],
    };
    if pinhole.fx > 0.0 && pinhole.fy > 0.0 && pinhole.fx.is_finite() && pinhole.fy.is_finite() {
        Ok(pinhole)
    } else {
        Err(ZhangError::Degenerate)
    }
}

/// The full closed form (zero skew imposed as an extra equation).
fn full_closed_form(hs: &[Matrix3<f64>]) -> Option<Pinhole> {
    let mut v = DMatrix::<f64>::zeros(2 * hs.len() + 1, 6);
    for (k, h) in hs.iter().enumerate() {
        v.row_mut(2 * k).copy_from(&v_row(h, 0, 1).transpose());
        v.row_mut(2 * k + 1)
            .copy_from(&(v_row(h, 0, 0) - v_row(h, 1, 1)).transpose());
    }
    // Zero skew: B12 = 0.
    v[(2 * hs.len(), 1)] = 1.0;
    // Null vector of V by SVD (not the eigenvectors of V^T V, which square the condition number).
    let svd = v.svd(false, true);
    let (imin, _) = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let v_t = svd.v_t?;
    let b = v_t.row(imin).transpose();
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let denom = b11 * b22 - b12 * b12;
    if denom.abs() < 1e-300 || b11.abs() < 1e-300 {
        return None;
    }
    let cy = (b12 * b13 - b11 * b23) / denom;
    let lambda = b33 - (b13 * b13 + cy * (b12 * b13 - b11 * b23)) / b11;
    let fx2 = lambda / b11;
    let fy2 = lambda * b11 / denom;
    if !(fx2 > 0.0 && fy2 > 0.0) {
        return None;
    }
    let (fx, fy) = (fx2.sqrt(), fy2.sqrt());
    let cx = -b13 * fx * fx / lambda;
    Some(Pinhole { fx, fy, cx, cy })
}

/// With the principal point at the (conditioned) origin, each homography gives two linear
/// equations in `1/fx^2` and `1/fy^2`.
fn centred_closed_form(hs: &[Matrix3<f64>]) -> Option<Pinhole> {
    let mut a = DMatrix::<f64>::zeros(2 * hs.len(), 2);
    let mut rhs = nalgebra::DVector::<f64>::zeros(2 * hs.len());
    for (k, h) in hs.iter().enumerate() {
        let v01 = v_row(h, 0, 1);
        let vdiff = v_row(h, 0, 0) - v_row(h, 1, 1);
        // With B = diag(1/fx^2, 1/fy^2, 1): v . (b11, 0, b22, 0, 0, 1) = 0.
        a[(2 * k, 0)] = v01[0];
        a[(2 * k, 1)] = v01[2];
        rhs[2 * k] = -v01[5];
        a[(2 * k + 1, 0)] = vdiff[0];
        a[(2 * k + 1, 1)] = vdiff[2];
        rhs[2 * k + 1] = -vdiff[5];
    }
    let sol = (a.transpose() * &a).try_inverse()? * a.transpose() * rhs;
    if !(sol[0] > 0.0 && sol[1] > 0.0) {
        return None;
    }
    Some(Pinhole {
        fx: 1.0 / sol[0].sqrt(),
        fy: 1.0 / sol[1].sqrt(),
        cx: 0.0,
        cy: 0.0,
    })
}

/// The board pose of one view from its homography and the intrinsics: `[r1 r2 t] ~ K^-1 H`, with
/// the rotation made orthonormal (nearest rotation) and the board in front of the device.
pub fn pose_from_homography(
    k: &Matrix3<f64>,
    h: &Matrix3<f64>,
) -> Option<(Rotation3<f64>, Vector3<f64>)> {
    let m = k.try_inverse()? * h;
    let (c0, c1, c2) = (m.column(0), m.column(1), m.column(2));
    let mut lambda = 2.0 / (c0.norm() + c1.norm());
    if !lambda.is_finite() {
        return None;
    }
    if c2[2] * lambda < 0.0 {
        // The board must lie in front of the device (t_z > 0).
        lambda = -lambda;
    }
    let r1 = c0 * lambda;
    let r2 = c1 * lambda;
    let r3 = r1.cross(&r2);
    let approx = Matrix3::from_columns(&[r1, r2, r3]);
    let svd = approx.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u = u;
        u.column_mut(2).neg_mut();
        r = u * vt;
    }
    Some((Rotation3::from_matrix_unchecked(r), c2 * lambda))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;

    /// Exact homography of board plane -> pixels for a given camera and pose.
    fn homography(k: &Matrix3<f64>, r: &Rotation3<f64>, t: &Vector3<f64>) -> Matrix3<f64> {
        let m = r.matrix();
        k * Matrix3::from_columns(&[m.column(0).into_owned(), m.column(1).into_owned(), *t])
    }

    fn views() -> Vec<(Rotation3<f64>, Vector3<f64>)> {
        vec![
            (
                Rotation3::from_euler_angles(0.3, -0.1, 0.05),
                Vector3::new(-200.0, -150.0, 900.0),
            ),
            (
                Rotation3::from_euler_angles(-0.25, 0.35, -0.1),
                Vector3::new(-250.0, -120.0, 1000.0),
            ),
            (
                Rotation3::from_euler_angles(0.1, 0.4, 0.3),
                Vector3::new(-180.0, -200.0, 850.0),
            ),
            (
                Rotation3::from_euler_angles(-0.4, -0.3, 0.0),
                Vector3::new(-220.0, -160.0, 950.0),
            ),
        ]
    }

    #[test]
    fn closed_form_recovers_intrinsics_and_poses_from_exact_homographies() {
        let truth = Pinhole {
            fx: 1510.0,
            fy: 1490.0,
            cx: 655.0,
            cy: 500.0,
        };
        let k = truth.k_matrix();
        let hs: Vec<_> = views().iter().map(|(r, t)| homography(&k, r, t)).collect();
        let got = intrinsics_from_homographies(&hs, 1280, 1024).unwrap();
        for (a, b) in [
            (got.fx, truth.fx),
            (got.fy, truth.fy),
            (got.cx, truth.cx),
            (got.cy, truth.cy),
        ] {
            assert!((a - b).abs() < 1e-6 * b, "{got:?} vs {truth:?}");
        }
        for ((r, t), h) in views().iter().zip(&hs) {
            // Any scale of H must give the same pose.
            let (r_est, t_est) = pose_from_homography(&k, &(h * -3.7)).unwrap();
            assert!((r_est.matrix() - r.matrix()).norm() < 1e-9);
            assert!((t_est - t).norm() < 1e-6);
        }
        // Board points map to the same pixels through the recovered pose.
        let (r_est, t_est) = pose_from_homography(&k, &hs[0]).unwrap();
        let p = Vector3::new(75.0, 150.0, 0.0);
        let pix = |x: Vector3<f64>| {
            let c = k * x;
            Vector2::new(c.x / c.z, c.y / c.z)
        };
        assert!((pix(r_est * p + t_est) - pix(views()[0].0 * p + views()[0].1)).norm() < 1e-9);
    }

    #[test]
    fn two_views_fall_back_to_a_centred_principal_point() {
        let truth = Pinhole {
            fx: 1200.0,
            fy: 1250.0,
            cx: 640.0,
            cy: 512.0,
        };
        let k = truth.k_matrix();
        let hs: Vec<_> = views()[..2]
            .iter()
            .map(|(r, t)| homography(&k, r, t))
            .collect();
        let got = intrinsics_from_homographies(&hs, 1280, 1024).unwrap();
        assert!((got.fx - truth.fx).abs() < 1e-6 * truth.fx, "{got:?}");
        assert!((got.fy - truth.fy).abs() < 1e-6 * truth.fy, "{got:?}");
        assert!(matches!(
            intrinsics_from_homographies(&hs[..1], 1280, 1024),
            Err(ZhangError::TooFewViews { .. })
        ));
    }
}

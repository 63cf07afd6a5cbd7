//! A head-like surface for the virtual booth: forehead, brow ridge, eye sockets, nose, nostril
//! wings, cheeks and upper lip on an ellipsoidal face, as an analytic height field.
//!
//! Conventions
//! - World frame of the booth (mm, x right, y down, z away from the camera). The face looks towards
//!   -z; the surface is `z = depth(x, y)`, the head is the region behind it (`z > depth`).
//! - Outside the face ellipse there is no surface (the booth's hole frames the face).
//! - Normals point out of the skin (towards the camera side).

use nalgebra::{Point3, Vector3};

/// A Gaussian bump added to the face depth: negative `amplitude_mm` comes towards the camera.
#[derive(Debug, Clone, Copy)]
struct Bump {
    x: f64,
    y: f64,
    sigma_x: f64,
    sigma_y: f64,
    amplitude_mm: f64,
}

impl Bump {
    const fn new(x: f64, y: f64, sigma_x: f64, sigma_y: f64, amplitude_mm: f64) -> Self {
        Self {
            x,
            y,
            sigma_x,
            sigma_y,
            amplitude_mm,
        }
    }

    fn eval(&self, x: f64, y: f64) -> f64 {
        let dx = (x - self.x) / self.sigma_x;
        let dy = (y - self.y) / self.sigma_y;
        let q = dx * dx + dy * dy;
        if q > 30.0 {
            0.0
        } else {
            self.amplitude_mm * (-0.5 * q).exp()
        }
    }
}

/// Half-axes of the face ellipsoid (width, height, depth), mm, and its centre.
const HALF_WIDTH: f64 = 78.0;
const HALF_HEIGHT: f64 = 105.0;
const HALF_DEPTH: f64 = 85.0;
const CENTRE_Y: f64 = -5.0;
/// Depth of the ellipsoid's front point (the cheek/forehead level), mm.
const FRONT_Z: f64 = 4.0;

/// Facial features as bumps on the ellipsoid, mm (positions relative to the nose bridge/cheek line).
const FEATURES: [Bump; 13] = [
    // Brow ridges.
    Bump::new(-24.0, -32.0, 16.0, 6.0, -3.5),
    Bump::new(24.0, -32.0, 16.0, 6.0, -3.5),
    // Eye sockets (away from the camera).
    Bump::new(-32.0, -16.0, 13.0, 8.0, 9.0),
    Bump::new(32.0, -16.0, 13.0, 8.0, 9.0),
    // Cheeks.
    Bump::new(-40.0, 16.0, 17.0, 15.0, -6.0),
    Bump::new(40.0, 16.0, 17.0, 15.0, -6.0),
    // Nostril wings (alae).
    Bump::new(-13.0, 13.0, 5.0, 5.0, -7.0),
    Bump::new(13.0, 13.0, 5.0, 5.0, -7.0),
    // Nose tip.
    Bump::new(0.0, 10.0, 7.0, 6.0, -8.0),
    // Upper lip and lips.
    Bump::new(0.0, 32.0, 18.0, 7.0, -3.0),
    Bump::new(0.0, 45.0, 20.0, 5.0, -4.0),
    // Chin.
    Bump::new(0.0, 78.0, 20.0, 12.0, -6.0),
    // Temples recede.
    Bump::new(0.0, -60.0, 60.0, 20.0, 2.0),
];

/// Nose ridge: protrusion grows from the bridge (y = -30) to the tip (y = 8), width grows too.
fn nose_ridge(x: f64, y: f64) -> f64 {
    let s = ((y + 30.0) / 38.0).clamp(0.0, 1.0);
    let along = s * s * (3.0 - 2.0 * s);
    // Falls off quickly under the tip (columella to the upper lip).
    let below = if y > 10.0 {
        (-((y - 10.0) / 4.5).powi(2)).exp()
    } else {
        1.0
    };
    let above = if y < -30.0 {
        (-((y + 30.0) / 6.0).powi(2)).exp()
    } else {
        1.0
    };
    let height = (5.0 + 13.0 * along) * below * above;
    let width = 5.0 + 4.0 * along;
    -height * (-0.5 * (x / width).powi(2)).exp()
}

/// The head surface.
#[derive(Debug, Clone, Default)]
pub struct Head;

/// Step limits of the ray march, mm.
const MIN_STEP_MM: f64 = 0.15;
const MAX_STEP_MM: f64 = 3.0;
/// The head lies within these depths (nose tip to the back of the ellipsoid), mm.
const Z_MIN: f64 = -30.0;
const Z_MAX: f64 = FRONT_Z + HALF_DEPTH;

impl Head {
    /// Depth of the face surface at (x, y), or `None` outside the face ellipse.
    pub fn depth(&self, x: f64, y: f64) -> Option<f64> {
        let ex = x / HALF_WIDTH;
        let ey = (y - CENTRE_Y) / HALF_HEIGHT;
        let q = 1.0 - ex * ex - ey * ey;
        if q <= 0.0 {
            return None;
        }
        let base = FRONT_Z + HALF_DEPTH * (1.0 - q.sqrt());
        // Features fade out towards the rim so the silhouette stays the ellipsoid's.
        let fade = (q * 4.0).min(1.0);
        let features: f64 = FEATURES.iter().map(|b| b.eval(x, y)).sum::<f64>() + nose_ridge(x, y);
        Some(base + fade * features)
    }

    /// Outward unit normal at (x, y) (central differences of the analytic depth).
    pub fn normal(&self, x: f64, y: f64) -> Vector3<f64> {
        const H: f64 = 1e-4;
        let d = |x, y| self.depth(x, y).unwrap_or(Z_MAX);
        let dzdx = (d(x + H, y) - d(x - H, y)) / (2.0 * H);
        let dzdy = (d(x, y + H) - d(x, y - H)) / (2.0 * H);
        Vector3::new(dzdx, dzdy, -1.0).normalize()
    }

    /// Signed vertical gap: negative in front of the face (outside the head), positive behind it.
    fn gap(&self, p: &Point3<f64>) -> f64 {
        match self.depth(p.x, p.y) {
            Some(z) => p.z - z,
            None => -1e3,
        }
    }

    /// First intersection of the ray `origin + t dir` (t in `(t_min, t_max)`) with the face.
    pub fn intersect(
        &self,
        origin: &Point3<f64>,
        dir: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> Option<f64> {
        // Start where the ray enters the slab of depths the head occupies.
        let (mut t, t_end) = slab_range(origin, dir, t_min, t_max)?;
        let mut prev_t = t;
        let mut prev_gap = self.gap(&(origin + dir * t));
        if prev_gap >= 0.0 {
            return None; // starts inside: not a visible front surface
        }
        while t < t_end {
            let step = (-prev_gap * 0.35).clamp(MIN_STEP_MM, MAX_STEP_MM);
            t = (t + step).min(t_end);
            let gap = self.gap(&(origin + dir * t));
            if gap >= 0.0 {
                return Some(self.refine(origin, dir, [prev_t, t], [prev_gap, gap]));
            }
            prev_t = t;
            prev_gap = gap;
            if t >= t_end {
                break;
            }
        }
        None
    }

    /// The crossing between a point in front of the surface (`lo`) and one behind it (`hi`), to
    /// [`REFINE_TOLERANCE_MM`]: regula falsi with the Illinois modification (the gap is smooth
    /// across the face, so it converges in a handful of depth evaluations where bisection
    /// took 40), every third step a bisection, which bounds the steps where the gap is not
    /// smooth (the face's rim).
    /// `gaps` are the gaps at the two ends.
    fn refine(
        &self,
        origin: &Point3<f64>,
        dir: &Vector3<f64>,
        [mut lo, mut hi]: [f64; 2],
        [mut g_lo, mut g_hi]: [f64; 2],
    ) -> f64 {
        let gap_at = |t: f64| self.gap(&(origin + dir * t));
        // Which end the last two steps kept (Illinois: halve the kept end's weight).
        let mut kept: i8 = 0;
        for step in 0..REFINE_MAX_STEPS {
            if hi - lo <= REFINE_TOLERANCE_MM {
                break;
            }
            let secant = (lo * g_hi - hi * g_lo) / (g_hi - g_lo);
            // Every third step, or when the secant leaves the bracket, bisect.
            let t = if step % 3 == 2 || !(secant > lo && secant < hi) {
                0.5 * (lo + hi)
            } else {
                secant
            };
            let g = gap_at(t);
            if g.abs() <= REFINE_GAP_MM {
                return t;
            }
            if g > 0.0 {
                hi = t;
                g_hi = g;
                if kept == 1 {
                    g_lo *= 0.5;
                }
                kept = 1;
            } else {
                lo = t;
                g_lo = g;
                if kept == -1 {
                    g_hi *= 0.5;
                }
                kept = -1;
            }
        }
        0.5 * (lo + hi)
    }
}

/// Width of the bracket [`Head::refine`] stops at, mm (bisection's 40 steps stopped at 2^-40 of
/// a march step of up to 3 mm, 3e-12 mm; a camera pixel covers 0.3 mm).
const REFINE_TOLERANCE_MM: f64 = 1e-10;
/// A point whose gap to the surface is at most this is on it, mm.
const REFINE_GAP_MM: f64 = 1e-12;
/// Most depth evaluations [`Head::refine`] makes (its bisection steps alone, one in three,
/// reach the tolerance in 105).
const REFINE_MAX_STEPS: usize = 120;

/// The part of the ray inside the depth slab `Z_MIN..Z_MAX`, clipped to `(t_min, t_max)`.
fn slab_range(
    origin: &Point3<f64>,
    dir: &Vector3<f64>,
    t_min: f64,
    t_max: f64,
) -> Option<(f64, f64)> {
    if dir.z.abs() < 1e-12 {
        return ((Z_MIN..Z_MAX).contains(&origin.z)).then_some((t_min, t_max));
    }
    let ta = (Z_MIN - origin.z) / dir.z;
    let tb = (Z_MAX - origin.z) / dir.z;
    let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
    let lo = lo.max(t_min);
    let hi = hi.min(t_max);
    (lo < hi).then_some((lo, hi))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nose_is_closest_to_the_camera_and_eyes_recede() {
        let head = Head;
        let nose = head.depth(0.0, 8.0).unwrap();
        let cheek = head.depth(40.0, 16.0).unwrap();
        let eye = head.depth(32.0, -16.0).unwrap();
        assert!(nose < cheek - 10.0, "nose {nose} cheek {cheek}");
        assert!(eye > cheek, "eye {eye} cheek {cheek}");
        assert!(head.depth(200.0, 0.0).is_none());
    }

    #[test]
    fn ray_hits_the_surface_where_the_depth_says() {
        let head = Head;
        let origin = Point3::new(0.0, 0.0, -500.0);
        for &(x, y) in &[(0.0, 8.0), (25.0, -40.0), (-45.0, 20.0), (10.0, 10.0)] {
            let z = head.depth(x, y).unwrap();
            let target = Point3::new(x, y, z);
            let dir = (target - origin).normalize();
            let t = head.intersect(&origin, &dir, 0.0, 1e4).unwrap();
            let p = origin + dir * t;
            assert!((p - target).norm() < 1e-6, "{p} vs {target}");
        }
    }

    #[test]
    fn normal_faces_the_camera_and_tilts_on_the_nose_side() {
        let head = Head;
        assert!(head.normal(0.0, -45.0).z < -0.9);
        // Right side of the nose faces +x.
        assert!(head.normal(6.0, 0.0).x > 0.3);
    }
}

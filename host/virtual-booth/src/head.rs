//! A head-like surface for the virtual booth: forehead, brow ridge, eye sockets, nose, nostril
//! wings, cheeks and upper lip on an ellipsoidal face, as an analytic height field.
//!
//! Conventions
//! - World frame of the booth (mm, x right, y down, z away from the camera). The face looks towards
//!   -z; the surface is `z = depth(x, y)`, the head is the region behind it (`z > depth`).
//! - Outside the face ellipse there is no surface (the booth's hole frames the face).
//! - Normals point out of the skin (towards the camera side).

use std::sync::OnceLock;

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

/// The face's depth at (x, y) with the features' offset from `features`, or `None` outside the
/// face ellipse.
#[inline(always)]
fn depth_with_features(x: f64, y: f64, features: impl Fn(f64, f64) -> f64) -> Option<f64> {
    let ex = x / HALF_WIDTH;
    let ey = (y - CENTRE_Y) / HALF_HEIGHT;
    let q = 1.0 - ex * ex - ey * ey;
    if q <= 0.0 {
        return None;
    }
    let base = FRONT_Z + HALF_DEPTH * (1.0 - q.sqrt());
    // Features fade out towards the rim so the silhouette stays the ellipsoid's.
    let fade = (q * 4.0).min(1.0);
    Some(base + fade * features(x, y))
}

/// The features' depth offset at (x, y): the bumps, then the nose ridge, mm.
fn features(x: f64, y: f64) -> f64 {
    FEATURES.iter().map(|b| b.eval(x, y)).sum::<f64>() + nose_ridge(x, y)
}

/// Spacing of [`FeatureTable`], mm.
const GUIDE_SPACING_MM: f64 = 0.25;
/// Bound on the difference between [`Head::guide_gap`] and [`Head::gap`], mm: some thirteen
/// times the largest seen, 3.9e-3 mm, at the nose ridge's kinks (its smoothstep and fall-offs
/// are only once differentiable); elsewhere the table is within ~3e-5 mm (test
/// `the_feature_table_is_within_a_tenth_of_the_guide_margin`).
const GUIDE_MARGIN_MM: f64 = 5e-2;

/// [`features`] sampled every [`GUIDE_SPACING_MM`] over the face ellipse's bounding box and read
/// back by Catmull-Rom interpolation: the guide that sizes the ray march's steps. Why: the march
/// evaluates the depth some 25 times per camera or shadow ray, and the features' 16
/// exponentials and 26 divisions were ~17 % of a quick head scan's CPU; the table (16 reads)
/// serves every step but those within [`GUIDE_MARGIN_MM`] of the surface, where
/// [`Head::intersect`] takes the analytic depth, so hits are where the analytic march finds
/// them (to the refinement's 1e-10 mm; test `the_guided_march_finds_the_analytic_march_hits`).
/// Head and exponential samples of a quick scan: 16.7 % -> 10.7 %.
struct FeatureTable {
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    values: Vec<f32>,
}

static FEATURE_TABLE: OnceLock<FeatureTable> = OnceLock::new();

impl FeatureTable {
    /// On one thread: it runs inside [`OnceLock::get_or_init`], usually from a rayon worker; a
    /// parallel build would let that worker, waiting for its stolen halves, steal another ray's
    /// job, which would call `get_or_init` again on the same thread (a deadlock). Serially the
    /// ~530k samples take a few tens of milliseconds, once per process.
    fn build() -> Self {
        // Two samples beyond the ellipse on every side: the 4 x 4 stencil of any point inside.
        let pad = 2.0 * GUIDE_SPACING_MM;
        let (x0, y0) = (-HALF_WIDTH - pad, CENTRE_Y - HALF_HEIGHT - pad);
        let nx = ((2.0 * (HALF_WIDTH + pad)) / GUIDE_SPACING_MM).ceil() as usize + 1;
        let ny = ((2.0 * (HALF_HEIGHT + pad)) / GUIDE_SPACING_MM).ceil() as usize + 1;
        let values = (0..nx * ny)
            .map(|i| {
                let x = x0 + (i % nx) as f64 * GUIDE_SPACING_MM;
                let y = y0 + (i / nx) as f64 * GUIDE_SPACING_MM;
                features(x, y) as f32
            })
            .collect();
        Self {
            x0,
            y0,
            nx,
            ny,
            values,
        }
    }

    /// The interpolated features at (x, y); [`features`] itself where the stencil leaves the
    /// table.
    fn at(&self, x: f64, y: f64) -> f64 {
        let fx = (x - self.x0) / GUIDE_SPACING_MM;
        let fy = (y - self.y0) / GUIDE_SPACING_MM;
        let (ix, iy) = (fx.floor(), fy.floor());
        if !(ix >= 1.0 && iy >= 1.0 && ix + 2.0 < self.nx as f64 && iy + 2.0 < self.ny as f64) {
            return features(x, y);
        }
        let (wx, wy) = (catmull_rom(fx - ix), catmull_rom(fy - iy));
        let (ix, iy) = (ix as usize - 1, iy as usize - 1);
        let mut sum = 0.0;
        for (r, wy) in wy.iter().enumerate() {
            let row = &self.values[(iy + r) * self.nx + ix..][..4];
            let across: f64 = row.iter().zip(&wx).map(|(&v, w)| f64::from(v) * w).sum();
            sum += wy * across;
        }
        sum
    }
}

/// The signed vertical gap from `p` to the face's depth `depth` at its (x, y); outside the face
/// ellipse (`None`) a point counts as far in front of it.
fn gap_to(p: &Point3<f64>, depth: Option<f64>) -> f64 {
    depth.map_or(-1e3, |z| p.z - z)
}

/// Catmull-Rom weights of the four samples around fraction `t` in [0, 1).
fn catmull_rom(t: f64) -> [f64; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

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
        depth_with_features(x, y, features)
    }

    /// [`Self::depth`] with the features read from [`FeatureTable`]: within [`GUIDE_MARGIN_MM`]
    /// of it, for sizing the ray march's steps.
    fn guide_depth(&self, x: f64, y: f64) -> Option<f64> {
        let table = FEATURE_TABLE.get_or_init(FeatureTable::build);
        depth_with_features(x, y, |x, y| table.at(x, y))
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
        gap_to(p, self.depth(p.x, p.y))
    }

    /// [`Self::gap`] from [`Self::guide_depth`].
    fn guide_gap(&self, p: &Point3<f64>) -> f64 {
        gap_to(p, self.guide_depth(p.x, p.y))
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
        // Whether `prev_gap` is the analytic gap (else the guide's, below -GUIDE_MARGIN_MM).
        let mut prev_exact = true;
        while t < t_end {
            let step = (-prev_gap * 0.35).clamp(MIN_STEP_MM, MAX_STEP_MM);
            t = (t + step).min(t_end);
            // The guide sizes the steps; near the surface, where it could be on the wrong side,
            // the analytic gap decides, so every crossing is found where the analytic march
            // finds it.
            let p = origin + dir * t;
            let mut gap = self.guide_gap(&p);
            let exact = gap >= -GUIDE_MARGIN_MM;
            if exact {
                gap = self.gap(&p);
            }
            if gap >= 0.0 {
                let g_lo = if prev_exact {
                    prev_gap
                } else {
                    self.gap(&(origin + dir * prev_t))
                };
                return Some(self.refine(origin, dir, [prev_t, t], [g_lo, gap]));
            }
            prev_exact = exact;
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
    fn the_feature_table_is_within_a_tenth_of_the_guide_margin() {
        let head = Head;
        let mut worst = 0.0f64;
        for iy in 0..1900 {
            for ix in 0..1420 {
                // Offsets that fall between the table's samples, over the whole face ellipse.
                let (x, y) = (-78.0 + ix as f64 * 0.1097, -110.0 + iy as f64 * 0.1103);
                if let (Some(a), Some(g)) = (head.depth(x, y), head.guide_depth(x, y)) {
                    worst = worst.max((a - g).abs());
                }
            }
        }
        assert!(
            worst < 0.1 * GUIDE_MARGIN_MM,
            "largest guide error {worst} mm"
        );
        assert!(
            worst > 0.0,
            "the guide is the table, not the analytic depth"
        );
    }

    /// The march as it was before the guide: the analytic gap at every step.
    fn intersect_analytic(head: &Head, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let (mut t, t_end) = slab_range(origin, dir, 0.0, 1e4)?;
        let (mut prev_t, mut prev_gap) = (t, head.gap(&(origin + dir * t)));
        if prev_gap >= 0.0 {
            return None;
        }
        while t < t_end {
            t = (t + (-prev_gap * 0.35).clamp(MIN_STEP_MM, MAX_STEP_MM)).min(t_end);
            let gap = head.gap(&(origin + dir * t));
            if gap >= 0.0 {
                return Some(head.refine(origin, dir, [prev_t, t], [prev_gap, gap]));
            }
            (prev_t, prev_gap) = (t, gap);
        }
        None
    }

    #[test]
    fn the_guided_march_finds_the_analytic_march_hits() {
        let head = Head;
        let camera = Point3::new(3.0, -4.0, -500.0);
        let projector = Point3::new(-260.0, -80.0, -430.0);
        let (mut hits, mut shadows) = (0, 0);
        for iy in 0..120 {
            for ix in 0..90 {
                let target = Point3::new(-85.0 + ix as f64 * 1.9, -115.0 + iy as f64 * 1.77, 0.0);
                let dir = (target - camera).normalize();
                let got = head.intersect(&camera, &dir, 0.0, 1e4);
                let want = intersect_analytic(&head, &camera, &dir);
                match (got, want) {
                    (Some(a), Some(b)) => assert!((a - b).abs() < 1e-9, "{target}: {a} vs {b}"),
                    (None, None) => continue,
                    other => panic!("camera ray to {target}: {other:?}"),
                }
                hits += 1;
                // The shadow ray from the hit towards a projector on the left.
                let p = camera + dir * got.unwrap_or_default();
                let start = p + head.normal(p.x, p.y) * 0.02;
                let to = (projector - start).normalize();
                let got = head.intersect(&start, &to, 0.0, 1e4);
                let want = intersect_analytic(&head, &start, &to);
                assert_eq!(got.is_some(), want.is_some(), "shadow ray from {p}");
                shadows += usize::from(got.is_some());
            }
        }
        assert!(
            hits > 5000 && shadows > 50,
            "{hits} hits, {shadows} shadowed"
        );
    }

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

//! End to end on a tiny scene with a hand-derived truth: a plane lit by four distant projectors,
//! an inhomogeneous two-layer medium (deep layer twice as strong on the right half), global slit
//! frames summed source column by source column from the model's definition (paper eq. 4, the
//! integral along the slit done in closed form). Profiles -> layered fit from 3 projectors ->
//! relight the 4th: the held-out global images match, and inhomogeneous beats homogeneous.

use nalgebra::Vector3;

use super::fit::{FitOptions, fit_dipole_model, fit_model, pixel_amplitudes};
use super::mixture::EmConfig;
use super::profiles::{
    Falloff, ProjectorIllumination, SlitFrame, SlitSweep, irradiance, pixel_geometry,
};
use super::relight::{pattern_irradiance, shifts};
use super::render::{RenderOptions, render_global};
use super::surface::{Surface, ViewRay};
use mlsss_core::capture::{Axis, Pattern};

const W: usize = 48;
const H: usize = 20;
const PITCH: f64 = 0.25; // mm per camera pixel = 1 projector pixel
const FAR: f64 = 1e5;
const ETA: f64 = 1.4;
const CHANNEL_SCALE: [f64; 3] = [1.0, 0.7, 0.5];

/// (depth mm, sigma mm, weight left, weight right)
const LAYERS: [(f64, f64, f64, f64); 2] = [(0.1, 0.3, 0.25, 0.25), (0.6, 0.7, 0.12, 0.24)];

fn surface() -> Surface {
    let centre = Vector3::new(W as f64 * PITCH / 2.0, H as f64 * PITCH / 2.0, 0.0);
    Surface::flat(W, H, PITCH, centre + Vector3::new(0.0, 0.0, FAR))
}

fn projector_centre(k: usize) -> Vector3<f64> {
    let az = (k as f64) * std::f64::consts::FRAC_PI_2 + 0.3;
    let el = 50f64.to_radians();
    let centre = Vector3::new(W as f64 * PITCH / 2.0, H as f64 * PITCH / 2.0, 0.0);
    centre + FAR * Vector3::new(az.cos() * el.sin(), az.sin() * el.sin(), el.cos())
}

fn weight(layer: usize, x: usize) -> f64 {
    if x < W / 2 {
        LAYERS[layer].2
    } else {
        LAYERS[layer].3
    }
}

fn g1(d: f64, sigma: f64) -> f64 {
    (-0.5 * (d / sigma).powi(2)).exp() / (sigma * (2.0 * std::f64::consts::PI).sqrt())
}

/// Whether the pattern lights a source column (or row), the pattern being constant the other way.
type LitAlong<'a> = Box<dyn Fn(i64) -> f32 + 'a>;

/// Truth global image of projector k under white or a slit pattern.
fn truth_global(s: &Surface, k: usize, pattern: &Pattern) -> Vec<[f32; 3]> {
    let e0 = irradiance(
        &s.points[0],
        &s.normals[0],
        &projector_centre(k),
        &Falloff::Isotropic,
    );
    let t = super::relight::shifts(s, &projector_centre(k), ETA, ViewRay::Refracted)[0].unwrap();
    let wrap = |c: i64, n: i64| c.rem_euclid(n) as u32;
    let (lit_x, lit_y): (LitAlong, LitAlong) = match *pattern {
        Pattern::White => (Box::new(|_| 1.0), Box::new(|_| 1.0)),
        Pattern::Slit { axis: Axis::X, .. } => (
            Box::new(|x| pattern.value(wrap(x, 1024), 0)),
            Box::new(|_| 1.0),
        ),
        Pattern::Slit { axis: Axis::Y, .. } => (
            Box::new(|_| 1.0),
            Box::new(|y| pattern.value(0, wrap(y, 768))),
        ),
        _ => unreachable!("the test uses white and slits only"),
    };
    let mut out = vec![[0.0f32; 3]; W * H];
    for yo in 0..H {
        for xo in 0..W {
            let mut v = 0.0;
            for (l, &(z, sigma, _, _)) in LAYERS.iter().enumerate() {
                // Sum over source pixels of w E dA G2. Weights vary along x only and the patterns
                // along one axis only, so the 2-D sum factors into two 1-D sums; the source grid
                // extends beyond the image (the plane is infinite, lit everywhere).
                let sx: f64 = (-30..W as i64 + 30)
                    .map(|xs| {
                        let wx = weight(l, xs.clamp(0, W as i64 - 1) as usize);
                        let gx = g1((xo as f64 - xs as f64) * PITCH - z * t.x, sigma) * PITCH;
                        wx * gx * f64::from(lit_x(xs))
                    })
                    .sum();
                let sy: f64 = (-30..H as i64 + 30)
                    .map(|ys| {
                        let gy = g1((yo as f64 - ys as f64) * PITCH - z * t.y, sigma) * PITCH;
                        gy * f64::from(lit_y(ys))
                    })
                    .sum();
                v += e0 * sx * sy;
            }
            for c in 0..3 {
                out[yo * W + xo][c] = (v * CHANNEL_SCALE[c]) as f32;
            }
        }
    }
    out
}

/// A booth's slit sweep: 10 slits 3 px wide every 30 px, offsets 3 px apart (consecutive
/// slits share an edge), along x then y.
pub(crate) fn slit_patterns() -> Vec<Pattern> {
    [Axis::X, Axis::Y]
        .into_iter()
        .flat_map(|axis| {
            (0..10).map(move |k| Pattern::Slit {
                axis,
                width: 3,
                period: 30,
                offset: 3 * k,
            })
        })
        .collect()
}

fn rel_rmse(a: &[[f32; 3]], b: &[[f32; 3]], cols: std::ops::Range<usize>) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for y in 3..H - 3 {
        for x in cols.clone() {
            let (p, q) = (a[y * W + x][0] as f64, b[y * W + x][0] as f64);
            num += (p - q).powi(2);
            den += q * q;
        }
    }
    (num / den).sqrt()
}

#[test]
fn profiles_fit_and_relight_a_held_out_projector() {
    let s = surface();
    let coords: Vec<Option<(f32, f32)>> = (0..W * H)
        .map(|i| Some(((i % W) as f32, (i / W) as f32)))
        .collect();
    let patterns = slit_patterns();
    let training = [0usize, 1, 2];
    let frames: Vec<Vec<Vec<[f32; 3]>>> = training
        .iter()
        .map(|&k| patterns.iter().map(|p| truth_global(&s, k, p)).collect())
        .collect();
    let views: Vec<ProjectorIllumination> = training
        .iter()
        .map(|&k| ProjectorIllumination {
            centre: projector_centre(k),
            falloff: Falloff::Isotropic,
            coords: &coords,
        })
        .collect();
    let geometries: Vec<_> = views
        .iter()
        .map(|v| pixel_geometry(&s, v, ETA, ViewRay::Refracted).unwrap())
        .collect();
    let sweeps: Vec<SlitSweep> = frames
        .iter()
        .map(|f| {
            let sf: Vec<SlitFrame> = patterns
                .iter()
                .zip(f)
                .map(|(p, g)| SlitFrame {
                    pattern: *p,
                    global: g,
                })
                .collect();
            SlitSweep::new(&sf, W * H).unwrap()
        })
        .collect();
    let opts = FitOptions {
        em: EmConfig {
            components: 8,
            max_iterations: 100,
            ..EmConfig::default()
        },
        block: 4,
        spacing_pixels: 6,
        ..FitOptions::default()
    };
    let fit = fit_model(&s, &geometries, &sweeps, &opts).unwrap();
    assert!(fit.stats.fits > 0 && fit.stats.depth_spacing_mm.is_finite());

    // Held-out projector 3: white and one slit frame along each axis.
    let held = ProjectorIllumination {
        centre: projector_centre(3),
        falloff: Falloff::Isotropic,
        coords: &coords,
    };
    let shift = shifts(&s, &held.centre, ETA, ViewRay::Refracted);
    let homogeneous = fit.model.homogeneous(&s.mask, &s.mask);
    let dipole = fit_dipole_model(
        &s,
        &geometries,
        &sweeps,
        ETA,
        1,
        &pixel_amplitudes(&s, &geometries, &sweeps),
    )
    .unwrap();
    let ropts = RenderOptions::default();
    for pattern in [
        Pattern::White,
        Pattern::Slit {
            axis: Axis::X,
            width: 3,
            period: 30,
            offset: 12,
        },
        Pattern::Slit {
            axis: Axis::Y,
            width: 3,
            period: 30,
            offset: 6,
        },
    ] {
        let e = pattern_irradiance(&s, &held, &pattern, 0.0, 0.0);
        let truth = truth_global(&s, 3, &pattern);
        let ours = render_global(&s, &e, &shift, &fit.model, &ropts).unwrap();
        let homog = render_global(&s, &e, &shift, &homogeneous, &ropts).unwrap();
        let dip = render_global(&s, &e, &shift, &dipole, &ropts).unwrap();
        let dipole_err = rel_rmse(&dip, &truth, 6..W - 6);
        // Interior columns, away from the image border and the material edge.
        let ours_err = rel_rmse(&ours, &truth, 6..W - 6);
        let homog_err = rel_rmse(&homog, &truth, 6..W - 6);
        eprintln!(
            "held-out {}: relative RMSE ours {ours_err:.4}, homogeneous {homog_err:.4}, \
             dipole {dipole_err:.4}, D {:.3} mm",
            pattern.label(),
            fit.stats.depth_spacing_mm
        );
        assert!(ours_err < 0.08, "{pattern:?}: relative RMSE {ours_err}");
        assert!(
            ours_err < homog_err,
            "{pattern:?}: ours {ours_err} vs homogeneous {homog_err}"
        );
        // Channels keep their ratios.
        let i = 10 * W + 12;
        assert!((ours[i][2] / ours[i][0] - 0.5).abs() < 0.02);
    }
}

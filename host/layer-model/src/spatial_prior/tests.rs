//! Tests of the spatial prior: shape merging, amplitude statistics, and the prior on synthetic
//! captures fitted like the fit stage.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::amplitude::{amplitude_stats, loo_kappa};
use super::shapes::{SIGMA_BINS, Shape, merged_mixture, without_faint};
use super::*;
use crate::fit::{FitOptions, fit_model};
use crate::mixture::EmConfig;
use crate::profiles::{AxisGeometry, GeometryMap, PixelGeometry, SlitFrame};
use crate::render::{RenderOptions, SplatLayer};
use mlsss_core::capture::{Axis, Pattern};

const SIZE: usize = 30;
const PERIOD: u32 = 10;
/// The true layer shape everywhere: (weight fraction, sigma mm).
const TRUE_SHAPE: [(f64, f64); 2] = [(0.6, 0.8), (0.4, 2.5)];

fn layer(index: u16, weight: f32, sigma_mm: f32) -> SplatLayer {
    SplatLayer {
        index,
        weight,
        sigma_mm,
        depth_mm: 0.0,
    }
}

#[test]
fn merging_keeps_bins_apart_and_moment_matches_within_a_bin() {
    // Two shapes: sigmas 1.0 and 1.05 share a bin (ratio 1.25), 3.0 does not.
    let a = vec![layer(0, 0.5, 1.0), layer(1, 0.5, 3.0)];
    let b = vec![layer(0, 1.0, 1.05)];
    let m = merged_mixture([a, b].iter(), 1.25).unwrap();
    assert_eq!(m.len(), 2, "{m:?}");
    let narrow = m.iter().find(|l| l.sigma_mm < 2.0).unwrap();
    let wide = m.iter().find(|l| l.sigma_mm > 2.0).unwrap();
    // Equal-weight mixture: narrow (0.5 + 1.0) / 2, wide 0.5 / 2.
    assert!((narrow.weight - 0.75).abs() < 1e-6);
    assert!((wide.weight - 0.25).abs() < 1e-6);
    let var = (0.5 * 1.0 + 1.0 * 1.05f64.powi(2)) / 1.5;
    assert!((f64::from(narrow.sigma_mm) - var.sqrt()).abs() < 1e-5);
    assert_eq!(f64::from(wide.sigma_mm), 3.0);
    // At depth 0 every index is one family: codes share depth index 0 and differ by bin.
    assert_eq!(narrow.index / SIGMA_BINS, 0);
    assert_eq!(wide.index / SIGMA_BINS, 0);
    assert_ne!(narrow.index, wide.index);
    // Same sigma, different depths: one layer at the weight-averaged depth.
    let deep = |index: u16, depth: f32| SplatLayer {
        depth_mm: depth,
        ..layer(index, 0.5, 1.0)
    };
    let c = vec![deep(1, 0.1), deep(2, 0.2)];
    let d = vec![deep(1, 0.1)];
    let m = merged_mixture([c, d].iter(), 1.25).unwrap();
    assert_eq!(m.len(), 1, "{m:?}");
    assert!((m[0].weight - 0.75).abs() < 1e-6);
    // Weights 0.5 at 0.1 (twice) and 0.5 at 0.2: mean depth 0.4 / 3.
    assert!((f64::from(m[0].depth_mm) - 0.4 / 3.0).abs() < 1e-6, "{m:?}");
    assert!(merged_mixture(std::iter::empty(), 1.25).is_none());
}

/// Regression (full-size model 1.8x too large): faint layers of a shape are not stored, and
/// a default render of the model does not change for it, to the bit.
#[test]
fn faint_layers_are_dropped_without_changing_a_default_render() {
    let shape = vec![
        layer(0, 0.55, 0.3),
        layer(1, 0.0009, 0.5),
        layer(2, 0.4, 1.2),
        layer(3, 0.0004, 2.5),
        layer(4, 0.0487, 4.0),
    ];
    let kept = without_faint(shape.clone());
    assert_eq!(kept, vec![shape[0], shape[2], shape[4]]);

    let (w, h, pitch) = (48, 40, 0.1);
    let surface = Surface::flat(w, h, pitch, Vector3::new(0.0, 0.0, 1e4));
    let mut rng = Pcg64::seed_from_u64(5);
    let irradiance: Vec<f32> = (0..w * h).map(|_| rng.gen_range(0.0..1.0)).collect();
    let amplitude: Vec<f32> = (0..w * h).map(|_| rng.gen_range(0.2..0.9)).collect();
    let scaled = |s: &Shape, i: usize| -> Vec<SplatLayer> {
        s.iter()
            .map(|l| SplatLayer {
                weight: l.weight * amplitude[i],
                ..*l
            })
            .collect()
    };
    let shift = vec![Some(Vector3::new(0.3, -0.2, 0.0)); w * h];
    let opts = RenderOptions::default();
    let render = |s: &Shape| {
        let model = LayerModel::from_fn(w, h, |i, _| scaled(s, i));
        crate::render::render_global(&surface, &irradiance, &shift, &model, &opts).unwrap()
    };
    assert_eq!(render(&shape), render(&kept));
}

#[test]
fn variance_components_are_recovered_from_per_projector_estimates() {
    // True relative deviations with variance 0.04, three projectors with noise variance 0.01.
    let mut rng = Pcg64::seed_from_u64(7);
    let mut normal = |sd: f64| {
        let (u, v): (f64, f64) = (rng.r#gen::<f64>().max(1e-12), rng.r#gen());
        sd * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let mean = 2.0;
    let lists: Vec<Vec<f64>> = (0..20_000)
        .map(|_| {
            let truth = 1.0 + normal(0.2);
            (0..3).map(|_| mean * (truth + normal(0.1))).collect()
        })
        .collect();
    let st = amplitude_stats(&lists, mean);
    assert!((st.signal - 0.04).abs() < 0.003, "{st:?}");
    assert!((st.noise - 0.01).abs() < 0.0005, "{st:?}");
    // Posterior keep fraction for 3 projectors: 0.04 / (0.04 + 0.01 / 3).
    assert!((st.keep(3) - 0.04 / (0.04 + 0.01 / 3.0)).abs() < 0.01);
    // One estimate per pixel: no noise estimate, nothing shrunk.
    let single: Vec<Vec<f64>> = lists.iter().map(|l| vec![l[0]]).collect();
    assert_eq!(amplitude_stats(&single, mean).keep(1), 1.0);
}

#[test]
fn loo_kappa_recovers_the_posterior_keep_fraction() {
    let mut rng = Pcg64::seed_from_u64(11);
    let mut normal = |sd: f64| {
        let (u, v): (f64, f64) = (rng.r#gen::<f64>().max(1e-12), rng.r#gen());
        sd * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let mean = 0.3;
    // True relative deviations with variance 0.04, three projectors with independent noise
    // of variance 0.01: the posterior keeps 0.04 / (0.04 + 0.01 / 3) of a pixel's deviation.
    let plain: Vec<Vec<f64>> = (0..20_000)
        .map(|_| {
            let t = normal(0.2);
            (0..3).map(|_| mean * (1.0 + t + normal(0.1))).collect()
        })
        .collect();
    let (kappa, _) = loo_kappa(&plain, mean).unwrap();
    let want = 0.04 / (0.04 + 0.01 / 3.0);
    assert!((3.0 / (3.0 + kappa) - want).abs() < 0.03, "kappa {kappa}");
    // No true variation, only noise: almost everything is shrunk away.
    let noise: Vec<Vec<f64>> = (0..20_000)
        .map(|_| (0..3).map(|_| mean * (1.0 + normal(0.1))).collect())
        .collect();
    let (kappa, _) = loo_kappa(&noise, mean).unwrap();
    assert!(3.0 / (3.0 + kappa) < 0.2, "kappa {kappa}");
}

/// Boxed Gaussian mass of a 1 mm slit at distance `s` (mm), with the comb's neighbours, for
/// the true shape with its sigmas scaled by `scale`.
fn true_profile(s: f64, scale: f64) -> f64 {
    TRUE_SHAPE
        .iter()
        .map(|&(w, sigma)| {
            let k = scale * sigma * std::f64::consts::SQRT_2;
            (-1..=1)
                .map(|m| {
                    let d = s - f64::from(m) * f64::from(PERIOD);
                    0.5 * (libm::erf((d + 0.5) / k) - libm::erf((d - 0.5) / k))
                })
                .sum::<f64>()
                * w
        })
        .sum()
}

/// A synthetic capture: a flat `SIZE x SIZE` patch, 1 mm per projector pixel, three
/// projectors with their own irradiance, each pixel's irradiance model off by a random
/// factor per projector (the non-transferable error), camera noise on the slit frames.
struct Scene {
    surface: Surface,
    geometries: Vec<GeometryMap>,
    frames: Vec<Vec<(Pattern, Vec<[f32; 3]>)>>,
}

fn scene(amplitude: impl Fn(usize) -> f64, scale: impl Fn(usize) -> f64, seed: u64) -> Scene {
    let n = SIZE * SIZE;
    let mut rng = Pcg64::seed_from_u64(seed);
    let surface = Surface {
        width: SIZE,
        height: SIZE,
        points: (0..n)
            .map(|i| Vector3::new((i % SIZE) as f64, (i / SIZE) as f64, 0.0))
            .collect(),
        normals: vec![Vector3::z(); n],
        mask: vec![true; n],
        camera_centre: Vector3::new(15.0, 15.0, 1000.0),
    };
    let axis = AxisGeometry {
        px_per_mm: 1.0,
        shift_per_depth: 0.0,
    };
    let mut geometries = Vec::new();
    let mut frames = Vec::new();
    for (p, irradiance) in [1.0, 0.8, 1.2].into_iter().enumerate() {
        let offset = 0.37 * p as f64;
        let geo: GeometryMap = (0..n)
            .map(|i| {
                Some(PixelGeometry {
                    coords: ((i % SIZE) as f64 + offset, (i / SIZE) as f64 - offset),
                    irradiance,
                    axes: [axis; 2],
                    shift: Vector3::zeros(),
                })
            })
            .collect();
        // The light really delivered differs from the model's by a few per cent per pixel.
        let delivered: Vec<f64> = (0..n)
            .map(|_| irradiance * (1.0 + 0.08 * (rng.r#gen::<f64>() - 0.5) * 3.46))
            .collect();
        let mut sweep = Vec::new();
        for (a, ax) in [Axis::X, Axis::Y].into_iter().enumerate() {
            for o in 0..PERIOD {
                let pattern = Pattern::Slit {
                    axis: ax,
                    width: 1,
                    period: PERIOD,
                    offset: o,
                };
                let img: Vec<[f32; 3]> = (0..n)
                    .map(|i| {
                        let g = geo.get(i).unwrap();
                        let coord = if a == 0 { g.coords.0 } else { g.coords.1 };
                        let s = super::super::profiles::slit_distance_px(coord, 1, PERIOD, o);
                        let clean = delivered[i] * amplitude(i) * true_profile(s, scale(i));
                        std::array::from_fn(|_| {
                            let noise = 0.004 * (rng.r#gen::<f64>() - 0.5) * 3.46;
                            (clean + noise) as f32
                        })
                    })
                    .collect();
                sweep.push((pattern, img));
            }
        }
        geometries.push(geo);
        frames.push(sweep);
    }
    Scene {
        surface,
        geometries,
        frames,
    }
}

/// The scene's slit frames as the fit stage sees them, one list per projector.
fn slit_frames(s: &Scene) -> Vec<Vec<SlitFrame<'_>>> {
    s.frames
        .iter()
        .map(|f| {
            f.iter()
                .map(|(pattern, img)| SlitFrame {
                    pattern: *pattern,
                    global: img,
                })
                .collect()
        })
        .collect()
}

/// One slit sweep per projector over `frames`.
fn sweeps<'a>(frames: &'a [Vec<SlitFrame<'a>>]) -> Vec<SlitSweep<'a>> {
    frames
        .iter()
        .map(|f| SlitSweep::new(f, SIZE * SIZE).unwrap())
        .collect()
}

/// Fits the scene like the fit stage (3 x 3 tiles, up to 4 components) and applies the prior.
fn fit_and_regularise(s: &Scene) -> (LayerModel, LayerModel, PriorReport) {
    let slit_frames = slit_frames(s);
    let sweeps = sweeps(&slit_frames);
    let opts = FitOptions {
        em: EmConfig {
            components: 3,
            max_iterations: 40,
            ..EmConfig::default()
        },
        depth_spacing: Some(0.0),
        block: 3,
        ..FitOptions::default()
    };
    let fit = fit_model(&s.surface, &s.geometries, &sweeps, &opts).unwrap();
    let (out, report) = regularise(
        &fit.model,
        &s.surface,
        &s.geometries,
        &sweeps,
        3,
        0.0,
        &PriorOptions::default(),
    )
    .unwrap();
    (fit.model, out, report)
}

fn total(model: &LayerModel, i: usize, c: usize) -> f64 {
    model.layers(i, c).iter().map(|l| f64::from(l.weight)).sum()
}

/// Second moment `sum w sigma^2 / sum w` of a pixel's kernel (mm^2).
fn second_moment(model: &LayerModel, i: usize, c: usize) -> f64 {
    let l = model.layers(i, c);
    l.iter()
        .map(|l| f64::from(l.weight) * f64::from(l.sigma_mm).powi(2))
        .sum::<f64>()
        / total(model, i, c)
}

fn rel_rms(values: impl Iterator<Item = (f64, f64)>) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for (got, want) in values {
        num += (got - want).powi(2);
        den += want * want;
    }
    (num / den).sqrt()
}

#[test]
fn free_em_fit_stage_recovers_amplitude_and_width_of_uniform_skin() {
    // `--em free` (the paper's variant) through the fit stage on the synthetic patch: every
    // pixel gets layers, the absolute weights add up to the true amplitude (the flux
    // normalisation), and the kernel's second moment is the truth's within the loss the
    // paper's rank averaging of sigmas causes.
    let truth = 0.3;
    let s = scene(|_| truth, |_| 1.0, 13);
    let slit_frames = slit_frames(&s);
    let sweeps = sweeps(&slit_frames);
    let opts = FitOptions {
        em: EmConfig {
            components: 3,
            max_iterations: 60,
            ..EmConfig::default()
        },
        variant: crate::fit::EmVariant::Free,
        block: 3,
        ..FitOptions::default()
    };
    let fit = fit_model(&s.surface, &s.geometries, &sweeps, &opts).unwrap();
    let n = SIZE * SIZE;
    assert_eq!(fit.stats.depth_spacing_mm, 0.0);
    assert!((0..n).all(|i| !fit.model.layers(i, 0).is_empty()));
    let amplitude = rel_rms((0..n).map(|i| (total(&fit.model, i, 0), truth)));
    assert!(amplitude < 0.1, "amplitude rel RMS error {amplitude}");
    let m2: f64 = TRUE_SHAPE.iter().map(|(w, s)| w * s * s).sum();
    let width = rel_rms((0..n).map(|i| (second_moment(&fit.model, i, 0), m2)));
    assert!(width < 0.35, "kernel second moment rel RMS error {width}");
    // No depth without geometry that moves the layers (shift_per_depth 0 here).
    assert!((0..n).all(|i| {
        fit.model
            .layers(i, 0)
            .iter()
            .all(|l| l.depth_mm == 0.0 && l.weight.is_finite() && l.sigma_mm > 0.0)
    }));
}

#[test]
fn uniform_skin_noise_is_shrunk_away() {
    let truth = 0.3;
    let s = scene(|_| truth, |_| 1.0, 11);
    let (raw, reg, report) = fit_and_regularise(&s);
    let n = SIZE * SIZE;
    let err = |m: &LayerModel| rel_rms((0..n).map(|i| (total(m, i, 0), truth)));
    let (before, after) = (err(&raw), err(&reg));
    // Nothing real varies: most of each pixel's deviation is noise and goes.
    assert!(report.channels[0].mean_keep_fraction < 0.5, "{report:?}");
    assert!(after < 0.6 * before, "amplitude error {before} -> {after}");
    // Shapes: one shape fits all, so the cross-validation pools neighbours, and the kernel's
    // second moment gets closer to the truth's.
    assert_ne!(report.channels[0].shape, "r0", "{report:?}");
    let m2: f64 = TRUE_SHAPE.iter().map(|(w, s)| w * s * s).sum();
    let shape_err = |m: &LayerModel| rel_rms((0..n).map(|i| (second_moment(m, i, 0), m2)));
    let (sb, sa) = (shape_err(&raw), shape_err(&reg));
    assert!(sa < sb, "second-moment error {sb} -> {sa}");
}

#[test]
fn a_real_material_edge_is_kept() {
    // Two materials: the left half re-emits twice what the right half does.
    let amp = |i: usize| if i % SIZE < SIZE / 2 { 0.4 } else { 0.2 };
    let s = scene(amp, |_| 1.0, 12);
    let (raw, reg, report) = fit_and_regularise(&s);
    // The true variation dwarfs the noise: deviations are kept.
    assert!(report.channels[0].mean_keep_fraction > 0.9, "{report:?}");
    let half_mean = |m: &LayerModel, left: bool| {
        let px: Vec<usize> = (0..SIZE * SIZE)
            .filter(|i| (i % SIZE < SIZE / 2 - 2) == left && (i % SIZE > SIZE / 2 + 1) != left)
            .collect();
        px.iter().map(|&i| total(m, i, 1)).sum::<f64>() / px.len() as f64
    };
    for (left, want) in [(true, 0.4), (false, 0.2)] {
        let (b, a) = (half_mean(&raw, left), half_mean(&reg, left));
        assert!(
            (a - want).abs() < 0.05 * want,
            "left={left}: {b} -> {a}, truth {want}"
        );
    }
    let n = SIZE * SIZE;
    let err = |m: &LayerModel| rel_rms((0..n).map(|i| (total(m, i, 1), amp(i))));
    assert!(
        err(&reg) <= err(&raw) * 1.02,
        "{} -> {}",
        err(&raw),
        err(&reg)
    );
}

#[test]
fn shapes_are_not_pooled_across_a_change_of_material() {
    // Same amplitude, but the right half scatters twice as wide: one global shape would be
    // wrong on both sides, so the cross-validation keeps shapes local.
    let scale = |i: usize| if i % SIZE < SIZE / 2 { 1.0 } else { 2.0 };
    let s = scene(|_| 0.3, scale, 14);
    let (raw, reg, report) = fit_and_regularise(&s);
    assert!(
        ["r0", "r1"].contains(&report.channels[0].shape.as_str()),
        "{report:?}"
    );
    let m2 = |i: usize| -> f64 {
        TRUE_SHAPE
            .iter()
            .map(|(w, s)| w * (s * scale(i)).powi(2))
            .sum()
    };
    let n = SIZE * SIZE;
    let shape_err = |m: &LayerModel| rel_rms((0..n).map(|i| (second_moment(m, i, 0), m2(i))));
    let (sb, sa) = (shape_err(&raw), shape_err(&reg));
    assert!(sa <= sb * 1.001, "second-moment error {sb} -> {sa}");
}

#[test]
fn switched_off_the_model_is_untouched() {
    let s = scene(|_| 0.3, |_| 1.0, 13);
    let raw = LayerModel::from_fn(SIZE, SIZE, |i, c| {
        vec![layer(0, 0.3 + (i % 7) as f32 * 0.01, 1.0 + c as f32)]
    });
    let mut same = raw.clone();
    let geometries = s.geometries.clone();
    let frames: Vec<SlitFrame> = s.frames[0]
        .iter()
        .map(|(pattern, img)| SlitFrame {
            pattern: *pattern,
            global: img,
        })
        .collect();
    let sweeps = vec![SlitSweep::new(&frames, SIZE * SIZE).unwrap()];
    let report = regularise_in_place(
        false,
        &mut same,
        &s.surface,
        &geometries[..1],
        &sweeps,
        3,
        0.0,
    )
    .unwrap();
    assert!(report.is_none());
    assert_eq!(same, raw);
    // Mismatched inputs are refused, not guessed.
    assert!(matches!(
        regularise_in_place(true, &mut same, &s.surface, &geometries, &sweeps, 3, 0.0),
        Err(SpatialPriorError::ProjectorCount { .. })
    ));
}

/// The log widths as they were computed before [`SlitSweep::samples_rgb`]: from each axis'
/// profile, channel by channel (the reference).
fn log_widths_from_profiles(inputs: &tiles::Inputs, i: usize, c: usize) -> Vec<Option<f64>> {
    inputs
        .geometries
        .iter()
        .zip(inputs.sweeps)
        .map(|(geo, sweep)| {
            let g = *geo.get(i)?;
            let (mut m0, mut m2) = (0.0, 0.0);
            for a in 0..2 {
                if let Some(p) = sweep.profile(i, c, a, &g) {
                    for s in &p.samples {
                        let y = s.y.max(0.0);
                        m0 += y;
                        m2 += y * s.s * s.s;
                    }
                }
            }
            (m0 > 0.0 && m2 > 0.0).then(|| (m2 / m0).ln())
        })
        .collect()
}

/// The three channels' log widths from one pass over the samples equal the profiles' channel
/// by channel, bit for bit: dense sweeps, and stacked ones that do not hold every pixel, with
/// pixels some projector does not light and negative (noisy, clamped) slit values.
#[test]
fn log_widths_of_all_channels_at_once_equal_the_profiles_bit_for_bit() {
    use crate::profiles::SlitStack;
    let mut s = scene(|_| 0.5, |_| 1.0, 71);
    let n = SIZE * SIZE;
    for (p, geo) in s.geometries.iter_mut().enumerate() {
        let full: Vec<Option<PixelGeometry>> = (0..n).map(|i| geo.get(i).copied()).collect();
        *geo = full
            .into_iter()
            .enumerate()
            .map(|(i, g)| g.filter(|_| (i + p) % 7 != 0))
            .collect();
    }
    let model = LayerModel::from_fn(SIZE, SIZE, |_, _| std::iter::empty());
    let frames = slit_frames(&s);
    let stacks: Vec<SlitStack> = frames
        .iter()
        .enumerate()
        .map(|(p, f)| SlitStack::new(f, n, |i| (i + 2 * p) % 5 != 0).unwrap())
        .collect();
    let dense = sweeps(&frames);
    let stacked: Vec<SlitSweep> = stacks
        .iter()
        .map(|st| SlitSweep::from_stack(st, n).unwrap())
        .collect();
    let opts = PriorOptions::default();
    let mut compared = 0;
    for sweeps in [&dense, &stacked] {
        let inputs = tiles::Inputs {
            model: &model,
            surface: &s.surface,
            geometries: &s.geometries,
            sweeps,
            tiles: tiles::Tiles::new(SIZE, SIZE, 3),
            depth_spacing: 0.0,
            opts: &opts,
        };
        for i in 0..n {
            let widths = cross_validation::log_widths(&inputs, i);
            for (c, got) in widths.iter().enumerate() {
                let want = log_widths_from_profiles(&inputs, i, c);
                let bits =
                    |w: &[Option<f64>]| w.iter().map(|x| x.map(f64::to_bits)).collect::<Vec<_>>();
                assert_eq!(bits(got), bits(&want), "pixel {i} channel {c}");
                compared += want.iter().flatten().count();
            }
        }
    }
    assert!(compared > 10_000, "only {compared} widths compared");
}

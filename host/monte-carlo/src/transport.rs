//! The photon random walk (MCML "hop, drop, spin", Wang, Jacques & Zheng 1995), batching and
//! reduction.
//!
//! Each photon carries a weight. At every interaction a fraction mu_a/mu_t of it is deposited in the
//! current layer and the rest scatters by Henyey-Greenstein. Step lengths are sampled in optical
//! depth (dimensionless) so a step that crosses into a layer with another mu_t keeps the unused part
//! of its optical depth. At the outer surfaces weight is split deterministically: the transmitted
//! fraction (1 - Fresnel R) escapes and is tallied, the rest is reflected back (MCML's "partial
//! reflection" option, lower variance than all-or-nothing). At internal interfaces the photon is
//! reflected or refracted at random with the Fresnel probability. Below a weight threshold the
//! photon plays Russian roulette, which keeps the estimate unbiased.

use std::time::Instant;

use rand::RngCore;
use rand_pcg::Pcg64;
use rayon::prelude::*;

use super::fresnel::{reflectance_with_cos_t, refracted_cos};
use super::tally::{BatchTally, GridSpec, RadialSpec};
use super::{McConfig, McResult, Medium};

/// Photons per batch: each batch has its own random stream, so results do not depend on threads.
const BATCH_PHOTONS: u64 = 4096;
/// Below this weight a photon plays Russian roulette (MCML's value).
const ROULETTE_THRESHOLD: f64 = 1e-4;
/// A photon survives roulette with this probability and has its weight divided by it.
const ROULETTE_SURVIVAL: f64 = 0.1;
/// A photon trapped by total internal reflection in a non-scattering layer would bounce forever;
/// after this many events it is dropped (its weight is then missing from every tally).
const MAX_EVENTS_PER_PHOTON: u32 = 1_000_000;
/// Directions with 1 - uz^2 below this are treated as vertical by the spin formula (MCML's
/// COSZERO, 1 - 1e-12, expressed on 1 - uz^2).
const NEAR_VERTICAL: f64 = 2e-12;

/// Per-layer constants precomputed once per run.
#[derive(Debug, Clone, Copy)]
struct LayerConsts {
    z_top: f64,
    z_bottom: f64,
    mu_t: f64,
    /// 1 / mu_t, infinite for a clear layer (so a step in it never ends inside it).
    inv_mu_t: f64,
    /// mu_a / mu_t: fraction of the weight deposited at each interaction.
    absorb_fraction: f64,
    hg: HenyeyGreenstein,
    n: f64,
    /// Index of the medium above and below this layer.
    n_up: f64,
    n_down: f64,
}

struct Geometry {
    layers: Vec<LayerConsts>,
    specular: f64,
    /// Entry direction after refraction: (sin theta_t, 0, cos theta_t).
    entry_dir: [f64; 3],
    grid: Option<GridSpec>,
    radial: Option<RadialSpec>,
}

impl Geometry {
    fn new(medium: &Medium, cfg: &McConfig) -> Self {
        let count = medium.layers.len();
        let mut layers = Vec::with_capacity(count);
        let mut z = 0.0;
        for (i, layer) in medium.layers.iter().enumerate() {
            let mu_t = layer.mu_t();
            layers.push(LayerConsts {
                z_top: z,
                z_bottom: z + layer.thickness_mm,
                mu_t,
                inv_mu_t: 1.0 / mu_t,
                absorb_fraction: if mu_t > 0.0 { layer.mu_a / mu_t } else { 0.0 },
                hg: HenyeyGreenstein::new(layer.g),
                n: layer.n,
                n_up: if i == 0 {
                    medium.n_above
                } else {
                    medium.layers[i - 1].n
                },
                n_down: if i + 1 == count {
                    medium.n_below
                } else {
                    medium.layers[i + 1].n
                },
            });
            z += layer.thickness_mm;
        }
        let n1 = medium.layers[0].n;
        let cos_i = cfg.incidence_deg.to_radians().cos();
        // Incidence below 90 degrees always refracts into an optically denser or equal medium or,
        // for n1 < n_above, may be totally reflected: then nothing enters.
        let (specular, entry_dir) = match refracted_cos(medium.n_above, n1, cos_i) {
            Some(cos_t) => {
                let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
                (
                    reflectance_with_cos_t(medium.n_above, n1, cos_i, cos_t),
                    [sin_t, 0.0, cos_t],
                )
            }
            None => (1.0, [0.0, 0.0, 1.0]),
        };
        Self {
            layers,
            specular,
            entry_dir,
            grid: cfg.grid,
            radial: cfg.radial,
        }
    }
}

/// The random stream of one batch: PCG-64 with the batch index as its stream selector.
struct Uniform(Pcg64);

impl Uniform {
    fn for_batch(seed: u64, batch: u64) -> Self {
        let state = (u128::from(splitmix64(seed)) << 64) | u128::from(splitmix64(!seed));
        Self(Pcg64::new(state, u128::from(batch)))
    }

    /// Uniform in [0, 1) with 53 random bits.
    #[inline(always)]
    fn next(&mut self) -> f64 {
        (self.0.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in (0, 1], safe for `ln`.
    #[inline(always)]
    fn next_open(&mut self) -> f64 {
        1.0 - self.next()
    }

    /// (cos phi, sin phi) for phi uniform on [0, 2 pi), by rejection in the unit disc (no trig).
    #[inline(always)]
    fn azimuth(&mut self) -> (f64, f64) {
        loop {
            let u = 2.0 * self.next() - 1.0;
            let v = 2.0 * self.next() - 1.0;
            let s = u * u + v * v;
            if s > 0.0 && s <= 1.0 {
                let inv = 1.0 / s;
                return ((u * u - v * v) * inv, 2.0 * u * v * inv);
            }
        }
    }
}

fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Henyey-Greenstein phase function constants for inverse-CDF sampling of the scattering cosine.
#[derive(Debug, Clone, Copy)]
struct HenyeyGreenstein {
    isotropic: bool,
    one_plus_g2: f64,
    one_minus_g2: f64,
    one_minus_g: f64,
    two_g: f64,
    inv_two_g: f64,
}

impl HenyeyGreenstein {
    fn new(g: f64) -> Self {
        // Below |g| = 1e-6 the inverse CDF loses precision; the isotropic law is then exact enough.
        let isotropic = g.abs() < 1e-6;
        Self {
            isotropic,
            one_plus_g2: 1.0 + g * g,
            one_minus_g2: 1.0 - g * g,
            one_minus_g: 1.0 - g,
            two_g: 2.0 * g,
            inv_two_g: if isotropic { 0.0 } else { 0.5 / g },
        }
    }

    /// Cosine of the scattering angle for a uniform `xi` in [0, 1).
    #[inline(always)]
    fn sample_cos(&self, xi: f64) -> f64 {
        if self.isotropic {
            2.0 * xi - 1.0
        } else {
            let t = self.one_minus_g2 / (self.one_minus_g + self.two_g * xi);
            ((self.one_plus_g2 - t * t) * self.inv_two_g).clamp(-1.0, 1.0)
        }
    }
}

/// Turns `dir` by polar cosine `cos_t` and azimuth (cos_p, sin_p) about itself (MCML's formulas,
/// with sin(theta) / sqrt(1 - uz^2) taken as one square root).
#[inline(always)]
fn spin(dir: &mut [f64; 3], cos_t: f64, cos_p: f64, sin_p: f64) {
    let sin_t_sq = (1.0 - cos_t * cos_t).max(0.0);
    let [ux, uy, uz] = *dir;
    let one_minus_uz2 = 1.0 - uz * uz;
    if one_minus_uz2 < NEAR_VERTICAL {
        let sin_t = sin_t_sq.sqrt();
        *dir = [sin_t * cos_p, sin_t * sin_p, cos_t * uz.signum()];
    } else {
        let k = (sin_t_sq / one_minus_uz2).sqrt();
        *dir = [
            k * (ux * uz * cos_p - uy * sin_p) + ux * cos_t,
            k * (uy * uz * cos_p + ux * sin_p) + uy * cos_t,
            -k * cos_p * one_minus_uz2 + uz * cos_t,
        ];
    }
}

/// Per-photon accumulators, reused across the photons of a batch (no allocation per photon).
struct PhotonTally {
    reflected: f64,
    transmitted: f64,
    absorbed: Vec<f64>,
}

/// Runs all photons of one batch.
fn run_batch(geo: &Geometry, seed: u64, batch: u64, photons: u64) -> BatchTally {
    let mut rng = Uniform::for_batch(seed, batch);
    let mut tally = BatchTally::new(geo.layers.len(), geo.grid.as_ref(), geo.radial.as_ref());
    let mut photon = PhotonTally {
        reflected: 0.0,
        transmitted: 0.0,
        absorbed: vec![0.0; geo.layers.len()],
    };
    for _ in 0..photons {
        photon.reflected = 0.0;
        photon.transmitted = 0.0;
        photon.absorbed.iter_mut().for_each(|a| *a = 0.0);
        trace_photon(geo, &mut rng, &mut photon, &mut tally);
        tally.reflect.add(photon.reflected);
        tally.transmit.add(photon.transmitted);
        for (m, &a) in tally.absorbed.iter_mut().zip(&photon.absorbed) {
            m.add(a);
        }
    }
    tally
}

/// Follows one photon from entry until it dies or its weight has left the medium.
fn trace_photon(
    geo: &Geometry,
    rng: &mut Uniform,
    photon: &mut PhotonTally,
    tally: &mut BatchTally,
) {
    let mut weight = 1.0 - geo.specular;
    if weight <= 0.0 {
        return;
    }
    let mut pos = [0.0f64; 3];
    let mut dir = geo.entry_dir;
    let mut layer_index = 0usize;
    // Remaining optical depth of the current step (0: sample a new one).
    let mut optical_left = 0.0f64;
    for _ in 0..MAX_EVENTS_PER_PHOTON {
        let layer = &geo.layers[layer_index];
        if optical_left == 0.0 {
            optical_left = -rng.next_open().ln();
        }
        // Compare depths rather than path lengths: no division on the common, interior step.
        let going_down = dir[2] > 0.0;
        let depth_to_boundary = if going_down {
            layer.z_bottom - pos[2]
        } else {
            pos[2] - layer.z_top
        };
        let uz_abs = dir[2].abs();
        let step = optical_left * layer.inv_mu_t;
        if step * uz_abs < depth_to_boundary {
            // Interaction inside the layer: move, deposit, scatter.
            pos[0] += step * dir[0];
            pos[1] += step * dir[1];
            pos[2] += step * dir[2];
            optical_left = 0.0;
            tally.interactions += 1;
            let deposit = weight * layer.absorb_fraction;
            photon.absorbed[layer_index] += deposit;
            weight -= deposit;
            let cos_t = layer.hg.sample_cos(rng.next());
            let (cos_p, sin_p) = rng.azimuth();
            spin(&mut dir, cos_t, cos_p, sin_p);
        } else {
            // Reach the boundary with the rest of the step kept in optical depth.
            let to_boundary = depth_to_boundary / uz_abs;
            if !to_boundary.is_finite() {
                // Travelling parallel to the layers in a clear layer: never comes back.
                return;
            }
            pos[0] += to_boundary * dir[0];
            pos[1] += to_boundary * dir[1];
            if layer.mu_t > 0.0 {
                optical_left = (optical_left - to_boundary * layer.mu_t).max(0.0);
            }
            pos[2] = if going_down {
                layer.z_bottom
            } else {
                layer.z_top
            };
            let last = layer_index + 1 == geo.layers.len();
            let outer = (going_down && last) || (!going_down && layer_index == 0);
            if outer {
                weight = escape_partially(geo, layer, &pos, &mut dir, weight, photon, tally);
                if weight <= 0.0 {
                    return;
                }
            } else {
                cross_internal(layer, &mut dir, &mut layer_index, rng);
            }
        }
        if weight < ROULETTE_THRESHOLD {
            if rng.next() < ROULETTE_SURVIVAL {
                weight /= ROULETTE_SURVIVAL;
            } else {
                return;
            }
        }
    }
}

/// At the top or bottom surface: the Fresnel-transmitted part of the weight leaves and is
/// tallied, the direction is mirrored and the reflected weight is returned.
fn escape_partially(
    geo: &Geometry,
    layer: &LayerConsts,
    pos: &[f64; 3],
    dir: &mut [f64; 3],
    weight: f64,
    photon: &mut PhotonTally,
    tally: &mut BatchTally,
) -> f64 {
    let going_down = dir[2] > 0.0;
    let n_out = if going_down { layer.n_down } else { layer.n_up };
    let cos_i = dir[2].abs();
    let reflectance = match refracted_cos(layer.n, n_out, cos_i) {
        None => 1.0,
        Some(cos_t) => reflectance_with_cos_t(layer.n, n_out, cos_i, cos_t),
    };
    let escaping = weight * (1.0 - reflectance);
    if going_down {
        photon.transmitted += escaping;
    } else if escaping > 0.0 {
        photon.reflected += escaping;
        tally_exit(geo, pos, escaping, tally);
    }
    dir[2] = -dir[2];
    weight * reflectance
}

fn tally_exit(geo: &Geometry, pos: &[f64; 3], w: f64, tally: &mut BatchTally) {
    tally.exit_wx += w * pos[0];
    tally.exit_wy += w * pos[1];
    if let Some(grid) = &geo.grid {
        match grid.cell_index(pos[0], pos[1]) {
            Some(i) => tally.grid[i] += w,
            None => tally.grid_outside += w,
        }
    }
    if let Some(radial) = &geo.radial {
        match radial.ring_index(pos[0].hypot(pos[1])) {
            Some(i) => tally.rings[i] += w,
            None => tally.rings_outside += w,
        }
    }
}

/// At an interface between two layers: reflect or refract at random with the Fresnel probability.
fn cross_internal(
    layer: &LayerConsts,
    dir: &mut [f64; 3],
    layer_index: &mut usize,
    rng: &mut Uniform,
) {
    let going_down = dir[2] > 0.0;
    let n_next = if going_down { layer.n_down } else { layer.n_up };
    let cos_i = dir[2].abs();
    if layer.n == n_next {
        *layer_index = if going_down {
            *layer_index + 1
        } else {
            *layer_index - 1
        };
        return;
    }
    match refracted_cos(layer.n, n_next, cos_i) {
        Some(cos_t) if rng.next() >= reflectance_with_cos_t(layer.n, n_next, cos_i, cos_t) => {
            let ratio = layer.n / n_next;
            dir[0] *= ratio;
            dir[1] *= ratio;
            dir[2] = if going_down { cos_t } else { -cos_t };
            *layer_index = if going_down {
                *layer_index + 1
            } else {
                *layer_index - 1
            };
        }
        _ => dir[2] = -dir[2],
    }
}

/// Runs every batch (in parallel, merged in batch order) and assembles the result.
pub(crate) fn simulate(medium: &Medium, cfg: &McConfig) -> McResult {
    let start = Instant::now();
    let geo = Geometry::new(medium, cfg);
    let batches = cfg.photons.div_ceil(BATCH_PHOTONS);
    let batch_size = |b: u64| BATCH_PHOTONS.min(cfg.photons - b * BATCH_PHOTONS);
    let threads = rayon::current_num_threads();
    // Batches run in rounds so that at most a few spatial tallies per thread are alive at once.
    let round = (4 * threads as u64).max(1);
    let mut total = BatchTally::new(medium.layers.len(), cfg.grid.as_ref(), cfg.radial.as_ref());
    let mut first = 0;
    while first < batches {
        let last = (first + round).min(batches);
        let tallies: Vec<BatchTally> = (first..last)
            .into_par_iter()
            .map(|b| run_batch(&geo, cfg.seed, b, batch_size(b)))
            .collect();
        for t in &tallies {
            total.merge(t);
        }
        first = last;
    }
    let elapsed = start.elapsed().as_secs_f64();
    assemble(&geo, cfg, &total, elapsed, threads)
}

fn assemble(
    geo: &Geometry,
    cfg: &McConfig,
    total: &BatchTally,
    elapsed: f64,
    threads: usize,
) -> McResult {
    let n = cfg.photons;
    let (diffuse_reflectance, diffuse_reflectance_se) = total.reflect.mean_se(n);
    let (total_transmittance, total_transmittance_se) = total.transmit.mean_se(n);
    let (absorbed, absorbed_se) = total.absorbed.iter().map(|m| m.mean_se(n)).unzip();
    let reflected_weight = diffuse_reflectance * n as f64;
    let exit_centroid_mm = if reflected_weight > 0.0 {
        [
            total.exit_wx / reflected_weight,
            total.exit_wy / reflected_weight,
        ]
    } else {
        [0.0, 0.0]
    };
    McResult {
        specular: geo.specular,
        diffuse_reflectance,
        diffuse_reflectance_se,
        total_transmittance,
        total_transmittance_se,
        absorbed,
        absorbed_se,
        exit_centroid_mm,
        photons: n,
        photons_per_second: if elapsed > 0.0 {
            n as f64 / elapsed
        } else {
            f64::INFINITY
        },
        threads,
        interactions_per_photon: total.interactions as f64 / n as f64,
        response: geo.grid.as_ref().map(|g| total.response(g, n)),
        radial: geo.radial.as_ref().map(|r| total.radial(r, n)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Layer, run};

    fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(f)
    }

    #[test]
    fn result_does_not_depend_on_the_thread_count() {
        let medium = Medium::slab(Layer::from_albedo(0.95, 3.0, 0.8, 1.4), 1.0, 1.33);
        let cfg = McConfig {
            incidence_deg: 30.0,
            grid: Some(GridSpec {
                cell_mm: 0.5,
                cells: 9,
            }),
            ..McConfig::new(3 * BATCH_PHOTONS + 17, 42)
        };
        let one = in_pool(1, || run(&medium, &cfg).unwrap());
        let three = in_pool(3, || run(&medium, &cfg).unwrap());
        assert_eq!(one.diffuse_reflectance, three.diffuse_reflectance);
        assert_eq!(one.total_transmittance_se, three.total_transmittance_se);
        assert_eq!(one.absorbed, three.absorbed);
        assert_eq!(one.response, three.response);
        let other_seed = run(&medium, &McConfig { seed: 43, ..cfg }).unwrap();
        assert_ne!(one.diffuse_reflectance, other_seed.diffuse_reflectance);
    }

    /// A purely absorbing slab between mismatched media: every pass transmits exp(-tau), each
    /// surface reflects the Fresnel R. Summing the multiple reflections (hand derivation):
    /// T = (1-R)^2 e / (1 - R^2 e^2), R_d = (1-R)^2 R e^2 / (1 - R^2 e^2), with e = exp(-tau).
    #[test]
    fn absorbing_slab_matches_the_multiple_reflection_series() {
        let tau = 0.7;
        let n = 1.5;
        let layer = Layer {
            thickness_mm: tau,
            mu_a: 1.0,
            mu_s: 0.0,
            g: 0.0,
            n,
        };
        let medium = Medium::slab(layer, 1.0, 1.0);
        let r = run(&medium, &McConfig::new(200_000, 5)).unwrap();
        let fr = ((n - 1.0) / (n + 1.0)).powi(2);
        let e = (-tau).exp();
        let denom = 1.0 - fr * fr * e * e;
        let t_exact = (1.0 - fr).powi(2) * e / denom;
        let rd_exact = (1.0 - fr).powi(2) * fr * e * e / denom;
        assert!((r.specular - fr).abs() < 1e-15);
        assert!(
            (r.total_transmittance - t_exact).abs() < 4.0 * r.total_transmittance_se,
            "T {} +- {} vs {t_exact}",
            r.total_transmittance,
            r.total_transmittance_se
        );
        assert!(
            (r.diffuse_reflectance - rd_exact).abs() < 4.0 * r.diffuse_reflectance_se,
            "Rd {} +- {} vs {rd_exact}",
            r.diffuse_reflectance,
            r.diffuse_reflectance_se
        );
        // Unscattered light leaves exactly at the entry point.
        assert!(r.exit_centroid_mm[0].abs() < 1e-12);
    }

    #[test]
    fn grid_and_rings_hold_the_diffuse_reflectance() {
        let medium = Medium::slab(Layer::from_albedo(0.9, f64::INFINITY, 0.0, 1.0), 1.0, 1.0);
        let cfg = McConfig {
            grid: Some(GridSpec {
                cell_mm: 0.25,
                cells: 21,
            }),
            radial: Some(RadialSpec {
                dr_mm: 0.1,
                rings: 30,
            }),
            ..McConfig::new(20_000, 3)
        };
        let r = run(&medium, &cfg).unwrap();
        let grid = r.response.as_ref().unwrap();
        let rings = r.radial.as_ref().unwrap();
        let rd = r.diffuse_reflectance;
        assert!((grid.total() + grid.outside - rd).abs() < 1e-9);
        assert!((rings.total() + rings.outside - rd).abs() < 1e-9);
        // Normal incidence on an isotropic medium: R(r) decreases away from the entry point.
        assert!(rings.values[0] > rings.values[10] && rings.values[10] > rings.values[29]);
    }
}

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

use rayon::prelude::*;

use super::fresnel::{ReflectanceBound, reflectance_with_cos_t, refracted_cos};
use super::photon_lanes::{self, Isa};
use super::tally::{BatchTally, GridSpec, RadialSpec};
use super::{McConfig, McResult, Medium};

/// Photons per batch: each batch has its own random stream, so results do not depend on threads.
const BATCH_PHOTONS: u64 = 4096;
/// Below this weight a photon plays Russian roulette (MCML's value).
pub(crate) const ROULETTE_THRESHOLD: f64 = 1e-4;
/// A photon survives roulette with this probability and has its weight divided by it.
pub(crate) const ROULETTE_SURVIVAL: f64 = 0.1;
/// A photon trapped by total internal reflection in a non-scattering layer would bounce forever;
/// after this many events it is dropped (its weight is then missing from every tally).
pub(crate) const MAX_EVENTS_PER_PHOTON: u32 = 1_000_000;

/// Per-layer constants precomputed once per run.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LayerConsts {
    pub(crate) z_top: f64,
    pub(crate) z_bottom: f64,
    pub(crate) mu_t: f64,
    /// 1 / mu_t, infinite for a clear layer (so a step in it never ends inside it).
    pub(crate) inv_mu_t: f64,
    /// mu_s / mu_t: fraction of the weight that scatters on at each interaction (the rest,
    /// mu_a / mu_t, is deposited); 1 for a clear layer.
    pub(crate) albedo: f64,
    pub(crate) hg: HenyeyGreenstein,
    pub(crate) n: f64,
    /// Index of the medium above and below this layer.
    pub(crate) n_up: f64,
    pub(crate) n_down: f64,
}

pub(crate) struct Geometry {
    pub(crate) layers: Vec<LayerConsts>,
    /// Per layer, the reflectance bounds of its top and bottom interfaces seen from inside it,
    /// `[up, down]`.
    pub(crate) interfaces: Vec<[ReflectanceBound; 2]>,
    pub(crate) specular: f64,
    /// Entry direction after refraction: (sin theta_t, 0, cos theta_t).
    pub(crate) entry_dir: [f64; 3],
    pub(crate) grid: Option<GridSpec>,
    pub(crate) radial: Option<RadialSpec>,
}

impl Geometry {
    pub(crate) fn new(medium: &Medium, cfg: &McConfig) -> Self {
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
                albedo: if mu_t > 0.0 { layer.mu_s / mu_t } else { 1.0 },
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
        let interfaces = layers
            .iter()
            .map(|l| {
                [
                    ReflectanceBound::new(l.n, l.n_up),
                    ReflectanceBound::new(l.n, l.n_down),
                ]
            })
            .collect();
        Self {
            layers,
            interfaces,
            specular,
            entry_dir,
            grid: cfg.grid,
            radial: cfg.radial,
        }
    }
}

/// Henyey-Greenstein phase function constants for inverse-CDF sampling of the scattering cosine
/// (see `henyey_greenstein` in `lane_kernels.rs` for the formula they enter).
#[derive(Debug, Clone, Copy)]
pub(crate) struct HenyeyGreenstein {
    pub(crate) g: f64,
    pub(crate) one_minus_g: f64,
    pub(crate) two_g: f64,
    /// 2 (1 - g)^2.
    pub(crate) scale: f64,
}

impl HenyeyGreenstein {
    fn new(g: f64) -> Self {
        Self {
            g,
            one_minus_g: 1.0 - g,
            two_g: 2.0 * g,
            scale: 2.0 * (1.0 - g) * (1.0 - g),
        }
    }
}

/// Adds one diffuse exit through the top at `pos` (x, y) with weight `w` to the spatial tallies.
pub(crate) fn tally_exit(geo: &Geometry, pos: &[f64; 2], w: f64, tally: &mut BatchTally) {
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

/// Runs every batch (in parallel, merged in batch order) and assembles the result.
pub(crate) fn simulate(medium: &Medium, cfg: &McConfig) -> McResult {
    let start = Instant::now();
    let geo = Geometry::new(medium, cfg);
    let batches = cfg.photons.div_ceil(BATCH_PHOTONS);
    let batch_size = |b: u64| BATCH_PHOTONS.min(cfg.photons - b * BATCH_PHOTONS);
    let threads = rayon::current_num_threads();
    let isa = Isa::detect();
    // Batches run in rounds so that at most a few spatial tallies per thread are alive at once.
    let round = (4 * threads as u64).max(1);
    let mut total = BatchTally::new(medium.layers.len(), cfg.grid.as_ref(), cfg.radial.as_ref());
    let mut first = 0;
    while first < batches {
        let last = (first + round).min(batches);
        let tallies: Vec<BatchTally> = (first..last)
            .into_par_iter()
            .map(|b| photon_lanes::run_batch(isa, &geo, cfg.seed, b, batch_size(b)))
            .collect();
        for t in &tallies {
            total.merge(t);
        }
        first = last;
    }
    let elapsed = start.elapsed().as_secs_f64();
    assemble(&geo, cfg, &total, elapsed, threads, isa)
}

fn assemble(
    geo: &Geometry,
    cfg: &McConfig,
    total: &BatchTally,
    elapsed: f64,
    threads: usize,
    isa: Isa,
) -> McResult {
    let n = cfg.photons;
    let per_second = |count: f64| {
        if elapsed > 0.0 {
            count / elapsed
        } else {
            f64::INFINITY
        }
    };
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
        photons_per_second: per_second(n as f64),
        interactions_per_second: per_second(total.interactions as f64),
        threads,
        simd: isa.name(),
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

    /// Changing the lane count or the batch size changes every result: the stream name that
    /// caches key on must say so.
    #[test]
    fn the_stream_name_follows_the_lane_count_and_batch_size() {
        let name = crate::RANDOM_STREAMS;
        let lanes = format!(
            "{} groups x {} lanes",
            crate::photon_lanes::GROUPS,
            crate::simd::LANES
        );
        assert!(name.contains(&lanes), "{name}");
        assert!(name.contains(&format!("{BATCH_PHOTONS}-photon")), "{name}");
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

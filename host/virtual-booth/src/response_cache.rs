//! Monte Carlo exit responses of the skin materials, computed once per material, incidence angle
//! and Monte Carlo setting, and cached on disk under a content hash of exactly those inputs, so a
//! second simulation with the same materials runs no Monte Carlo at all.
//!
//! Conventions
//! - Responses follow `mc`'s frame: x forward (away from the light), y to the side; per unit
//!   incident power, 1/mm^2, per channel. They are symmetrised in y (the layered medium is
//!   mirror-symmetric about the plane of incidence), which halves the Monte Carlo noise.
//! - Cache file: `<dir>/responses/<blake3 hex>.bin` = the line `mlsss-response v1`, one JSON line
//!   (the key and the grid shape), then `cells^2 x 3` little-endian f32 values.
//! - Default cache directory: `$MLSSS_CACHE`, else `$XDG_CACHE_HOME/mlsss`, else `~/.cache/mlsss`.

use std::io::Write;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::VirtualBoothError;
use super::skin_optics::Material;
use super::subsurface_transport::{ResponseGrid, ResponseSet};
use mlsss_mc::{self, GridSpec, Layer, McConfig, Medium};

/// Version of the cached data; bump when the meaning of a cached response changes.
const CACHE_FORMAT: &str = "mlsss-response v1";

/// How the responses are computed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct McSettings {
    /// Photons per material, angle and channel.
    pub photons: u64,
    pub seed: u64,
    /// Tabulated incidence angles, degrees, ascending.
    pub angles_deg: Vec<f64>,
    /// Grid cell, mm, and cells per side (odd).
    pub cell_mm: f64,
    pub cells: usize,
}

/// What one simulation's responses cost.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct CacheStats {
    pub hits: usize,
    pub misses: usize,
    /// Photons traced for the misses.
    pub photons_traced: u64,
    /// Wall-clock seconds of the Monte Carlo (0 when everything was cached).
    pub mc_seconds: f64,
}

/// The on-disk response cache.
#[derive(Debug, Clone)]
pub struct ResponseCache {
    dir: PathBuf,
}

/// The inputs a cached response depends on (hashed into its file name).
#[derive(Debug, Serialize, Deserialize, PartialEq)]
struct CacheKey {
    format: String,
    /// `mlsss_mc::RANDOM_STREAMS`: a response computed with other streams is another draw.
    random_streams: String,
    /// Per channel: the layered medium.
    media: Vec<Medium>,
    incidence_deg: f64,
    photons: u64,
    seed: u64,
    cell_mm: f64,
    cells: usize,
}

impl ResponseCache {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// `$MLSSS_CACHE`, else `$XDG_CACHE_HOME/mlsss`, else `~/.cache/mlsss`, else `./.mlsss-cache`.
    pub fn default_dir() -> PathBuf {
        if let Some(dir) = std::env::var_os("MLSSS_CACHE") {
            return PathBuf::from(dir);
        }
        if let Some(dir) = std::env::var_os("XDG_CACHE_HOME") {
            return PathBuf::from(dir).join("mlsss");
        }
        if let Some(home) = std::env::var_os("HOME") {
            return PathBuf::from(home).join(".cache").join("mlsss");
        }
        PathBuf::from(".mlsss-cache")
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Responses of `materials` at every angle of `settings`, from the cache or Monte Carlo.
    /// `on_step` is called once per (material, angle) with whether it was cached.
    ///
    /// The missing responses are computed as parallel jobs, one per (material, angle, channel),
    /// each itself split into the Monte Carlo's fixed photon batches: every core stays busy to
    /// the end (a single response of a few batches would leave cores idle), and the result is
    /// the same as computing the responses one after the other.
    pub fn response_set(
        &self,
        materials: &[Material],
        settings: &McSettings,
        on_step: &(dyn Fn(bool) + Sync),
    ) -> Result<(ResponseSet, CacheStats), VirtualBoothError> {
        let mut stats = CacheStats::default();
        let start = std::time::Instant::now();
        let keys: Vec<(usize, f64)> = (0..materials.len())
            .flat_map(|m| settings.angles_deg.iter().map(move |&a| (m, a)))
            .collect();
        let looked_up: Vec<Lookup> = keys
            .iter()
            .map(|&(m, angle)| self.look_up(&materials[m], angle, settings))
            .collect::<Result<_, _>>()?;
        let jobs: Vec<(usize, usize)> = looked_up
            .iter()
            .enumerate()
            .filter(|(_, l)| l.grid.is_none())
            .flat_map(|(i, _)| (0..3).map(move |c| (i, c)))
            .collect();
        let computed: Vec<Vec<f64>> = jobs
            .par_iter()
            .map(|&(i, c)| {
                let (m, angle) = keys[i];
                let values = channel_response(&materials[m], c, angle, settings);
                if c == 2 {
                    on_step(false);
                }
                values
            })
            .collect::<Result<_, _>>()?;
        let mut channels = jobs.iter().zip(computed);
        let mut grids = vec![Vec::with_capacity(settings.angles_deg.len()); materials.len()];
        for (&(m, _), lookup) in keys.iter().zip(looked_up) {
            let grid = match lookup.grid {
                Some(grid) => {
                    stats.hits += 1;
                    on_step(true);
                    grid
                }
                None => {
                    let mut values = vec![[0.0f32; 3]; settings.cells * settings.cells];
                    for _ in 0..3 {
                        let (&(_, c), response) = channels.next().ok_or(
                            VirtualBoothError::Internal("a Monte Carlo job result is missing"),
                        )?;
                        for (v, r) in values.iter_mut().zip(&response) {
                            v[c] = *r as f32;
                        }
                    }
                    symmetrise_in_y(&mut values, settings.cells);
                    stats.misses += 1;
                    stats.photons_traced += 3 * settings.photons;
                    let grid = ResponseGrid {
                        cell_mm: settings.cell_mm,
                        cells: settings.cells,
                        values,
                    };
                    write_cached(&lookup.path, &lookup.key_json, &grid)?;
                    grid
                }
            };
            grids[m].push(grid);
        }
        if stats.misses > 0 {
            stats.mc_seconds = start.elapsed().as_secs_f64();
        }
        Ok((
            ResponseSet {
                angles_deg: settings.angles_deg.clone(),
                grids,
            },
            stats,
        ))
    }

    /// The cache file of one (material, angle) and its grid when already cached.
    fn look_up(
        &self,
        material: &Material,
        angle: f64,
        settings: &McSettings,
    ) -> Result<Lookup, VirtualBoothError> {
        let key = CacheKey {
            format: CACHE_FORMAT.into(),
            random_streams: mlsss_mc::RANDOM_STREAMS.into(),
            media: (0..3).map(|c| material_medium(material, c)).collect(),
            incidence_deg: angle,
            photons: settings.photons,
            seed: settings.seed,
            cell_mm: settings.cell_mm,
            cells: settings.cells,
        };
        let key_json = serde_json::to_string(&key).map_err(VirtualBoothError::Json)?;
        let path = self.dir.join("responses").join(format!(
            "{}.bin",
            blake3::hash(key_json.as_bytes()).to_hex()
        ));
        let grid = read_cached(&path, &key_json, settings)?;
        Ok(Lookup {
            path,
            key_json,
            grid,
        })
    }
}

/// Where one (material, angle) response lives in the cache, and its grid when present.
struct Lookup {
    path: PathBuf,
    key_json: String,
    grid: Option<ResponseGrid>,
}

/// The Monte Carlo exit grid of `material` at channel `c` and incidence `angle` (degrees).
fn channel_response(
    material: &Material,
    c: usize,
    angle: f64,
    settings: &McSettings,
) -> Result<Vec<f64>, VirtualBoothError> {
    let cfg = McConfig {
        photons: settings.photons,
        seed: settings.seed.wrapping_add(c as u64),
        incidence_deg: angle,
        grid: Some(GridSpec {
            cell_mm: settings.cell_mm,
            cells: settings.cells,
        }),
        radial: None,
    };
    let result = mlsss_mc::run(&material_medium(material, c), &cfg)?;
    let response = result.response.ok_or(VirtualBoothError::Internal(
        "Monte Carlo run returned no exit grid although one was requested",
    ))?;
    Ok(response.values)
}

/// The layered medium of `material` at channel `c`, in air, semi-infinite below.
pub fn material_medium(material: &Material, c: usize) -> Medium {
    Medium {
        layers: material
            .layers
            .iter()
            .map(|l| Layer {
                thickness_mm: l.thickness_mm,
                mu_a: l.mu_a[c],
                mu_s: l.mu_s[c],
                g: l.g[c],
                n: l.n,
            })
            .collect(),
        n_above: 1.0,
        n_below: 1.0,
    }
}

/// Averages each cell with its mirror image across y = 0.
fn symmetrise_in_y(values: &mut [[f32; 3]], cells: usize) {
    for iy in 0..cells / 2 {
        let my = cells - 1 - iy;
        for ix in 0..cells {
            let (a, b) = (values[iy * cells + ix], values[my * cells + ix]);
            let mean = [0, 1, 2].map(|c| 0.5 * (a[c] + b[c]));
            values[iy * cells + ix] = mean;
            values[my * cells + ix] = mean;
        }
    }
}

fn cache_error(path: &Path) -> impl FnOnce(std::io::Error) -> VirtualBoothError + '_ {
    move |source| VirtualBoothError::Cache {
        path: path.to_owned(),
        source,
    }
}

/// Reads a cached grid; `None` when absent or written for other inputs (a hash collision or an
/// interrupted write is treated as a miss and overwritten).
fn read_cached(
    path: &Path,
    key_json: &str,
    settings: &McSettings,
) -> Result<Option<ResponseGrid>, VirtualBoothError> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(cache_error(path)(e)),
    };
    let mut lines = bytes.splitn(3, |&b| b == b'\n');
    let (Some(magic), Some(key), Some(data)) = (lines.next(), lines.next(), lines.next()) else {
        return Ok(None);
    };
    let n = settings.cells * settings.cells * 3;
    if magic != CACHE_FORMAT.as_bytes() || key != key_json.as_bytes() || data.len() != n * 4 {
        return Ok(None);
    }
    let flat: Vec<f32> = data
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok(Some(ResponseGrid {
        cell_mm: settings.cell_mm,
        cells: settings.cells,
        values: flat.chunks_exact(3).map(|v| [v[0], v[1], v[2]]).collect(),
    }))
}

/// Writes a grid atomically (temporary file, then rename).
fn write_cached(path: &Path, key_json: &str, grid: &ResponseGrid) -> Result<(), VirtualBoothError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(cache_error(dir))?;
    let tmp = path.with_extension(format!("tmp-{}", std::process::id()));
    let mut bytes = Vec::with_capacity(grid.values.len() * 12 + key_json.len() + 32);
    bytes.extend_from_slice(CACHE_FORMAT.as_bytes());
    bytes.push(b'\n');
    bytes.extend_from_slice(key_json.as_bytes());
    bytes.push(b'\n');
    for v in &grid.values {
        for x in v {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
    }
    let mut file = std::fs::File::create(&tmp).map_err(cache_error(&tmp))?;
    file.write_all(&bytes).map_err(cache_error(&tmp))?;
    drop(file);
    std::fs::rename(&tmp, path).map_err(cache_error(path))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skin_optics::SkinPreset;

    fn settings() -> McSettings {
        McSettings {
            photons: 3000,
            seed: 5,
            angles_deg: vec![0.0, 60.0],
            cell_mm: 0.2,
            cells: 41,
        }
    }

    #[test]
    fn second_request_is_served_from_disk_without_monte_carlo() {
        let dir = tempfile::tempdir().unwrap();
        let cache = ResponseCache::new(dir.path());
        let materials = &SkinPreset::LIGHT.materials()[..1];
        let (first, stats1) = cache.response_set(materials, &settings(), &|_| {}).unwrap();
        assert_eq!((stats1.hits, stats1.misses), (0, 2));
        assert!(stats1.photons_traced > 0);
        let (second, stats2) = cache.response_set(materials, &settings(), &|_| {}).unwrap();
        assert_eq!(
            (stats2.hits, stats2.misses, stats2.photons_traced),
            (2, 0, 0)
        );
        assert_eq!(first.grids, second.grids);
        // Other Monte Carlo settings are a different key.
        let mut other = settings();
        other.photons += 1;
        let (_, stats3) = cache.response_set(materials, &other, &|_| {}).unwrap();
        assert_eq!(stats3.misses, 2);
    }

    /// The responses computed as parallel (material, angle, channel) jobs are, cell for cell,
    /// those of one Monte Carlo run per channel done one after the other.
    #[test]
    fn parallel_jobs_give_the_sequential_runs_in_their_places() {
        let dir = tempfile::tempdir().unwrap();
        let cache = ResponseCache::new(dir.path());
        let materials = &SkinPreset::LIGHT.materials()[1..3];
        let settings = settings();
        let (set, stats) = cache.response_set(materials, &settings, &|_| {}).unwrap();
        assert_eq!((stats.hits, stats.misses), (0, 4));
        for (m, material) in materials.iter().enumerate() {
            for (a, &angle) in settings.angles_deg.iter().enumerate() {
                let mut expected = vec![[0.0f32; 3]; settings.cells * settings.cells];
                for c in 0..3 {
                    let cfg = McConfig {
                        photons: settings.photons,
                        seed: settings.seed + c as u64,
                        incidence_deg: angle,
                        grid: Some(GridSpec {
                            cell_mm: settings.cell_mm,
                            cells: settings.cells,
                        }),
                        radial: None,
                    };
                    let run = mlsss_mc::run(&material_medium(material, c), &cfg).unwrap();
                    for (e, v) in expected.iter_mut().zip(&run.response.unwrap().values) {
                        e[c] = *v as f32;
                    }
                }
                symmetrise_in_y(&mut expected, settings.cells);
                assert!(
                    set.grids[m][a].values == expected,
                    "material {m}, angle {angle}"
                );
            }
        }
    }

    #[test]
    fn oblique_response_is_symmetric_and_shifted_forward() {
        let dir = tempfile::tempdir().unwrap();
        let cache = ResponseCache::new(dir.path());
        let materials = &SkinPreset::LIGHT.materials()[..1];
        let (set, _) = cache.response_set(materials, &settings(), &|_| {}).unwrap();
        let grid = &set.grids[0][1];
        let n = grid.cells;
        let centre = (n - 1) / 2;
        let mut forward = 0.0;
        for iy in 0..n {
            for ix in 0..n {
                let v = grid.values[iy * n + ix][0] as f64;
                assert_eq!(grid.values[iy * n + ix], grid.values[(n - 1 - iy) * n + ix]);
                forward += v * (ix as f64 - centre as f64);
            }
        }
        assert!(
            forward > 0.0,
            "60 degree response must lean away from the light"
        );
    }
}

//! Projector response calibration: gamma and black level of each projector from the grey levels of
//! a calibration capture (`FramePlan::calibration`), and the removal of the light that the dark
//! projectors' black level adds to every frame ("stray black").
//!
//! Conventions
//! - Response model (`calib::ProjectorResponse`): a pixel showing value v emits
//!   `e(v) = b + (1 - b) v^gamma` of its white.
//! - Frames are linear camera values. While projector k shows level v, the others show black, so a
//!   camera pixel reads `m_k(v) = S_k e_k(v) + O_k` with `S_k` the pixel's reading of projector k's
//!   white alone and `O_k = sum_{j != k} b_j S_j` (zero when the other projectors are truly dark).
//!
//! Estimation, per projector k, over the pixels every projector lights well:
//! - gamma: `(m_k(v) - m_k(0)) / (m_k(1) - m_k(0)) = v^gamma` whatever `b` and `O`; the median of
//!   this ratio over the pixels at each grey level is fitted by 1-D least squares on gamma.
//! - black level: `D_j = m_j(1) - m_j(0) = (1 - b_j) S_j`, so the black frame of projector k,
//!   `m_k(0) = sum_j c_kj D_j` with `c_kk = b_k / (1 - b_k)` and `c_kj = b_j / (1 - b_j)` or 0 for
//!   the others. Least squares over the pixels (the projectors light the board with different
//!   falloff and incidence, which makes the `D_j` independent) gives `c_kk`, hence
//!   `b_k = c_kk / (1 + c_kk)`. Ambient light is assumed absent (a dark booth).

use image::Rgb32FImage;
use nalgebra::{DMatrix, DVector, Matrix4};
use rayon::prelude::*;

use mlsss_core::calibration::ProjectorResponse;

/// Errors of the response calibration.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ResponseError {
    /// A projector's frames lack level 0 (black) or level 1 (white).
    #[error("projector {0}: the calibration needs its black (level 0) and white (level 1) frames")]
    MissingLevels(usize),
    /// A projector has no intermediate grey level, so gamma is undetermined.
    #[error("projector {0}: no grey level strictly between 0 and 1 to fit gamma")]
    NoGreyLevels(usize),
    /// Frames of one pose differ in size.
    #[error("pose {pose}: frames differ in size")]
    SizeMismatch { pose: usize },
    /// Too few pixels are lit well by every projector.
    #[error("only {0} pixels are lit well by every projector (need 100); is the board in view?")]
    TooFewPixels(usize),
    /// The projectors light the board too similarly to tell their black levels apart.
    #[error("black-level regression is ill-conditioned (condition number {0:.0})")]
    IllConditioned(f64),
    /// Poses have different numbers of projectors.
    #[error("pose {pose} has {got} projectors, pose 0 has {expected}")]
    ProjectorCount {
        pose: usize,
        got: usize,
        expected: usize,
    },
}

/// The frames of one projector in one pose: `(level in [0, 1], image)`.
#[derive(Debug, Clone, Default)]
pub struct LevelFrames {
    pub frames: Vec<(f64, Rgb32FImage)>,
}

/// Result for one projector.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ResponseFit {
    pub gamma: f64,
    pub black_level: f64,
    /// RMS difference between the median measured ratios and `v^gamma`.
    pub gamma_fit_rms: f64,
    /// Pixels used (over all poses).
    pub pixels: usize,
}

impl ResponseFit {
    pub fn response(&self) -> ProjectorResponse {
        ProjectorResponse {
            gamma: self.gamma,
            black_level: self.black_level,
        }
    }
}

/// Mean of the frames at `level` (several frames may show it, e.g. Black and Grey 0).
fn level_image(frames: &LevelFrames, level: f64) -> Option<Vec<f32>> {
    let mut sum: Option<Vec<f32>> = None;
    let mut count = 0;
    for (l, img) in &frames.frames {
        if (l - level).abs() > 1e-9 {
            continue;
        }
        count += 1;
        let grey = img.pixels().map(|p| p.0.iter().sum::<f32>() / 3.0);
        match &mut sum {
            Some(s) => s.iter_mut().zip(grey).for_each(|(a, b)| *a += b),
            None => sum = Some(grey.collect()),
        }
    }
    sum.map(|s| s.into_iter().map(|v| v / count as f32).collect())
}

/// Per pose: `white[k]`, `black[k]` grey images and the selected pixels.
struct PoseData {
    white: Vec<Vec<f32>>,
    black: Vec<Vec<f32>>,
    selected: Vec<usize>,
}

fn pose_data(
    pose: &[LevelFrames],
    min_signal: f32,
    saturation: f32,
) -> Result<PoseData, ResponseError> {
    let mut white = Vec::new();
    let mut black = Vec::new();
    for (k, frames) in pose.iter().enumerate() {
        let w = level_image(frames, 1.0).ok_or(ResponseError::MissingLevels(k))?;
        let b = level_image(frames, 0.0).ok_or(ResponseError::MissingLevels(k))?;
        white.push(w);
        black.push(b);
    }
    let n = white.first().map_or(0, Vec::len);
    let selected = (0..n)
        .filter(|&p| {
            white
                .iter()
                .zip(&black)
                .all(|(w, b)| w[p] - b[p] > min_signal && w[p] < saturation)
        })
        .collect();
    Ok(PoseData {
        white,
        black,
        selected,
    })
}

/// Estimates every projector's response from calibration poses (`poses[pose][projector]`).
pub fn estimate_responses(poses: &[Vec<LevelFrames>]) -> Result<Vec<ResponseFit>, ResponseError> {
    let projectors = poses.first().map_or(0, Vec::len);
    for (pose, p) in poses.iter().enumerate() {
        if p.len() != projectors {
            return Err(ResponseError::ProjectorCount {
                pose,
                got: p.len(),
                expected: projectors,
            });
        }
        let size = p
            .first()
            .and_then(|f| f.frames.first())
            .map(|(_, i)| i.dimensions());
        if p.iter()
            .flat_map(|f| &f.frames)
            .any(|(_, i)| Some(i.dimensions()) != size)
        {
            return Err(ResponseError::SizeMismatch { pose });
        }
    }
    // Pixels well lit by every projector (a tenth of the brightest white) and not saturated.
    let brightest = poses
        .iter()
        .flatten()
        .filter_map(|f| level_image(f, 1.0))
        .flat_map(|v| v.into_iter())
        .fold(0.0f32, f32::max);
    let data: Vec<PoseData> = poses
        .iter()
        .map(|p| pose_data(p, 0.1 * brightest, 0.98))
        .collect::<Result<_, _>>()?;
    let pixels: usize = data.iter().map(|d| d.selected.len()).sum();
    if pixels < 100 {
        return Err(ResponseError::TooFewPixels(pixels));
    }
    let blacks = black_levels(&data, projectors)?;
    (0..projectors)
        .map(|k| {
            let (gamma, rms) = fit_gamma(poses, &data, k)?;
            Ok(ResponseFit {
                gamma,
                black_level: blacks[k],
                gamma_fit_rms: rms,
                pixels,
            })
        })
        .collect()
}

fn fit_gamma(
    poses: &[Vec<LevelFrames>],
    data: &[PoseData],
    k: usize,
) -> Result<(f64, f64), ResponseError> {
    let mut levels: Vec<f64> = poses
        .iter()
        .flat_map(|p| p[k].frames.iter().map(|(l, _)| *l))
        .filter(|&l| l > 1e-6 && l < 1.0 - 1e-6)
        .collect();
    levels.sort_by(f64::total_cmp);
    levels.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    if levels.is_empty() {
        return Err(ResponseError::NoGreyLevels(k));
    }
    let mut points = Vec::new();
    for &level in &levels {
        let mut ratios = Vec::new();
        for (pose, d) in poses.iter().zip(data) {
            let Some(img) = level_image(&pose[k], level) else {
                continue;
            };
            ratios.extend(
                d.selected
                    .iter()
                    .map(|&p| ((img[p] - d.black[k][p]) / (d.white[k][p] - d.black[k][p])) as f64),
            );
        }
        if ratios.is_empty() {
            continue;
        }
        ratios.sort_by(f64::total_cmp);
        points.push((level, ratios[ratios.len() / 2]));
    }
    let cost = |g: f64| {
        points
            .iter()
            .map(|(v, r)| (v.powf(g) - r).powi(2))
            .sum::<f64>()
    };
    // Golden-section search: the cost is unimodal in gamma for ratios in (0, 1).
    let (mut lo, mut hi) = (0.1f64, 8.0f64);
    let phi = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..200 {
        let a = hi - phi * (hi - lo);
        let b = lo + phi * (hi - lo);
        if cost(a) < cost(b) {
            hi = b;
        } else {
            lo = a;
        }
    }
    let gamma = 0.5 * (lo + hi);
    Ok((gamma, (cost(gamma) / points.len() as f64).sqrt()))
}

/// Black levels by regressing each projector's black frame on every projector's `D_j`.
fn black_levels(data: &[PoseData], projectors: usize) -> Result<Vec<f64>, ResponseError> {
    let rows: usize = data.iter().map(|d| d.selected.len()).sum();
    let mut design = DMatrix::<f64>::zeros(rows, projectors);
    let mut targets = vec![DVector::<f64>::zeros(rows); projectors];
    let mut row = 0;
    for d in data {
        for &p in &d.selected {
            for j in 0..projectors {
                design[(row, j)] = (d.white[j][p] - d.black[j][p]) as f64;
            }
            for (k, t) in targets.iter_mut().enumerate() {
                t[row] = d.black[k][p] as f64;
            }
            row += 1;
        }
    }
    let normal = design.transpose() * &design;
    let eig = normal.clone().symmetric_eigen().eigenvalues;
    let condition = (eig.max() / eig.min().max(f64::MIN_POSITIVE)).sqrt();
    if !condition.is_finite() || condition > 1e4 {
        return Err(ResponseError::IllConditioned(condition));
    }
    let chol = normal
        .cholesky()
        .ok_or(ResponseError::IllConditioned(condition))?;
    Ok((0..projectors)
        .map(|k| {
            let coef = chol.solve(&(design.transpose() * &targets[k]));
            let c = coef[k].max(0.0);
            c / (1.0 + c)
        })
        .collect())
}

/// Removes the stray light of the dark projectors from the frames of a scan. With every
/// projector's white frame `W_k = S_k + sum_{j != k} b_j S_j`, solving this 4x4 (or NxN) system
/// per pixel gives `S_k`; the stray light under projector k is `W_k - S_k`, the same in every
/// frame lit by k.
pub fn stray_light(whites: &[&Rgb32FImage], black_levels: &[f64]) -> Option<Vec<Rgb32FImage>> {
    let n = whites.len();
    if n != black_levels.len() || n == 0 || n > 4 {
        return None;
    }
    let mut m = Matrix4::<f64>::identity();
    for k in 0..n {
        for j in 0..n {
            if j != k {
                m[(k, j)] = black_levels[j];
            }
        }
    }
    let inverse = m.view((0, 0), (n, n)).into_owned().try_inverse()?;
    let (w, h) = whites[0].dimensions();
    if whites.iter().any(|i| i.dimensions() != (w, h)) {
        return None;
    }
    let mut rows = [[0.0f64; 4]; 4];
    for (k, row) in rows.iter_mut().enumerate().take(n) {
        for (j, entry) in row.iter_mut().enumerate().take(n) {
            *entry = inverse[(k, j)];
        }
    }
    let mut out: Vec<Rgb32FImage> = (0..n).map(|_| Rgb32FImage::new(w, h)).collect();
    // The samples are independent: blocks of them go to the threads, each block writing its
    // part of every projector's image.
    let mut blocks: Vec<Vec<&mut [f32]>> = Vec::new();
    for image in &mut out {
        let raw: &mut [f32] = image;
        for (b, part) in raw.chunks_mut(STRAY_BLOCK).enumerate() {
            if b == blocks.len() {
                blocks.push(Vec::with_capacity(n));
            }
            blocks[b].push(part);
        }
    }
    blocks
        .into_par_iter()
        .enumerate()
        .for_each(|(b, mut parts)| {
            let start = b * STRAY_BLOCK;
            for i in 0..parts[0].len() {
                let mut white = [0.0f64; 4];
                for (k, v) in white.iter_mut().enumerate().take(n) {
                    *v = f64::from(whites[k].as_raw()[start + i]);
                }
                for (k, part) in parts.iter_mut().enumerate() {
                    let stray = (white[k] - own_light(&rows[k], &white, n)).max(0.0);
                    part[i] = if stray.is_finite() { stray as f32 } else { 0.0 };
                }
            }
        });
    Some(out)
}

/// Samples per block of [`stray_light`]'s parallel loop.
const STRAY_BLOCK: usize = 1 << 16;

/// Row `row` of the inverse times the first `n` white readings, summed column by column as
/// nalgebra's matrix-vector product does (the same bits as the `DMatrix * DVector` this
/// replaces, without its heap vector per sample: `stray_light_matches_the_matrix_product`).
#[inline]
fn own_light(row: &[f64; 4], white: &[f64; 4], n: usize) -> f64 {
    let mut own = white[0] * row[0];
    for j in 1..n {
        own += white[j] * row[j];
    }
    own
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::capture::frame_plan::RESPONSE_LEVELS_MILLI;
    use nalgebra::{Point3, Vector3, Vector4};
    use rand::SeedableRng;

    const GAMMA: [f64; 4] = [2.2, 2.1, 2.3, 2.2];
    const BLACK: [f64; 4] = [0.02, 0.025, 0.018, 0.022];
    const PROJECTORS: [[f64; 3]; 4] = [
        [-260.0, -200.0, -420.0],
        [260.0, -200.0, -420.0],
        [-260.0, 200.0, -420.0],
        [260.0, 200.0, -420.0],
    ];

    /// Reading of projector k's white alone on a chessboard plane through the origin with normal
    /// `normal`, seen by a 64x48 grid of camera pixels 2 mm apart.
    fn own_white(k: usize, normal: &Vector3<f64>) -> Vec<f64> {
        let light = Point3::from(PROJECTORS[k]);
        let reference = light.coords.norm_squared();
        (0..64 * 48)
            .map(|p| {
                let (x, y) = ((p % 64) as f64 * 2.0 - 64.0, (p / 64) as f64 * 2.0 - 48.0);
                // Point on the plane n . X = 0 below camera ray (x, y).
                let z = -(normal.x * x + normal.y * y) / normal.z;
                let point = Point3::new(x, y, z);
                let to_light = light - point;
                let r2 = to_light.norm_squared();
                let cosine = to_light.normalize().dot(normal).max(0.0);
                let square = ((x / 16.0).floor() + (y / 16.0).floor()) as i64;
                let albedo = if square.rem_euclid(2) == 0 { 0.8 } else { 0.05 };
                0.6 * albedo * cosine * reference / r2
            })
            .collect()
    }

    /// Calibration frames of one pose, with or without the other projectors' black level, with
    /// shot and read noise of a 12-bit camera.
    fn pose(normal: Vector3<f64>, stray: bool, seed: u64) -> Vec<LevelFrames> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let own: Vec<Vec<f64>> = (0..4).map(|k| own_white(k, &normal)).collect();
        let mut levels = vec![0.0, 1.0];
        levels.extend(RESPONSE_LEVELS_MILLI.iter().map(|&m| m as f64 / 1000.0));
        (0..4)
            .map(|k| LevelFrames {
                frames: levels
                    .iter()
                    .map(|&v| {
                        let emitted = BLACK[k] + (1.0 - BLACK[k]) * v.powf(GAMMA[k]);
                        let data = (0..own[k].len() * 3)
                            .map(|i| {
                                let p = i / 3;
                                let others: f64 = (0..4)
                                    .filter(|&j| j != k && stray)
                                    .map(|j| BLACK[j] * own[j][p])
                                    .sum();
                                let clean = own[k][p] * emitted + others;
                                let sigma = (clean / 12000.0 + (2.0f64 / 4095.0).powi(2)).sqrt();
                                let noise: f64 = rand_distr_normal(&mut rng) * sigma;
                                (((clean + noise).clamp(0.0, 1.0) * 4095.0).round() / 4095.0) as f32
                            })
                            .collect();
                        (v, Rgb32FImage::from_raw(64, 48, data).unwrap())
                    })
                    .collect(),
            })
            .collect()
    }

    fn rand_distr_normal<R: rand::Rng>(rng: &mut R) -> f64 {
        let u1: f64 = rng.gen_range(f64::EPSILON..1.0);
        let u2: f64 = rng.r#gen();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    fn poses(stray: bool) -> Vec<Vec<LevelFrames>> {
        [
            Vector3::new(0.0, 0.0, -1.0),
            Vector3::new(0.3, 0.1, -1.0).normalize(),
            Vector3::new(-0.2, 0.35, -1.0).normalize(),
        ]
        .into_iter()
        .enumerate()
        .map(|(i, n)| pose(n, stray, i as u64))
        .collect()
    }

    #[test]
    fn gamma_within_2_percent_and_black_within_10_percent_with_stray_black() {
        for stray in [true, false] {
            let fits = estimate_responses(&poses(stray)).unwrap();
            for (k, fit) in fits.iter().enumerate() {
                let eg = (fit.gamma - GAMMA[k]).abs() / GAMMA[k];
                let eb = (fit.black_level - BLACK[k]).abs() / BLACK[k];
                eprintln!("stray {stray} projector {k}: gamma error {eg:.4}, black error {eb:.4}");
                assert!(
                    eg < 0.02,
                    "stray {stray} projector {k}: gamma {} vs {}",
                    fit.gamma,
                    GAMMA[k]
                );
                assert!(
                    eb < 0.10,
                    "stray {stray} projector {k}: black {} vs {}",
                    fit.black_level,
                    BLACK[k]
                );
            }
        }
    }

    #[test]
    fn ignoring_the_stray_black_would_overestimate_black_levels() {
        // The naive estimate (black frame / white frame) counts the other projectors' light.
        let p = poses(true);
        let white = level_image(&p[0][0], 1.0).unwrap();
        let black = level_image(&p[0][0], 0.0).unwrap();
        let mut ratios: Vec<f32> = white
            .iter()
            .zip(&black)
            .filter(|(w, _)| **w > 0.2)
            .map(|(w, b)| b / w)
            .collect();
        ratios.sort_by(f32::total_cmp);
        assert!(ratios[ratios.len() / 2] as f64 > 2.0 * BLACK[0]);
    }

    #[test]
    fn missing_levels_and_dark_frames_are_errors() {
        let mut p = poses(false);
        p[0][2].frames.retain(|(l, _)| *l != 1.0);
        assert!(matches!(
            estimate_responses(&p),
            Err(ResponseError::MissingLevels(2))
        ));
        let dark = vec![vec![
            LevelFrames {
                frames: vec![
                    (0.0, Rgb32FImage::new(8, 8)),
                    (1.0, Rgb32FImage::new(8, 8)),
                    (0.5, Rgb32FImage::new(8, 8))
                ],
            };
            4
        ]];
        assert!(matches!(
            estimate_responses(&dark),
            Err(ResponseError::TooFewPixels(0))
        ));
    }

    /// The plain per-pixel solve `stray_light` had: nalgebra's product of the inverse with
    /// each pixel's white readings.
    fn stray_light_by_matrix_product(whites: &[&Rgb32FImage], black: &[f64]) -> Vec<Vec<f32>> {
        let n = whites.len();
        let mut m = Matrix4::<f64>::identity();
        for k in 0..n {
            for j in 0..n {
                if j != k {
                    m[(k, j)] = black[j];
                }
            }
        }
        let inverse = m.view((0, 0), (n, n)).into_owned().try_inverse().unwrap();
        let mut out = vec![vec![0.0f32; whites[0].as_raw().len()]; n];
        for (i, _) in whites[0].as_raw().iter().enumerate() {
            let mut white = Vector4::zeros();
            for k in 0..n {
                white[k] = whites[k].as_raw()[i] as f64;
            }
            let own = &inverse * white.rows(0, n);
            for k in 0..n {
                let stray = (white[k] - own[k]).max(0.0);
                out[k][i] = if stray.is_finite() { stray as f32 } else { 0.0 };
            }
        }
        out
    }

    #[test]
    fn stray_light_matches_the_matrix_product() {
        use rand::Rng;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(19);
        for n in 1..=4 {
            // Wider than one block of the parallel loop, not a multiple of it.
            let (w, h) = (301, 229);
            let black: Vec<f64> = (0..n).map(|_| rng.gen_range(0.0..0.05)).collect();
            let whites: Vec<Rgb32FImage> = (0..n)
                .map(|_| {
                    Rgb32FImage::from_fn(w, h, |x, _| {
                        let v: f32 = rng.gen_range(0.0..1.5);
                        // Saturated, dark and broken readings too.
                        image::Rgb(match x % 97 {
                            0 => [f32::NAN, f32::INFINITY, 0.0],
                            1 => [0.0, -0.0, 1.0],
                            _ => [v, v * 0.7, v * 0.4],
                        })
                    })
                })
                .collect();
            let refs: Vec<&Rgb32FImage> = whites.iter().collect();
            let fast = stray_light(&refs, &black).unwrap();
            let plain = stray_light_by_matrix_product(&refs, &black);
            for (k, (f, p)) in fast.iter().zip(&plain).enumerate() {
                let f_bits: Vec<u32> = f.as_raw().iter().map(|v| v.to_bits()).collect();
                let p_bits: Vec<u32> = p.iter().map(|v| v.to_bits()).collect();
                assert!(f_bits == p_bits, "{n} projectors, projector {k} differs");
            }
        }
    }

    #[test]
    fn stray_light_is_recovered_exactly_from_the_white_frames() {
        let normal = Vector3::new(0.1, 0.0, -1.0).normalize();
        let own: Vec<Vec<f64>> = (0..4).map(|k| own_white(k, &normal)).collect();
        let whites: Vec<Rgb32FImage> = (0..4)
            .map(|k| {
                Rgb32FImage::from_fn(64, 48, |x, y| {
                    let p = (y * 64 + x) as usize;
                    let v = own[k][p]
                        + (0..4)
                            .filter(|&j| j != k)
                            .map(|j| BLACK[j] * own[j][p])
                            .sum::<f64>();
                    image::Rgb([v as f32; 3])
                })
            })
            .collect();
        let refs: Vec<&Rgb32FImage> = whites.iter().collect();
        let stray = stray_light(&refs, &BLACK).unwrap();
        for (k, stray_k) in stray.iter().enumerate() {
            for p in [0usize, 1000, 3000] {
                let truth: f64 = (0..4)
                    .filter(|&j| j != k)
                    .map(|j| BLACK[j] * own[j][p])
                    .sum();
                let got = stray_k.as_raw()[p * 3] as f64;
                assert!(
                    (got - truth).abs() < 1e-6,
                    "projector {k} pixel {p}: {got} vs {truth}"
                );
            }
        }
    }
}

//! Chessboard inner-corner detection with sub-pixel refinement, for real photos (perspective,
//! uneven light, partial shadows) and simulated frames alike. No OpenCV: the steps are
//!
//! 1. saddle response: the negative determinant of the Hessian of a Gaussian-smoothed image, which is
//!    large only where two dark and two bright quadrants meet (an X-junction), and whose local maxima
//!    are the candidate corners;
//! 2. a ring test on every candidate: intensities on a circle around it, thresholded at their own
//!    mean (so uneven light does not matter), must change sign exactly four times with four arcs of
//!    sensible length; the sign changes also give the two edge directions through the corner;
//! 3. grid assembly: from a seed, neighbours are looked for along the edge directions, then the grid
//!    grows by linear extrapolation of rows and columns, accepting only candidates close to the
//!    prediction; the grid must come out exactly `cols x rows`;
//! 4. refinement in the manner of OpenCV's `cornerSubPix`: the corner is the point that every image
//!    gradient in a small Gaussian-weighted window is orthogonal to (least squares, iterated).
//!
//! Conventions
//! - Pixel coordinates: origin at the top-left pixel, pixel centres at integer coordinates (x right,
//!   y down), the same as [`mlsss_core::calibration`].
//! - Corners are returned row-major, `cols` per row, like OpenCV's `findChessboardCorners` for a
//!   pattern size `(cols, rows)`: index `r * cols + c` is board point `(c, r)`. The first corner is
//!   the one nearest the image's top-left and rows run along the board axis that has `cols`
//!   corners. The labelling is always a rotation of the board (never a mirror image), so that with
//!   board points `(c * square, r * square, 0)` the board's +z axis points away from the camera.

use std::collections::HashMap;

use nalgebra::{Matrix2, Point2, Vector2};

use mlsss_core::gaussian_blur::{BlurError, Border, GaussianKernel, Normalisation, blur_2d};
use mlsss_core::imageio::GrayF32;

/// Why no chessboard was found in an image.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ChessboardError {
    /// The image is too small or has no contrast at all.
    #[error("image is {width}x{height} with intensity range {range:.4}: nothing to detect")]
    EmptyImage { width: u32, height: u32, range: f32 },
    /// Too few X-junctions were found to hold the board.
    #[error("found {found} chessboard-like corners, the board needs {needed}")]
    TooFewCorners { found: usize, needed: usize },
    /// Corners were found but no seed grew into a complete `cols x rows` grid.
    #[error(
        "no complete {cols}x{rows} grid of inner corners (largest grid found: {best_cols}x{best_rows}); \
         is the whole board visible and is --board right?"
    )]
    NoGrid {
        cols: usize,
        rows: usize,
        best_cols: usize,
        best_rows: usize,
    },
    /// The image's pixel buffer does not hold `width x height` values.
    #[error("image buffer: {0}")]
    Shape(#[from] BlurError),
}

/// Tuning of the detector. The defaults work for boards whose squares are 12 to 200 pixels wide.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectorOptions {
    /// Standard deviation (px) of the smoothing before the saddle response.
    pub response_sigma: f32,
    /// Radius (px) of the ring test.
    pub ring_radius: f32,
    /// Smallest ring contrast (bright mean minus dark mean) relative to the image's intensity range.
    pub min_ring_contrast: f32,
    /// Tolerance of grid growth, as a fraction of the local grid step.
    pub growth_tolerance: f64,
    /// Half size (px) of the refinement window; `None` picks a third of the grid step, at most 10.
    pub refine_half_window: Option<usize>,
}

impl Default for DetectorOptions {
    fn default() -> Self {
        Self {
            response_sigma: 2.0,
            ring_radius: 5.0,
            min_ring_contrast: 0.04,
            growth_tolerance: 0.3,
            refine_half_window: None,
        }
    }
}

/// A candidate X-junction: position and the two edge directions through it (unit vectors).
#[derive(Debug, Clone, Copy)]
struct Candidate {
    position: Vector2<f64>,
    edges: [Vector2<f64>; 2],
}

/// Finds the `cols x rows` inner corners of a chessboard in `image` (any intensity scale).
pub fn find_chessboard_corners(
    image: &GrayF32,
    cols: usize,
    rows: usize,
    options: &DetectorOptions,
) -> Result<Vec<Point2<f64>>, ChessboardError> {
    let range = intensity_range(image);
    if image.width < 16 || image.height < 16 || range <= 0.0 {
        return Err(ChessboardError::EmptyImage {
            width: image.width,
            height: image.height,
            range,
        });
    }
    let smoothed = gaussian_blur(image, options.response_sigma)?;
    let response = saddle_response(&smoothed);
    let candidates = ring_tested_candidates(&smoothed, &response, range, options);
    let needed = cols * rows;
    if candidates.len() < needed {
        return Err(ChessboardError::TooFewCorners {
            found: candidates.len(),
            needed,
        });
    }
    let grid = assemble_grid(&candidates, cols, rows, options.growth_tolerance)?;
    let ordered = order_grid(grid, cols, rows);
    let step = mean_grid_step(&ordered, cols);
    let half = options
        .refine_half_window
        .unwrap_or_else(|| ((step / 3.0).round() as usize).clamp(2, 10));
    let fine = gaussian_blur(image, 0.8)?;
    Ok(ordered
        .iter()
        .map(|p| refine_corner(&fine, Point2::from(*p), half))
        .collect())
}

fn intensity_range(image: &GrayF32) -> f32 {
    let (lo, hi) = image
        .data
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if lo.is_finite() && hi.is_finite() {
        hi - lo
    } else {
        0.0
    }
}

/// Separable Gaussian blur with clamped borders, truncated at 3 sigma; the kernel is built and
/// applied in `f32`.
pub fn gaussian_blur(image: &GrayF32, sigma: f32) -> Result<GrayF32, BlurError> {
    let kernel = GaussianKernel::new(sigma, 3.0, Normalisation::Weights);
    let mut out = image.clone();
    blur_2d(
        &mut out.data,
        image.width as usize,
        image.height as usize,
        &kernel,
        Border::Clamp,
    )?;
    Ok(out)
}

/// `Lxy^2 - Lxx Lyy`: positive at saddle points (X-junctions), about zero on straight edges.
fn saddle_response(smoothed: &GrayF32) -> GrayF32 {
    let (w, h) = (smoothed.width as usize, smoothed.height as usize);
    let mut out = GrayF32::new(smoothed.width, smoothed.height);
    let at = |x: usize, y: usize| smoothed.data[y * w + x];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let c = at(x, y);
            let lxx = at(x + 1, y) - 2.0 * c + at(x - 1, y);
            let lyy = at(x, y + 1) - 2.0 * c + at(x, y - 1);
            let lxy =
                0.25 * (at(x + 1, y + 1) - at(x + 1, y - 1) - at(x - 1, y + 1) + at(x - 1, y - 1));
            out.data[y * w + x] = (lxy * lxy - lxx * lyy).max(0.0);
        }
    }
    out
}

/// Bilinear sample with clamping to the image.
pub fn sample_bilinear(image: &GrayF32, x: f64, y: f64) -> f32 {
    let (w, h) = (image.width as usize, image.height as usize);
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let d = &image.data;
    let top = d[y0 * w + x0] * (1.0 - fx) + d[y0 * w + x1] * fx;
    let bottom = d[y1 * w + x0] * (1.0 - fx) + d[y1 * w + x1] * fx;
    top * (1.0 - fy) + bottom * fy
}

/// Local maxima of the saddle response that pass the ring test, strongest first.
fn ring_tested_candidates(
    smoothed: &GrayF32,
    response: &GrayF32,
    range: f32,
    options: &DetectorOptions,
) -> Vec<Candidate> {
    let (w, h) = (response.width as usize, response.height as usize);
    let margin = (options.ring_radius.ceil() as usize + 2).max(3);
    let peak = response.data.iter().cloned().fold(0.0f32, f32::max);
    // A very low floor: contrast is checked by the ring test, which is insensitive to shading.
    let floor = peak * 1e-3;
    let mut maxima = Vec::new();
    for y in margin..h.saturating_sub(margin) {
        for x in margin..w.saturating_sub(margin) {
            let v = response.data[y * w + x];
            if v <= floor || !is_local_maximum(response, x, y, 3) {
                continue;
            }
            maxima.push((x, y, v));
        }
    }
    maxima.sort_by(|a, b| b.2.total_cmp(&a.2));
    maxima.truncate(5000);
    maxima
        .into_iter()
        .filter_map(|(x, y, _)| {
            let position = peak_offset(response, x, y);
            let edges = ring_test(
                smoothed,
                position,
                options.ring_radius,
                range * options.min_ring_contrast,
            )?;
            Some(Candidate { position, edges })
        })
        .collect()
}

fn is_local_maximum(image: &GrayF32, x: usize, y: usize, radius: usize) -> bool {
    let w = image.width as usize;
    let v = image.data[y * w + x];
    for yy in y.saturating_sub(radius)..=(y + radius).min(image.height as usize - 1) {
        for xx in x.saturating_sub(radius)..=(x + radius).min(w - 1) {
            let u = image.data[yy * w + xx];
            // Ties are broken by position so a plateau yields exactly one maximum.
            if u > v || (u == v && (yy, xx) < (y, x)) {
                return false;
            }
        }
    }
    true
}

/// Sub-pixel position of a response peak by a 1-D parabola along each axis.
fn peak_offset(response: &GrayF32, x: usize, y: usize) -> Vector2<f64> {
    let w = response.width as usize;
    let at = |xx: usize, yy: usize| response.data[yy * w + xx] as f64;
    let parabola = |m: f64, c: f64, p: f64| {
        let denom = m - 2.0 * c + p;
        if denom.abs() < 1e-12 {
            0.0
        } else {
            (0.5 * (m - p) / denom).clamp(-0.5, 0.5)
        }
    };
    let dx = parabola(at(x - 1, y), at(x, y), at(x + 1, y));
    let dy = parabola(at(x, y - 1), at(x, y), at(x, y + 1));
    Vector2::new(x as f64 + dx, y as f64 + dy)
}

/// The ring test: `Some(edge directions)` when the circle around `centre` reads
/// bright-dark-bright-dark with four arcs of similar size and enough contrast.
fn ring_test(
    smoothed: &GrayF32,
    centre: Vector2<f64>,
    radius: f32,
    min_contrast: f32,
) -> Option<[Vector2<f64>; 2]> {
    const SAMPLES: usize = 32;
    let angle = |i: usize| i as f64 * std::f64::consts::TAU / SAMPLES as f64;
    let values: Vec<f32> = (0..SAMPLES)
        .map(|i| {
            let a = angle(i);
            sample_bilinear(
                smoothed,
                centre.x + radius as f64 * a.cos(),
                centre.y + radius as f64 * a.sin(),
            )
        })
        .collect();
    let mean = values.iter().sum::<f32>() / SAMPLES as f32;
    let bright: Vec<bool> = values.iter().map(|&v| v > mean).collect();
    let transitions: Vec<usize> = (0..SAMPLES)
        .filter(|&i| bright[i] != bright[(i + 1) % SAMPLES])
        .collect();
    if transitions.len() != 4 {
        return None;
    }
    // Each of the four arcs must span at least 1/8 of the circle (perspective squeezes them, but
    // an L-corner or an edge end gives a very unequal split).
    for k in 0..4 {
        let arc = (transitions[(k + 1) % 4] + SAMPLES - transitions[k]) % SAMPLES;
        if arc < SAMPLES / 8 {
            return None;
        }
    }
    let (mut hi, mut nh, mut lo, mut nl) = (0.0, 0, 0.0, 0);
    for (&v, &b) in values.iter().zip(&bright) {
        if b {
            hi += v;
            nh += 1;
        } else {
            lo += v;
            nl += 1;
        }
    }
    if hi / nh as f32 - lo / nl as f32 <= min_contrast {
        return None;
    }
    // Edge k crosses the circle between samples t and t+1 and again on the opposite side.
    let crossing = |t: usize| angle(t) + 0.5 * std::f64::consts::TAU / SAMPLES as f64;
    let direction = |a: f64, b: f64| {
        // Average of two opposite crossings as an axis (angle doubled to ignore the sign).
        let (s, c) = (
            (2.0 * a).sin() + (2.0 * b).sin(),
            (2.0 * a).cos() + (2.0 * b).cos(),
        );
        let axis = 0.5 * s.atan2(c);
        Vector2::new(axis.cos(), axis.sin())
    };
    Some([
        direction(crossing(transitions[0]), crossing(transitions[2])),
        direction(crossing(transitions[1]), crossing(transitions[3])),
    ])
}

/// Integer grid coordinates (column, row) to corner position.
type Grid = HashMap<(i32, i32), Vector2<f64>>;

/// Grows grids from the strongest candidates and returns the first complete `cols x rows` one.
fn assemble_grid(
    candidates: &[Candidate],
    cols: usize,
    rows: usize,
    tolerance: f64,
) -> Result<Grid, ChessboardError> {
    let mut best = (0usize, 0usize);
    let needed = cols * rows;
    // Seeds: strongest candidates first; a wrong seed (a saddle on a label or tape) just fails.
    for seed in 0..candidates.len().min(60) {
        let Some(grid) = grow_grid(candidates, seed, tolerance) else {
            continue;
        };
        let (gc, gr) = grid_extent(&grid);
        if gc * gr > best.0 * best.1 {
            best = (gc, gr);
        }
        let complete =
            grid.len() == needed && ((gc, gr) == (cols, rows) || (gc, gr) == (rows, cols));
        if complete {
            return Ok(grid);
        }
    }
    Err(ChessboardError::NoGrid {
        cols,
        rows,
        best_cols: best.0,
        best_rows: best.1,
    })
}

fn grid_extent(grid: &Grid) -> (usize, usize) {
    let (mut c0, mut c1, mut r0, mut r1) = (i32::MAX, i32::MIN, i32::MAX, i32::MIN);
    for &(c, r) in grid.keys() {
        c0 = c0.min(c);
        c1 = c1.max(c);
        r0 = r0.min(r);
        r1 = r1.max(r);
    }
    if grid.is_empty() {
        return (0, 0);
    }
    ((c1 - c0 + 1) as usize, (r1 - r0 + 1) as usize)
}

/// Nearest unused candidate within `radius` of `target`.
fn nearest_candidate(
    candidates: &[Candidate],
    used: &[bool],
    target: Vector2<f64>,
    radius: f64,
) -> Option<usize> {
    candidates
        .iter()
        .enumerate()
        .filter(|(i, _)| !used[*i])
        .map(|(i, c)| (i, (c.position - target).norm()))
        .filter(|&(_, d)| d < radius)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Nearest candidate roughly along `direction` (within about 20 degrees) from `from`.
fn neighbour_along(
    candidates: &[Candidate],
    from: Vector2<f64>,
    direction: Vector2<f64>,
) -> Option<usize> {
    candidates
        .iter()
        .enumerate()
        .filter_map(|(i, c)| {
            let d = c.position - from;
            let along = d.dot(&direction);
            let dist = d.norm();
            (along > 3.0 && along > 0.94 * dist).then_some((i, dist))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Grows a grid from candidate `seed`: first its four neighbours along its edge directions, then
/// row/column extrapolation until nothing more fits.
fn grow_grid(candidates: &[Candidate], seed: usize, tolerance: f64) -> Option<Grid> {
    let mut used = vec![false; candidates.len()];
    let mut grid = Grid::new();
    let origin = candidates[seed].position;
    used[seed] = true;
    grid.insert((0, 0), origin);
    let [e0, e1] = candidates[seed].edges;
    for (key, dir) in [((1, 0), e0), ((-1, 0), -e0), ((0, 1), e1), ((0, -1), -e1)] {
        let i = neighbour_along(candidates, origin, dir)?;
        if used[i] {
            return None;
        }
        used[i] = true;
        grid.insert(key, candidates[i].position);
    }
    // The two steps along an axis must agree (same line, similar length).
    let consistent = |a: Vector2<f64>, b: Vector2<f64>| {
        let (na, nb) = (a.norm(), b.norm());
        na.min(nb) > 0.6 * na.max(nb) && a.dot(&b) > 0.9 * na * nb
    };
    if !consistent(grid[&(1, 0)] - origin, origin - grid[&(-1, 0)])
        || !consistent(grid[&(0, 1)] - origin, origin - grid[&(0, -1)])
    {
        return None;
    }
    loop {
        let mut added = false;
        let keys: Vec<(i32, i32)> = grid.keys().copied().collect();
        let mut frontier: Vec<(i32, i32)> = keys
            .iter()
            .flat_map(|&(c, r)| [(c + 1, r), (c - 1, r), (c, r + 1), (c, r - 1)])
            .filter(|k| !grid.contains_key(k))
            .collect();
        frontier.sort_unstable();
        frontier.dedup();
        for key in frontier {
            let Some((prediction, step)) = predict(&grid, key) else {
                continue;
            };
            if let Some(i) = nearest_candidate(candidates, &used, prediction, tolerance * step) {
                used[i] = true;
                grid.insert(key, candidates[i].position);
                added = true;
            }
        }
        if !added {
            break;
        }
        if grid.len() > 4000 {
            return None;
        }
    }
    Some(grid)
}

/// Predicted position of grid cell `key` by linear extrapolation from two known cells in a line
/// (row or column), or else by completing a parallelogram, plus the local step length; averages
/// the predictions that exist.
fn predict(grid: &Grid, key: (i32, i32)) -> Option<(Vector2<f64>, f64)> {
    let (c, r) = key;
    let mut sum = Vector2::zeros();
    let mut step = 0.0;
    let mut n = 0.0;
    for (dc, dr) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
        let (Some(p1), Some(p2)) = (
            grid.get(&(c + dc, r + dr)),
            grid.get(&(c + 2 * dc, r + 2 * dr)),
        ) else {
            continue;
        };
        sum += 2.0 * p1 - p2;
        step += (p1 - p2).norm();
        n += 1.0;
    }
    if n == 0.0 {
        // No two cells in a line: complete a parallelogram from a corner of known cells.
        for (dc, dr) in [(1, 1), (1, -1), (-1, 1), (-1, -1)] {
            let (Some(a), Some(b), Some(d)) = (
                grid.get(&(c + dc, r)),
                grid.get(&(c, r + dr)),
                grid.get(&(c + dc, r + dr)),
            ) else {
                continue;
            };
            sum += a + b - d;
            step += 0.5 * ((a - d).norm() + (b - d).norm());
            n += 1.0;
        }
    }
    (n > 0.0).then(|| (sum / n, step / n))
}

/// Turns a complete grid into the row-major corner list described in the module conventions.
fn order_grid(grid: Grid, cols: usize, rows: usize) -> Vec<Vector2<f64>> {
    let (gc, gr) = grid_extent(&grid);
    let c0 = grid.keys().map(|k| k.0).min().unwrap_or(0);
    let r0 = grid.keys().map(|k| k.1).min().unwrap_or(0);
    let at = |c: usize, r: usize| grid[&(c0 + c as i32, r0 + r as i32)];
    // Table indexed [row][col] along the axis that has `cols` corners.
    let mut table: Vec<Vec<Vector2<f64>>> = if (gc, gr) == (cols, rows) {
        (0..rows)
            .map(|r| (0..cols).map(|c| at(c, r)).collect())
            .collect()
    } else {
        (0..rows)
            .map(|r| (0..cols).map(|c| at(r, c)).collect())
            .collect()
    };
    // Make the labelling a rotation: column direction x row direction must be positive in image
    // coordinates (x right, y down), i.e. the board's z axis points away from the camera.
    let col_dir = table[0][cols - 1] - table[0][0];
    let row_dir = table[rows - 1][0] - table[0][0];
    if col_dir.x * row_dir.y - col_dir.y * row_dir.x < 0.0 {
        table.reverse();
    }
    // Of the two rotations that keep the axes (0 and 180 degrees), start nearest the top-left.
    let first = table[0][0];
    let last = table[rows - 1][cols - 1];
    if last.x + last.y < first.x + first.y {
        table.reverse();
        for row in &mut table {
            row.reverse();
        }
    }
    table.into_iter().flatten().collect()
}

fn mean_grid_step(corners: &[Vector2<f64>], cols: usize) -> f64 {
    let steps: Vec<f64> = corners
        .windows(2)
        .enumerate()
        .filter(|(i, _)| (i + 1) % cols != 0)
        .map(|(_, w)| (w[1] - w[0]).norm())
        .collect();
    if steps.is_empty() {
        return 10.0;
    }
    steps.iter().sum::<f64>() / steps.len() as f64
}

/// Sub-pixel corner refinement (the `cornerSubPix` idea): every gradient `g` at a point `q` near a
/// corner `p` satisfies `g . (q - p) = 0`, so `p` solves `sum(g g^T) p = sum(g g^T q)`, with
/// Gaussian weights. Iterated from the integer estimate until it moves less than 1e-3 px.
pub fn refine_corner(image: &GrayF32, start: Point2<f64>, half: usize) -> Point2<f64> {
    let mut p = start.coords;
    let half = half as isize;
    let sigma = half as f64 * 0.6 + 0.5;
    let offsets: Vec<(f64, f64, f64)> = (-half..=half)
        .flat_map(|dy| (-half..=half).map(move |dx| (dx as f64, dy as f64)))
        .filter_map(|(dx, dy)| {
            // The gradients right at the saddle are unreliable; OpenCV leaves out a zone too.
            let r2 = dx * dx + dy * dy;
            (r2 >= 1.0).then(|| (dx, dy, (-r2 / (2.0 * sigma * sigma)).exp()))
        })
        .collect();
    let mut gradients = Vec::with_capacity(offsets.len());
    for _ in 0..30 {
        gradients.clear();
        let mut mean = Vector2::zeros();
        let mut total = 0.0;
        for &(dx, dy, weight) in &offsets {
            let q = Vector2::new(p.x + dx, p.y + dy);
            let g = gradient(image, q);
            mean += g * weight;
            total += weight;
            gradients.push((q, g, weight));
        }
        // Smooth shading adds about the same vector to every gradient and tilts the edges'
        // gradients, which biases the corner by several hundredths of a pixel. The board's own
        // gradients cancel over a window centred on an X-junction (each edge line changes sign at
        // the corner), so the weighted mean gradient is the shading's and is removed.
        mean /= total;
        let mut a = Matrix2::zeros();
        let mut b = Vector2::zeros();
        for &(q, g, weight) in &gradients {
            let g = g - mean;
            let ggt = g * g.transpose() * weight;
            a += ggt;
            b += ggt * q;
        }
        let Some(inv) = a.try_inverse() else {
            break;
        };
        let next = inv * b;
        if !next.x.is_finite() || !next.y.is_finite() || (next - start.coords).norm() > half as f64
        {
            return start;
        }
        let moved = (next - p).norm();
        p = next;
        if moved < 1e-3 {
            break;
        }
    }
    Point2::from(p)
}

/// Central-difference gradient at a sub-pixel position (bilinear samples).
fn gradient(image: &GrayF32, q: Vector2<f64>) -> Vector2<f64> {
    let gx = sample_bilinear(image, q.x + 1.0, q.y) - sample_bilinear(image, q.x - 1.0, q.y);
    let gy = sample_bilinear(image, q.x, q.y + 1.0) - sample_bilinear(image, q.x, q.y - 1.0);
    Vector2::new(0.5 * gx as f64, 0.5 * gy as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A perspective chessboard rendered with anti-aliasing (supersampled), with known corners.
    pub(crate) fn render_board(
        width: u32,
        height: u32,
        homography: &nalgebra::Matrix3<f64>,
        squares: (i32, i32),
        shade: impl Fn(f64, f64) -> f32,
    ) -> GrayF32 {
        let inv = homography.try_inverse().unwrap();
        let mut img = GrayF32::new(width, height);
        const SS: usize = 8;
        for y in 0..height {
            for x in 0..width {
                let mut acc = 0.0;
                for sy in 0..SS {
                    for sx in 0..SS {
                        let px = x as f64 + (sx as f64 + 0.5) / SS as f64 - 0.5;
                        let py = y as f64 + (sy as f64 + 0.5) / SS as f64 - 0.5;
                        let b = inv * nalgebra::Vector3::new(px, py, 1.0);
                        let (u, v) = (b.x / b.z, b.y / b.z);
                        // Board units: squares of size 1; the board spans [-1, squares] with a
                        // white margin of one square.
                        let inside =
                            u >= 0.0 && v >= 0.0 && u < squares.0 as f64 && v < squares.1 as f64;
                        let dark = inside && ((u.floor() as i32 + v.floor() as i32) % 2 == 0);
                        acc += if dark { 0.1 } else { 0.9 };
                    }
                }
                img.set(x, y, acc / (SS * SS) as f32 * shade(x as f64, y as f64));
            }
        }
        img
    }

    #[test]
    fn finds_perspective_board_corners_to_sub_pixel_accuracy() {
        // Board of 8x6 squares -> 7x5 inner corners at integer board coordinates 1..=7, 1..=5.
        let h = nalgebra::Matrix3::new(38.0, 6.0, 60.0, -4.0, 35.0, 50.0, 0.0003, 0.0008, 1.0);
        // Uneven light: a strong gradient across the image.
        let img = render_board(420, 320, &h, (8, 6), |x, y| {
            (0.35 + 0.65 * (x / 420.0)) as f32 * (1.0 - 0.3 * (y / 320.0) as f32)
        });
        let corners = find_chessboard_corners(&img, 7, 5, &DetectorOptions::default()).unwrap();
        assert_eq!(corners.len(), 35);
        let mut worst: f64 = 0.0;
        for (i, c) in corners.iter().enumerate() {
            // Row-major from the top-left; the truth for board point (col+1, row+1).
            let (col, row) = ((i % 7) as f64 + 1.0, (i / 7) as f64 + 1.0);
            let t = h * nalgebra::Vector3::new(col, row, 1.0);
            let truth = Vector2::new(t.x / t.z, t.y / t.z);
            worst = worst.max((c.coords - truth).norm());
            eprintln!(
                "{i} {:.4} {:.4}",
                (c.coords - truth).x,
                (c.coords - truth).y
            );
        }
        assert!(worst < 0.03, "worst corner error {worst} px");
    }

    #[test]
    fn blank_and_wrong_size_boards_are_errors_not_panics() {
        let blank = GrayF32::new(200, 150);
        assert!(matches!(
            find_chessboard_corners(&blank, 7, 5, &DetectorOptions::default()),
            Err(ChessboardError::EmptyImage { .. })
        ));
        let h = nalgebra::Matrix3::new(30.0, 0.0, 40.0, 0.0, 30.0, 40.0, 0.0, 0.0, 1.0);
        let img = render_board(340, 260, &h, (8, 6), |_, _| 1.0);
        let err = find_chessboard_corners(&img, 6, 5, &DetectorOptions::default()).unwrap_err();
        assert!(
            matches!(
                err,
                ChessboardError::NoGrid {
                    best_cols: 7,
                    best_rows: 5,
                    ..
                }
            ),
            "{err}"
        );
    }
}

//! Robust N-light photometric stereo for Lambertian surfaces (Woodham 1980), with the shadow and
//! highlight handling of Barsky & Petrou 2003 generalised from 4 to N lights.
//!
//! Conventions
//! - All vectors of one pixel are in one frame (the lights file's frame for `mlsss normals`, the
//!   world frame of the calibration for the booth). Light directions and the view direction point
//!   from the surface towards the light and the camera; normals point out of the surface.
//! - A light reading is linear RGB. The model is `I_c = albedo_c * irradiance_c * max(0, n . d)`,
//!   where `irradiance_c` is the light's colour times its intensity at the pixel (for a near point
//!   light: intensity over the squared distance).
//!
//! Per pixel, the solver:
//! 1. drops unusable readings (non-finite, saturated) and shadowed ones (below an absolute noise
//!    floor, or an irradiance-normalised reading below `shadow_fraction` of the brightest);
//! 2. for RGB readings of a coloured surface, drops highlights by chromaticity: a specular
//!    reflection has the light's colour, so it pulls the reading's chromaticity towards white;
//! 3. solves least squares on the rest and checks the conditioning (flagged above
//!    `max_condition`) and the residuals;
//! 4. when a residual is too large, removes one reading at a time. With few lights (up to 8) every
//!    leave-one-out solution is tried: with 4 lights a single outlier cannot be found from the
//!    residuals (they all lie along one null vector), so the choice is made on physical
//!    plausibility as in Barsky & Petrou: a dark outlier must be much darker than predicted
//!    (cast shadow), a bright one must lie near the mirror direction of its light. With many
//!    lights the reading with the largest normalised residual is removed.
//! 5. flags a pixel with fewer than 3 good lights, an ill-conditioned light set, no signal, or a
//!    normal facing away from the camera; flagged pixels get a zero normal and albedo.

mod distant_least_squares;

use std::cell::RefCell;

use nalgebra::{Cholesky, Matrix3, U3, Vector3};

use crate::symmetric_eigen3;

/// The most lights a pixel can use (the `used` set is a 128-bit mask).
pub const MAX_LIGHTS: usize = 128;

/// Errors of photometric stereo.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PhotometricStereoError {
    /// More lights than [`MAX_LIGHTS`].
    #[error("{0} lights given; at most {MAX_LIGHTS} are supported")]
    TooManyLights(usize),
    /// Fewer than 3 lights: no normal can be solved.
    #[error("photometric stereo needs at least 3 lights, got {0}")]
    TooFewLights(usize),
    /// Images and lights disagree in number or size.
    #[error("{0}")]
    Mismatch(String),
}

/// Solver variant.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Least squares on every usable reading (the textbook baseline).
    LeastSquares,
    /// Shadow and highlight rejection, then least squares on the good readings.
    Robust,
}

/// Tuning of the solver. Defaults suit linear images in [0, 1].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PsParams {
    pub method: Method,
    /// Readings at or below this linear value are shadow/noise.
    pub noise_floor: f64,
    /// A reading whose irradiance-normalised value is below this fraction of the pixel's brightest
    /// one is treated as shadowed (robust method only).
    pub shadow_fraction: f64,
    /// Residual allowed per reading, as a fraction of the pixel's brightest reading (plus the
    /// noise floor).
    pub residual_tolerance: f64,
    /// Largest accepted condition number of the light matrix (ratio of its singular values).
    pub max_condition: f64,
    /// Readings at or above this value in any channel are saturated.
    pub saturation: f64,
    /// A reading whose chromaticity is this far (degrees) from the pixel's median, towards white,
    /// is a highlight (only used when the median chromaticity is clearly coloured).
    pub highlight_chroma_deg: f64,
}

impl Default for PsParams {
    fn default() -> Self {
        Self {
            method: Method::Robust,
            noise_floor: 2e-3,
            shadow_fraction: 0.05,
            residual_tolerance: 0.05,
            max_condition: 30.0,
            saturation: 0.999,
            highlight_chroma_deg: 4.0,
        }
    }
}

/// One light as seen from one pixel.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LightSample {
    /// Unit direction from the surface point to the light.
    pub direction: Vector3<f64>,
    /// Irradiance per channel at the pixel for a surface facing the light (colour x intensity x
    /// falloff).
    pub irradiance: [f64; 3],
}

/// Outcome of one pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[repr(u8)]
pub enum PixelStatus {
    /// Solved.
    Ok = 0,
    /// Not in the mask (not attempted).
    Masked = 1,
    /// Fewer than 3 good readings.
    TooFewLights = 2,
    /// The good lights are (nearly) coplanar: condition number above the limit.
    IllConditioned = 3,
    /// No light reached the pixel (every reading at the noise floor).
    NoSignal = 4,
    /// The solved normal faces away from the camera.
    BackFacing = 5,
}

/// Solution of one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSolution {
    /// Unit normal, or zero when flagged.
    pub normal: [f32; 3],
    /// RGB albedo, or zero when flagged.
    pub albedo: [f32; 3],
    /// RMS residual of the used readings relative to the brightest reading.
    pub residual: f32,
    /// Bit i set when light i was used.
    pub used: u128,
    pub status: PixelStatus,
}

impl PixelSolution {
    fn flagged(status: PixelStatus, used: u128) -> Self {
        Self {
            normal: [0.0; 3],
            albedo: [0.0; 3],
            residual: 0.0,
            used,
            status,
        }
    }

    /// Number of lights used.
    pub fn lights_used(&self) -> u32 {
        self.used.count_ones()
    }
}

/// Grey reading and light vector of one light at one pixel: `grey = albedo_grey * (vector . n)`.
#[derive(Debug, Clone, Copy)]
struct GreyReading {
    grey: f64,
    vector: Vector3<f64>,
    /// Irradiance-normalised reading (albedo x cosine).
    shading: f64,
    /// Chromaticity (unit RGB) after dividing out the light's colour.
    chroma: Vector3<f64>,
    /// The reading with the light's colour divided out (RGB).
    colour_free: Vector3<f64>,
}

/// Fills `out` with the grey reading of each light (reusing its allocation across pixels).
fn grey_readings_into(
    readings: &[[f32; 3]],
    lights: &[LightSample],
    out: &mut Vec<Option<GreyReading>>,
) {
    out.clear();
    out.extend(
        readings
            .iter()
            .zip(lights)
            .map(|(rgb, light)| grey_reading(rgb, light)),
    );
}

fn grey_reading(rgb: &[f32; 3], light: &LightSample) -> Option<GreyReading> {
    let scale = light.irradiance.iter().sum::<f64>() / 3.0;
    if !(scale > 0.0 && scale.is_finite()) || light.direction.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let mut colour_free = Vector3::zeros();
    for c in 0..3 {
        let relative = light.irradiance[c] / scale;
        colour_free[c] = if relative > 0.0 {
            rgb[c] as f64 / relative
        } else {
            0.0
        };
    }
    let grey = colour_free.sum() / 3.0;
    if !grey.is_finite() {
        return None;
    }
    let norm = colour_free.norm();
    Some(GreyReading {
        grey,
        vector: light.direction * scale,
        shading: grey / scale,
        chroma: if norm > 0.0 {
            colour_free / norm
        } else {
            Vector3::zeros()
        },
        colour_free,
    })
}

/// The Cholesky factor of a light set's normal matrix `A^T A` and its conditioning; `None` when
/// the matrix cannot be inverted.
type NormalFactor = Option<(Cholesky<f64, U3>, Conditioning)>;

/// A normal matrix's condition number, taken from its eigenvalues only when a cheap bound
/// cannot decide the test it is asked for. Why: every subset the robust fit tries got a 3x3
/// eigen decomposition (an `acos` and two `cos`), about 8 % of the full-size normals stage
/// (perf), though only the final set's number is ever compared, and with a bound far inside
/// the limit the comparison's outcome is known without it (the same outcome as the exact
/// number's, so the results are bit-identical).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Conditioning {
    normal_matrix: Matrix3<f64>,
    /// An upper bound of the squared condition number: `trace e2 / det`, with `e2` the sum of
    /// the principal 2x2 minors (for eigenvalues `l1 <= l2 <= l3`: `l3 <= trace`,
    /// `l2 l3 <= e2`, so `l1 = det / (l2 l3) >= det / e2`).
    squared_bound: f64,
}

impl Conditioning {
    /// Bounds below this squared condition bound are trusted to prove the matrix positive
    /// definite: its smallest eigenvalue is then at least `trace / 1e8`, ten orders of
    /// magnitude above the closed-form eigenvalues' rounding error.
    const TRUSTED_SQUARED_BOUND: f64 = 1e8;
    /// A bound this far inside a limit decides the test (the exact number, within rounding of
    /// the true one, cannot be on the other side).
    const MARGIN: f64 = 0.99;

    /// `None` when the matrix is not positive definite by its eigenvalues (as
    /// [`symmetric_eigen3::eigenvalues`] computes them) or its eigenvalues are not finite.
    fn of(normal_matrix: Matrix3<f64>) -> Option<Self> {
        let squared_bound = squared_condition_bound(&normal_matrix);
        // A NaN bound (not proven positive definite) is not trusted either.
        let trusted = squared_bound <= Self::TRUSTED_SQUARED_BOUND;
        if !trusted {
            exact_condition(&normal_matrix)?;
        }
        Some(Self {
            normal_matrix,
            squared_bound,
        })
    }

    /// Whether the condition number is at most `limit`.
    pub(crate) fn at_most(&self, limit: f64) -> bool {
        if self.squared_bound.sqrt() <= Self::MARGIN * limit {
            return true;
        }
        exact_condition(&self.normal_matrix).is_some_and(|condition| condition <= limit)
    }
}

/// The bound of [`Conditioning::squared_bound`]; NaN or infinite when the matrix is singular,
/// not positive definite, not finite, or so large that the eigenvalues could overflow.
fn squared_condition_bound(a: &Matrix3<f64>) -> f64 {
    const LARGEST: f64 = 1e100;
    let trace = a.trace();
    let e2 = a[(0, 0)] * a[(1, 1)] - a[(0, 1)] * a[(1, 0)] + a[(0, 0)] * a[(2, 2)]
        - a[(0, 2)] * a[(2, 0)]
        + a[(1, 1)] * a[(2, 2)]
        - a[(1, 2)] * a[(2, 1)];
    let det = a.determinant();
    let usable = a.iter().all(|v| v.is_finite() && v.abs() < LARGEST)
        && trace > 0.0
        && e2 > 0.0
        && det > 0.0;
    if usable { trace * e2 / det } else { f64::NAN }
}

/// The condition number `sqrt(largest / smallest eigenvalue)`; `None` when the smallest is not
/// positive or the largest not finite.
fn exact_condition(a: &Matrix3<f64>) -> Option<f64> {
    let [lo, _, hi] = symmetric_eigen3::eigenvalues(a)?;
    if lo.is_nan() || lo <= 0.0 || !hi.is_finite() {
        return None;
    }
    Some((hi / lo).sqrt())
}

/// Normal-matrix factors per light set. With distant lights (the same light vectors at every
/// pixel) a set's factor is the same for every pixel: it is computed once per thread and set and
/// reused (the per-pixel eigenvalues and Cholesky were most of the least-squares time). Otherwise
/// the cache holds one pixel's sets ([`NormalFactors::begin_pixel`] empties it). The arithmetic
/// is the same as without the cache, so the results are bit-identical.
struct NormalFactors {
    uniform: bool,
    cache: RefCell<Vec<(u128, NormalFactor)>>,
}

impl NormalFactors {
    /// Bound on the cached sets (many lights can yield many subsets; the rest are computed).
    const CAPACITY: usize = 256;

    fn new(uniform: bool) -> Self {
        Self {
            uniform,
            cache: RefCell::new(Vec::new()),
        }
    }

    /// Forgets the factors of the previous pixel's lights unless every pixel sees the same ones.
    fn begin_pixel(&self) {
        if !self.uniform {
            self.cache.borrow_mut().clear();
        }
    }

    /// The factor of `set`'s light vectors in `readings`: cached, as one pixel's solve asks for
    /// the same set more than once (the robust fit's set again for its condition number), and
    /// with distant lights every pixel does.
    fn get(&self, readings: &[Option<GreyReading>], set: u128) -> NormalFactor {
        if let Some((_, found)) = self.cache.borrow().iter().find(|(s, _)| *s == set) {
            return *found;
        }
        let factor = normal_factor(readings, set);
        let mut cache = self.cache.borrow_mut();
        if cache.len() < Self::CAPACITY {
            cache.push((set, factor));
        }
        factor
    }
}

fn normal_factor(readings: &[Option<GreyReading>], set: u128) -> NormalFactor {
    normal_factor_of(indices(set).map(|i| readings[i].map(|r| r.vector)))
}

/// The factor of the light vectors given (`None` among them: no factor).
fn normal_factor_of(vectors: impl Iterator<Item = Option<Vector3<f64>>>) -> NormalFactor {
    let mut ata = Matrix3::zeros();
    for vector in vectors {
        let vector = vector?;
        ata += vector * vector.transpose();
    }
    let conditioning = Conditioning::of(ata)?;
    Some((ata.cholesky()?, conditioning))
}

/// Least-squares `g = albedo * n` from the readings in `set`, with the conditioning of the
/// light matrix; `None` when the normal matrix cannot be inverted.
fn least_squares(
    readings: &[Option<GreyReading>],
    set: u128,
    factors: &NormalFactors,
) -> Option<(Vector3<f64>, Conditioning)> {
    let mut aty = Vector3::zeros();
    for (i, r) in readings.iter().enumerate() {
        if set & (1 << i) == 0 {
            continue;
        }
        let r = r.as_ref()?;
        aty += r.vector * r.grey;
    }
    let (cholesky, condition) = factors.get(readings, set)?;
    let g = cholesky.solve(&aty);
    g.iter().all(|v| v.is_finite()).then_some((g, condition))
}

/// The lights in `set`, ascending. Walks the set bits (not all [`MAX_LIGHTS`] positions: with 4
/// lights that was 128 tests per call, several calls per pixel).
pub(crate) fn indices(set: u128) -> impl Iterator<Item = usize> {
    let mut rest = set;
    std::iter::from_fn(move || {
        (rest != 0).then(|| {
            let i = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            i
        })
    })
}

/// Solves one pixel from its readings (one RGB per light), the lights as seen from the pixel, and
/// the unit direction to the camera.
pub fn solve_pixel(
    readings: &[[f32; 3]],
    lights: &[LightSample],
    view: &Vector3<f64>,
    params: &PsParams,
) -> PixelSolution {
    solve_pixel_with(
        readings,
        lights,
        view,
        params,
        &mut PixelBuffers::default(),
        &NormalFactors::new(false),
    )
}

/// The buffers of one pixel's solve, reused from pixel to pixel.
#[derive(Default)]
struct PixelBuffers {
    grey: Vec<Option<GreyReading>>,
    chroma: ChromaBuffers,
}

/// [`solve_pixel`] with reusable buffers and the normal-matrix factors.
fn solve_pixel_with(
    readings: &[[f32; 3]],
    lights: &[LightSample],
    view: &Vector3<f64>,
    params: &PsParams,
    buffers: &mut PixelBuffers,
    factors: &NormalFactors,
) -> PixelSolution {
    let n = readings.len().min(lights.len()).min(MAX_LIGHTS);
    factors.begin_pixel();
    let PixelBuffers { grey, chroma } = buffers;
    grey_readings_into(&readings[..n], &lights[..n], grey);
    let grey = grey.as_slice();
    let robust = params.method == Method::Robust;
    let mut set: u128 = 0;
    for (i, (r, rgb)) in grey.iter().zip(readings).enumerate() {
        // The baseline keeps saturated readings, as textbook least squares does.
        let saturated = robust && rgb.iter().any(|&v| v as f64 >= params.saturation);
        if r.is_some() && !saturated {
            set |= 1 << i;
        }
    }
    let brightest = indices(set)
        .filter_map(|i| grey[i].map(|r| r.grey))
        .fold(0.0, f64::max);
    if brightest <= params.noise_floor {
        return PixelSolution::flagged(PixelStatus::NoSignal, 0);
    }
    if robust {
        set = drop_shadows(grey, set, params);
        set = drop_chroma_highlights(grey, set, params, chroma);
    }
    if set.count_ones() < 3 {
        return PixelSolution::flagged(PixelStatus::TooFewLights, set);
    }
    let tolerance = params.noise_floor + params.residual_tolerance * brightest;
    let (g, set, condition) = match params.method {
        Method::LeastSquares => match least_squares(grey, set, factors) {
            Some((g, condition)) => (g, set, Some(condition)),
            None => return PixelSolution::flagged(PixelStatus::IllConditioned, set),
        },
        Method::Robust => match robust_fit(grey, set, view, tolerance, factors) {
            Some((g, set)) => (g, set, None),
            None => return PixelSolution::flagged(PixelStatus::IllConditioned, set),
        },
    };
    let solved = Solved {
        g,
        set,
        brightest,
        condition,
    };
    finish(readings, lights, grey, solved, view, params, factors)
}

/// A pixel's solved `g = albedo * n`, the readings it used, its brightest reading and, when the
/// solve already computed it for this `set`, the light matrix's conditioning.
struct Solved {
    g: Vector3<f64>,
    set: u128,
    brightest: f64,
    condition: Option<Conditioning>,
}

fn finish(
    readings: &[[f32; 3]],
    lights: &[LightSample],
    grey: &[Option<GreyReading>],
    Solved {
        g,
        set,
        brightest,
        condition,
    }: Solved,
    view: &Vector3<f64>,
    params: &PsParams,
    factors: &NormalFactors,
) -> PixelSolution {
    // Least squares solved this very set already; the robust fit may have changed it.
    let condition = condition.or_else(|| least_squares(grey, set, factors).map(|(_, c)| c));
    match condition {
        Some(condition) if condition.at_most(params.max_condition) => {}
        _ => return PixelSolution::flagged(PixelStatus::IllConditioned, set),
    }
    let length = g.norm();
    if length.is_nan() || length <= 0.0 {
        return PixelSolution::flagged(PixelStatus::NoSignal, set);
    }
    let normal = g / length;
    if normal.dot(view) <= 0.0 {
        return PixelSolution::flagged(PixelStatus::BackFacing, set);
    }
    let mut albedo = [0.0f32; 3];
    for (c, out) in albedo.iter_mut().enumerate() {
        let (mut num, mut den) = (0.0, 0.0);
        for i in indices(set) {
            let a = lights[i].irradiance[c] * lights[i].direction.dot(&normal).max(0.0);
            num += readings[i][c] as f64 * a;
            den += a * a;
        }
        *out = if den > 0.0 { (num / den) as f32 } else { 0.0 };
    }
    let mut sq = 0.0;
    for i in indices(set) {
        if let Some(r) = &grey[i] {
            sq += (r.grey - r.vector.dot(&g)).powi(2);
        }
    }
    let residual = (sq / set.count_ones() as f64).sqrt() / brightest;
    PixelSolution {
        normal: [normal.x as f32, normal.y as f32, normal.z as f32],
        albedo,
        residual: residual as f32,
        used: set,
        status: PixelStatus::Ok,
    }
}

fn drop_shadows(grey: &[Option<GreyReading>], set: u128, params: &PsParams) -> u128 {
    let max_shading = indices(set)
        .filter_map(|i| grey[i].map(|r| r.shading))
        .fold(0.0, f64::max);
    indices(set)
        .filter(|&i| {
            grey[i].is_some_and(|r| {
                r.grey > params.noise_floor && r.shading >= params.shadow_fraction * max_shading
            })
        })
        .fold(0, |acc, i| acc | (1 << i))
}

/// The buffers of [`drop_chroma_highlights`], kept from pixel to pixel (allocating them for
/// every solve was a visible share of a full-size capture's 3 solves per pixel).
#[derive(Default)]
struct ChromaBuffers {
    chromas: Vec<(usize, Vector3<f64>)>,
    channel: Vec<f64>,
    suspects: Vec<(f64, usize)>,
}

/// Drops readings whose chromaticity moved towards white (a specular reflection of a white-ish
/// light on a coloured surface). Keeps at least 3 readings; does nothing on grey surfaces.
fn drop_chroma_highlights(
    grey: &[Option<GreyReading>],
    set: u128,
    params: &PsParams,
    buffers: &mut ChromaBuffers,
) -> u128 {
    let ChromaBuffers {
        chromas,
        channel,
        suspects,
    } = buffers;
    chromas.clear();
    chromas.extend(indices(set).filter_map(|i| grey[i].map(|r| (i, r.chroma))));
    if chromas.len() < 4 {
        return set;
    }
    let mut median = |c: usize| {
        channel.clear();
        channel.extend(chromas.iter().map(|(_, x)| x[c]));
        channel.sort_by(f64::total_cmp);
        channel[channel.len() / 2]
    };
    let reference = Vector3::new(median(0), median(1), median(2));
    let Some(reference) = reference.try_normalize(1e-12) else {
        return set;
    };
    let white = Vector3::repeat(1.0 / 3f64.sqrt());
    let angle = |a: &Vector3<f64>, b: &Vector3<f64>| a.dot(b).clamp(-1.0, 1.0).acos().to_degrees();
    let tol = params.highlight_chroma_deg;
    let reference_to_white = angle(&reference, &white);
    if reference_to_white < 2.0 * tol {
        return set;
    }
    let mut out = set;
    // Most suspicious first, so at least 3 readings always remain.
    suspects.clear();
    suspects.extend(
        chromas
            .iter()
            .filter(|(_, ch)| {
                angle(ch, &reference) > tol && angle(ch, &white) < reference_to_white - 0.5 * tol
            })
            .map(|(i, ch)| (angle(ch, &reference), *i)),
    );
    suspects.sort_by(|a, b| b.0.total_cmp(&a.0));
    for &(_, i) in suspects.iter() {
        if out.count_ones() > 3 {
            out &= !(1 << i);
        }
    }
    out
}

fn within_tolerance(
    grey: &[Option<GreyReading>],
    set: u128,
    g: &Vector3<f64>,
    tolerance: f64,
) -> bool {
    indices(set).all(|i| {
        grey[i].is_some_and(|r| {
            let predicted = r.vector.dot(g);
            predicted > 0.0 && (r.grey - predicted).abs() <= tolerance
        })
    })
}

/// Least squares, then removal of outliers one at a time until the residuals are within tolerance
/// or only 3 readings remain.
fn robust_fit(
    grey: &[Option<GreyReading>],
    mut set: u128,
    view: &Vector3<f64>,
    tolerance: f64,
    factors: &NormalFactors,
) -> Option<(Vector3<f64>, u128)> {
    let (mut g, _) = least_squares(grey, set, factors)?;
    while set.count_ones() > 3 && !within_tolerance(grey, set, &g, tolerance) {
        let next = if set.count_ones() <= 8 {
            most_plausible_removal(grey, set, view, tolerance, factors)
        } else {
            None
        };
        let next = match next {
            Some(found) => found,
            None => {
                let worst = worst_residual(grey, set, &g)?;
                let smaller = set & !(1 << worst);
                (least_squares(grey, smaller, factors)?.0, smaller)
            }
        };
        g = next.0;
        set = next.1;
    }
    Some((g, set))
}

fn worst_residual(grey: &[Option<GreyReading>], set: u128, g: &Vector3<f64>) -> Option<usize> {
    indices(set)
        .filter_map(|i| grey[i].map(|r| (i, (r.grey - r.vector.dot(g)).abs())))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Tries every leave-one-out subset and returns the most physically plausible one: its own
/// readings fit, and the left-out reading is either much darker than predicted (a cast shadow) or
/// brighter and near the mirror direction of its light (a highlight).
fn most_plausible_removal(
    grey: &[Option<GreyReading>],
    set: u128,
    view: &Vector3<f64>,
    tolerance: f64,
    factors: &NormalFactors,
) -> Option<(Vector3<f64>, u128)> {
    let mut best: Option<(f64, Vector3<f64>, u128)> = None;
    for out in indices(set) {
        let subset = set & !(1 << out);
        let Some((g, _)) = least_squares(grey, subset, factors) else {
            continue;
        };
        let Some(left_out) = grey[out] else {
            continue;
        };
        if !within_tolerance(grey, subset, &g, tolerance) {
            continue;
        }
        let predicted = left_out.vector.dot(&g);
        let Some(normal) = g.try_normalize(1e-12) else {
            continue;
        };
        let plausibility = if left_out.grey < predicted {
            // Cast shadow: 1 when the reading is black, 0 when it matches the prediction.
            1.0 - left_out.grey / predicted
        } else if excess_is_surface_coloured(grey, subset, &left_out, predicted) {
            // A diffuse-coloured excess is not a highlight (a specular reflection has the light's
            // colour): this subset explains the data only by blaming the wrong reading.
            0.0
        } else {
            // Highlight: cosine between the normal and the half vector of the left-out light.
            let light = left_out.vector.normalize();
            match (light + view).try_normalize(1e-12) {
                Some(half) => normal.dot(&half),
                None => 0.0,
            }
        };
        if best.as_ref().is_none_or(|(p, _, _)| plausibility > *p) {
            best = Some((plausibility, g, subset));
        }
    }
    best.map(|(_, g, subset)| (g, subset))
}

/// Whether the excess of a bright left-out reading over its prediction has the surface's colour
/// rather than white; `false` on grey surfaces, where colour cannot tell.
fn excess_is_surface_coloured(
    grey: &[Option<GreyReading>],
    subset: u128,
    left_out: &GreyReading,
    predicted: f64,
) -> bool {
    let total: Vector3<f64> = indices(subset)
        .filter_map(|i| grey[i].map(|r| r.colour_free))
        .sum();
    let Some(surface) = total.try_normalize(1e-12) else {
        return false;
    };
    let white = Vector3::repeat(1.0 / 3f64.sqrt());
    let angle = |a: &Vector3<f64>, b: &Vector3<f64>| a.dot(b).clamp(-1.0, 1.0).acos();
    if angle(&surface, &white) < 5f64.to_radians() {
        return false;
    }
    // Diffuse prediction of the left-out reading, with the surface's colour (grey = mean of RGB).
    let diffuse = surface * (3.0 * predicted / surface.sum());
    match (left_out.colour_free - diffuse).try_normalize(1e-12) {
        Some(excess) => angle(&excess, &surface) < angle(&excess, &white),
        None => false,
    }
}

/// The lights as seen from one pixel, and the direction to the camera.
pub trait LightModel: Sync {
    /// Number of lights.
    fn count(&self) -> usize;
    /// Fills `out` (length [`LightModel::count`]) with the lights at pixel `(x, y)`; returns the
    /// unit direction to the camera, or `None` when the pixel has no geometry.
    fn at(&self, x: u32, y: u32, out: &mut [LightSample]) -> Option<Vector3<f64>>;
    /// Whether every pixel sees the same lights and camera direction (distant lights), `at`
    /// never returning `None`: lets the solver read them once and factor each light set's
    /// normal matrix once instead of per pixel.
    fn uniform(&self) -> bool {
        false
    }
}

/// Distant lights: the same direction and irradiance at every pixel, camera along `view`.
#[derive(Debug, Clone)]
pub struct DirectionalLights {
    pub lights: Vec<LightSample>,
    pub view: Vector3<f64>,
}

impl LightModel for DirectionalLights {
    fn count(&self) -> usize {
        self.lights.len()
    }

    fn at(&self, _x: u32, _y: u32, out: &mut [LightSample]) -> Option<Vector3<f64>> {
        out.copy_from_slice(&self.lights);
        Some(self.view)
    }

    fn uniform(&self) -> bool {
        true
    }
}

/// Per-pixel results of photometric stereo over an image.
#[derive(Debug, Clone)]
pub struct NormalMap {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<PixelSolution>,
}

/// Counts of a normal map's outcomes.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct NormalMapStats {
    /// Pixels attempted (in the mask).
    pub pixels: u64,
    /// Pixels solved.
    pub solved: u64,
    pub too_few_lights: u64,
    pub ill_conditioned: u64,
    pub no_signal: u64,
    pub back_facing: u64,
    /// Mean number of lights used over the solved pixels.
    pub lights_used_mean: f64,
}

impl NormalMapStats {
    /// The report fields shared by `mlsss normals --json` and the pipeline's normals stage.
    pub fn report_json(&self) -> serde_json::Value {
        serde_json::json!({
            "pixels": self.pixels,
            "solved": self.solved,
            "lights_used_mean": self.lights_used_mean,
            "flagged": {
                "too_few_lights": self.too_few_lights,
                "ill_conditioned": self.ill_conditioned,
                "no_signal": self.no_signal,
                "back_facing": self.back_facing,
            },
        })
    }
}

impl NormalMap {
    /// Outcome counts.
    pub fn stats(&self) -> NormalMapStats {
        let mut s = NormalMapStats::default();
        let mut used = 0u64;
        for p in &self.pixels {
            match p.status {
                PixelStatus::Masked => continue,
                PixelStatus::Ok => {
                    s.solved += 1;
                    used += p.lights_used() as u64;
                }
                PixelStatus::TooFewLights => s.too_few_lights += 1,
                PixelStatus::IllConditioned => s.ill_conditioned += 1,
                PixelStatus::NoSignal => s.no_signal += 1,
                PixelStatus::BackFacing => s.back_facing += 1,
            }
            s.pixels += 1;
        }
        s.lights_used_mean = if s.solved > 0 {
            used as f64 / s.solved as f64
        } else {
            0.0
        };
        s
    }

    /// Normals as an RGB float image (zero where flagged).
    pub fn normal_image(&self) -> image::Rgb32FImage {
        self.image_of(|p| p.normal)
    }

    /// Albedo as an RGB float image (zero where flagged).
    pub fn albedo_image(&self) -> image::Rgb32FImage {
        self.image_of(|p| p.albedo)
    }

    /// In parallel into a buffer on huge pages (a serial `flat_map` collect, which cannot know
    /// its length, took longer than the 4-light solve itself).
    fn image_of(&self, f: impl Fn(&PixelSolution) -> [f32; 3] + Sync) -> image::Rgb32FImage {
        use rayon::prelude::*;
        let mut data = mlsss_core::resources::zeros_on_huge_pages(self.pixels.len() * 3);
        data.par_chunks_mut(3 * 4096)
            .zip(self.pixels.par_chunks(4096))
            .for_each(|(out, pixels)| {
                for (rgb, p) in out.chunks_exact_mut(3).zip(pixels) {
                    rgb.copy_from_slice(&f(p));
                }
            });
        image::Rgb32FImage::from_raw(self.width, self.height, data)
            .unwrap_or_else(|| image::Rgb32FImage::new(self.width, self.height))
    }
}

/// Solves every masked pixel of an image set (`images[i]` lit by light `i`).
pub fn solve_images(
    images: &[&image::Rgb32FImage],
    lights: &dyn LightModel,
    mask: Option<&[bool]>,
    params: &PsParams,
) -> Result<NormalMap, PhotometricStereoError> {
    use rayon::prelude::*;
    if params.method == Method::LeastSquares && lights.uniform() {
        let (width, height) = check_inputs(images, lights, mask)?;
        let count = images.len();
        let n = width as usize * height as usize;
        let raws: Vec<&[f32]> = images.iter().map(|im| im.as_raw().as_slice()).collect();
        let mut samples = vec![
            LightSample {
                direction: Vector3::z(),
                irradiance: [0.0; 3],
            };
            count
        ];
        let view = lights.at(0, 0, &mut samples);
        let solver = view.and_then(|view| {
            distant_least_squares::DistantLeastSquares::new(&samples, view, params)
        });
        if let Some(solver) = solver {
            // 48 bytes a pixel, 68 MB at full size: on huge pages, written in place, a block of
            // pixels at a time (the last, partial block pixel by pixel).
            use distant_least_squares::BLOCK;
            let full = n / BLOCK;
            let mut blocks = mlsss_core::resources::vec_on_huge_pages(n.div_ceil(BLOCK));
            blocks.par_extend(
                (0..full)
                    .into_par_iter()
                    .with_min_len(512)
                    .map(|b| solver.solve_block(&raws, mask, b * BLOCK)),
            );
            let mut pixels: Vec<PixelSolution> = blocks.into_flattened();
            pixels.extend((full * BLOCK..n).map(|p| {
                if mask.is_some_and(|m| !m[p]) {
                    return PixelSolution::flagged(PixelStatus::Masked, 0);
                }
                solver.solve(|i| {
                    let raw: &[f32] = raws[i];
                    [raw[p * 3], raw[p * 3 + 1], raw[p * 3 + 2]]
                })
            }));
            return Ok(NormalMap {
                width,
                height,
                pixels,
            });
        }
    }
    // Checks the inputs as the distant least squares above does.
    solve_each_pixel(images, lights, mask, |pixel, solver| {
        solver.solve(pixel, params)
    })
}

/// The sizes of `images` (all alike), checked against the lights and the mask.
fn check_inputs(
    images: &[&image::Rgb32FImage],
    lights: &dyn LightModel,
    mask: Option<&[bool]>,
) -> Result<(u32, u32), PhotometricStereoError> {
    let count = images.len();
    if count > MAX_LIGHTS {
        return Err(PhotometricStereoError::TooManyLights(count));
    }
    if count < 3 {
        return Err(PhotometricStereoError::TooFewLights(count));
    }
    if lights.count() != count {
        return Err(PhotometricStereoError::Mismatch(format!(
            "{count} images but {} lights",
            lights.count()
        )));
    }
    let (width, height) = images[0].dimensions();
    if let Some(i) = images
        .iter()
        .position(|im| im.dimensions() != (width, height))
    {
        return Err(PhotometricStereoError::Mismatch(format!(
            "image {i} is {:?}, image 0 is {:?}",
            images[i].dimensions(),
            (width, height)
        )));
    }
    let n = width as usize * height as usize;
    if mask.is_some_and(|m| m.len() != n) {
        return Err(PhotometricStereoError::Mismatch(format!(
            "mask has {} pixels, images have {n}",
            mask.map_or(0, |m| m.len())
        )));
    }
    Ok((width, height))
}

/// What a pixel's solve reads: one RGB reading per light, the lights as the light model gives
/// them at the pixel, and the unit direction to the camera.
pub(crate) struct PixelInput<'a> {
    pub readings: &'a [[f32; 3]],
    pub lights: &'a [LightSample],
    pub view: Vector3<f64>,
}

/// One thread's buffers for [`solve_pixel_with`], reused from pixel to pixel.
pub(crate) struct PixelSolver {
    buffers: PixelBuffers,
    /// Factors of the light model's own lights (shared by every pixel when they are uniform).
    model_factors: NormalFactors,
    /// Factors of lights a pixel's solve changed itself (never shared between pixels).
    own_factors: NormalFactors,
    /// The lights of [`PixelSolver::solve_scaled`].
    scaled: Vec<LightSample>,
}

impl PixelSolver {
    fn new(uniform: bool, count: usize) -> Self {
        Self {
            buffers: PixelBuffers {
                grey: Vec::with_capacity(count),
                chroma: ChromaBuffers::default(),
            },
            model_factors: NormalFactors::new(uniform),
            own_factors: NormalFactors::new(false),
            scaled: Vec::with_capacity(count),
        }
    }

    /// [`solve_pixel`] of the light model's own lights at the pixel.
    pub(crate) fn solve(&mut self, pixel: &PixelInput, params: &PsParams) -> PixelSolution {
        solve_pixel_with(
            pixel.readings,
            pixel.lights,
            &pixel.view,
            params,
            &mut self.buffers,
            &self.model_factors,
        )
    }

    /// [`solve_pixel`] of the pixel's lights with each irradiance scaled by `factor(light)`.
    pub(crate) fn solve_scaled(
        &mut self,
        pixel: &PixelInput,
        params: &PsParams,
        factor: impl Fn(&LightSample) -> f64,
    ) -> PixelSolution {
        self.scaled.clear();
        self.scaled.extend(pixel.lights.iter().map(|light| {
            let factor = factor(light);
            LightSample {
                direction: light.direction,
                irradiance: light.irradiance.map(|e| e * factor),
            }
        }));
        solve_pixel_with(
            pixel.readings,
            &self.scaled,
            &pixel.view,
            params,
            &mut self.buffers,
            &self.own_factors,
        )
    }
}

/// Runs `solve` on every masked pixel of `images` that the light model sees (the others are
/// [`PixelStatus::Masked`]), in parallel; the inputs are checked as [`solve_images`] checks them.
/// A solver that needs several passes over a pixel makes them all here, while the pixel's
/// readings and lights are at hand (one pass over the images instead of one per iteration).
pub(crate) fn solve_each_pixel(
    images: &[&image::Rgb32FImage],
    lights: &dyn LightModel,
    mask: Option<&[bool]>,
    solve: impl Fn(&PixelInput, &mut PixelSolver) -> PixelSolution + Sync + Send,
) -> Result<NormalMap, PhotometricStereoError> {
    use rayon::prelude::*;
    let (width, height) = check_inputs(images, lights, mask)?;
    let count = images.len();
    let raws: Vec<&[f32]> = images.iter().map(|im| im.as_raw().as_slice()).collect();
    let pixels: Vec<PixelSolution> = (0..width as usize * height as usize)
        .into_par_iter()
        .map_init(
            || {
                let placeholder = LightSample {
                    direction: Vector3::z(),
                    irradiance: [0.0; 3],
                };
                (
                    vec![placeholder; count],
                    vec![[0f32; 3]; count],
                    PixelSolver::new(lights.uniform(), count),
                )
            },
            |(samples, readings, solver), p| {
                if mask.is_some_and(|m| !m[p]) {
                    return PixelSolution::flagged(PixelStatus::Masked, 0);
                }
                let (x, y) = ((p % width as usize) as u32, (p / width as usize) as u32);
                let Some(view) = lights.at(x, y, samples) else {
                    return PixelSolution::flagged(PixelStatus::Masked, 0);
                };
                for (reading, raw) in readings.iter_mut().zip(&raws) {
                    reading.copy_from_slice(&raw[p * 3..p * 3 + 3]);
                }
                let pixel = PixelInput {
                    readings,
                    lights: samples,
                    view,
                };
                solve(&pixel, solver)
            },
        )
        .collect();
    Ok(NormalMap {
        width,
        height,
        pixels,
    })
}

/// Angle in degrees between two normals (0 when either is zero: callers skip those).
pub fn angular_error_deg(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    let va = Vector3::new(a[0] as f64, a[1] as f64, a[2] as f64);
    let vb = Vector3::new(b[0] as f64, b[1] as f64, b[2] as f64);
    match (va.try_normalize(1e-12), vb.try_normalize(1e-12)) {
        (Some(x), Some(y)) => x.dot(&y).clamp(-1.0, 1.0).acos().to_degrees(),
        _ => 0.0,
    }
}

/// Mean, median and 95th percentile of angular errors (degrees) between `estimate` and `truth`
/// over pixels where both are non-zero (and `mask` is set).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct AngularErrors {
    pub pixels: u64,
    pub mean_deg: f64,
    pub median_deg: f64,
    pub p95_deg: f64,
}

/// Angular error statistics; `None` when no pixel can be compared.
pub fn angular_errors(
    estimate: &image::Rgb32FImage,
    truth: &image::Rgb32FImage,
    mask: Option<&[bool]>,
) -> Option<AngularErrors> {
    let is_set = |v: &[f32; 3]| v.iter().any(|c| *c != 0.0) && v.iter().all(|c| c.is_finite());
    let mut errors: Vec<f64> = estimate
        .pixels()
        .zip(truth.pixels())
        .enumerate()
        .filter(|(i, (e, t))| mask.is_none_or(|m| m[*i]) && is_set(&e.0) && is_set(&t.0))
        .map(|(_, (e, t))| angular_error_deg(&e.0, &t.0))
        .collect();
    if errors.is_empty() {
        return None;
    }
    errors.sort_by(f64::total_cmp);
    let pick = |q: f64| errors[((errors.len() - 1) as f64 * q).round() as usize];
    Some(AngularErrors {
        pixels: errors.len() as u64,
        mean_deg: errors.iter().sum::<f64>() / errors.len() as f64,
        median_deg: pick(0.5),
        p95_deg: pick(0.95),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four lights like the booth's projectors: up-left, up-right, down-left, down-right, about
    /// 35 degrees off the view axis.
    fn booth_lights() -> Vec<LightSample> {
        [(-1.0, 1.0), (1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)]
            .iter()
            .map(|&(x, y)| LightSample {
                direction: Vector3::new(0.45 * x, 0.45 * y, 0.77).normalize(),
                irradiance: [1.0, 0.9, 1.1],
            })
            .collect()
    }

    fn render(normal: &Vector3<f64>, albedo: [f64; 3], lights: &[LightSample]) -> Vec<[f32; 3]> {
        lights
            .iter()
            .map(|l| {
                let c = normal.dot(&l.direction).max(0.0);
                [0, 1, 2].map(|k| (albedo[k] * l.irradiance[k] * c) as f32)
            })
            .collect()
    }

    fn angle(sol: &PixelSolution, truth: &Vector3<f64>) -> f64 {
        let t = [truth.x as f32, truth.y as f32, truth.z as f32];
        angular_error_deg(&sol.normal, &t)
    }

    const VIEW: Vector3<f64> = Vector3::new(0.0, 0.0, 1.0);

    fn robust() -> PsParams {
        PsParams::default()
    }

    fn least_squares() -> PsParams {
        PsParams {
            method: Method::LeastSquares,
            ..PsParams::default()
        }
    }

    /// The parallel image fill puts each pixel's normal and albedo at its place, across the
    /// fill's chunk boundaries.
    #[test]
    fn normal_and_albedo_images_hold_each_pixels_values() {
        let (width, height) = (97u32, 61u32);
        let pixels: Vec<PixelSolution> = (0..width * height)
            .map(|i| PixelSolution {
                normal: [i as f32, 0.5, -(i as f32)],
                albedo: [0.25, i as f32 * 2.0, 1.0],
                residual: 0.0,
                used: 7,
                status: PixelStatus::Ok,
            })
            .collect();
        let map = NormalMap {
            width,
            height,
            pixels,
        };
        let (normals, albedo) = (map.normal_image(), map.albedo_image());
        for (i, p) in map.pixels.iter().enumerate() {
            let (x, y) = (i as u32 % width, i as u32 / width);
            assert_eq!(normals.get_pixel(x, y).0, p.normal);
            assert_eq!(albedo.get_pixel(x, y).0, p.albedo);
        }
    }

    #[test]
    fn four_clean_lights_recover_normal_and_rgb_albedo() {
        let lights = booth_lights();
        let normal = Vector3::new(0.2, -0.1, 0.97).normalize();
        let readings = render(&normal, [0.6, 0.4, 0.3], &lights);
        for params in [robust(), least_squares()] {
            let sol = solve_pixel(&readings, &lights, &VIEW, &params);
            assert_eq!(sol.status, PixelStatus::Ok);
            assert!(angle(&sol, &normal) < 1e-3);
            for (a, t) in sol.albedo.iter().zip([0.6, 0.4, 0.3]) {
                assert!((*a as f64 - t).abs() < 1e-5, "{:?}", sol.albedo);
            }
            assert_eq!(sol.lights_used(), 4);
        }
    }

    #[test]
    fn cast_shadow_is_detected_and_solved_with_the_other_three() {
        let lights = booth_lights();
        let normal = Vector3::new(-0.3, 0.25, 0.92).normalize();
        for shadowed in 0..4 {
            // Skin-coloured: with a grey surface and 4 symmetric lights, a partial shadow at one
            // light and a highlight at a neighbouring one explain the readings equally well.
            let mut readings = render(&normal, [0.7, 0.45, 0.35], &lights);
            // A partial cast shadow (penumbra): 30% of the light remains, above the shadow
            // threshold, so only the residual test can find it.
            readings[shadowed] = readings[shadowed].map(|v| v * 0.3);
            let sol = solve_pixel(&readings, &lights, &VIEW, &robust());
            assert_eq!(sol.status, PixelStatus::Ok);
            assert_eq!(sol.used, 0b1111 & !(1 << shadowed), "shadow at {shadowed}");
            assert!(angle(&sol, &normal) < 1e-3);
            let ls = solve_pixel(&readings, &lights, &VIEW, &least_squares());
            assert!(angle(&ls, &normal) > 5.0);
        }
    }

    #[test]
    fn highlight_is_detected_by_the_mirror_direction() {
        let lights = booth_lights();
        for k in 0..4 {
            // A normal halfway between the view and light k: light k's mirror direction.
            let normal = (lights[k].direction + VIEW).normalize();
            let mut readings = render(&normal, [0.4; 3], &lights);
            readings[k] = readings[k].map(|v| v + 0.3);
            let sol = solve_pixel(&readings, &lights, &VIEW, &robust());
            assert_eq!(sol.used, 0b1111 & !(1 << k), "highlight at {k}");
            assert!(angle(&sol, &normal) < 1e-3);
        }
    }

    #[test]
    fn highlight_on_coloured_skin_is_detected_by_chromaticity() {
        let mut lights = booth_lights();
        lights.push(LightSample {
            direction: Vector3::new(0.0, 0.3, 0.95).normalize(),
            irradiance: [1.0; 3],
        });
        let normal = Vector3::new(0.1, 0.1, 0.99).normalize();
        let mut readings = render(&normal, [0.7, 0.45, 0.35], &lights);
        // A white specular spike at light 4, just above the residual tolerance.
        readings[4] = readings[4].map(|v| v + 0.06);
        let sol = solve_pixel(&readings, &lights, &VIEW, &robust());
        assert_eq!(sol.used, 0b01111);
        assert!(angle(&sol, &normal) < 1e-3);
    }

    #[test]
    fn attached_shadow_and_grazing_light_are_dropped() {
        let lights = booth_lights();
        // Tilted so light 3 (down-right) grazes at about 88 degrees and light 2 is behind.
        let normal = Vector3::new(-0.55, 0.6, 0.58).normalize();
        let readings = render(&normal, [0.5; 3], &lights);
        let sol = solve_pixel(&readings, &lights, &VIEW, &robust());
        assert!(sol.lights_used() <= 3);
        if sol.status == PixelStatus::Ok {
            assert!(angle(&sol, &normal) < 0.5);
        } else {
            assert_eq!(sol.status, PixelStatus::TooFewLights);
            assert_eq!(sol.normal, [0.0; 3]);
        }
    }

    #[test]
    fn fewer_than_three_lights_is_flagged_not_guessed() {
        let lights = booth_lights();
        let normal = Vector3::new(0.0, 0.0, 1.0);
        let mut readings = render(&normal, [0.5; 3], &lights);
        readings[0] = [0.0; 3];
        readings[1] = [1.0; 3]; // saturated
        let sol = solve_pixel(&readings, &lights, &VIEW, &robust());
        assert_eq!(sol.status, PixelStatus::TooFewLights);
        assert_eq!((sol.normal, sol.albedo), ([0.0; 3], [0.0; 3]));
    }

    /// The bound's verdicts against the eigenvalues' on light matrices from well conditioned to
    /// singular, at limits on both sides of and right at the exact condition number.
    #[test]
    fn bounded_conditioning_decides_as_the_eigenvalues_do() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(19);
        let mut decided_by_bound = 0;
        for trial in 0..20_000 {
            let count = 3 + trial % 3;
            // Flatness from none to coplanar: the lights' z spread shrinks towards 0.
            let flatness = [1.0, 1e-2, 1e-5, 1e-9, 0.0][trial % 5];
            let scale = 10f64.powf(rng.gen_range(-3.0..3.0));
            let mut a = Matrix3::zeros();
            for _ in 0..count {
                let v = Vector3::new(
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                    0.5 + flatness * rng.gen_range(-1.0..1.0),
                ) * scale;
                a += v * v.transpose();
            }
            let exact = exact_condition(&a);
            let bounded = Conditioning::of(a);
            assert_eq!(bounded.is_some(), exact.is_some(), "{a}");
            let (Some(bounded), Some(exact)) = (bounded, exact) else {
                continue;
            };
            for limit in [
                30.0,
                exact,
                exact * (1.0 - 1e-12),
                exact * 1.02,
                exact * 0.98,
            ] {
                if bounded.squared_bound.sqrt() <= Conditioning::MARGIN * limit {
                    decided_by_bound += 1;
                }
                assert_eq!(bounded.at_most(limit), exact <= limit, "{a} at {limit}");
            }
        }
        // The bound must decide often, or the test checks only the exact path.
        assert!(decided_by_bound > 10_000, "{decided_by_bound}");
    }

    #[test]
    fn near_coplanar_lights_are_flagged_ill_conditioned() {
        // Four lights within 0.5 degree of one plane (x z).
        let lights: Vec<LightSample> = [-40.0f64, -10.0, 15.0, 45.0]
            .iter()
            .enumerate()
            .map(|(i, a)| LightSample {
                direction: Vector3::new(
                    a.to_radians().sin(),
                    0.005 * (i as f64 - 1.5),
                    a.to_radians().cos(),
                )
                .normalize(),
                irradiance: [1.0; 3],
            })
            .collect();
        let normal = Vector3::new(0.1, 0.2, 0.97).normalize();
        let readings = render(&normal, [0.5; 3], &lights);
        for params in [robust(), least_squares()] {
            let sol = solve_pixel(&readings, &lights, &VIEW, &params);
            assert_eq!(sol.status, PixelStatus::IllConditioned);
            assert_eq!(sol.normal, [0.0; 3]);
        }
    }

    #[test]
    fn zero_nan_inf_and_huge_dynamic_range_never_produce_non_finite_output() {
        let lights = booth_lights();
        let cases: Vec<Vec<[f32; 3]>> = vec![
            vec![[0.0; 3]; 4],
            vec![[f32::NAN; 3], [0.3; 3], [0.3; 3], [0.3; 3]],
            vec![[f32::INFINITY; 3], [0.2; 3], [0.3; 3], [0.25; 3]],
            vec![[1e-30; 3], [1e-20; 3], [3e-30; 3], [1e-25; 3]],
            vec![[3e38; 3], [1e38; 3], [2e38; 3], [1e38; 3]],
            vec![[-0.5; 3], [0.2; 3], [0.3; 3], [0.25; 3]],
        ];
        let huge = PsParams {
            saturation: f64::INFINITY,
            ..PsParams::default()
        };
        for readings in cases {
            for params in [robust(), least_squares(), huge] {
                let sol = solve_pixel(&readings, &lights, &VIEW, &params);
                assert!(
                    sol.normal.iter().chain(&sol.albedo).all(|v| v.is_finite())
                        && sol.residual.is_finite(),
                    "{readings:?} -> {sol:?}"
                );
                if sol.status == PixelStatus::Ok {
                    let len: f32 = sol.normal.iter().map(|v| v * v).sum();
                    assert!((len - 1.0).abs() < 1e-4);
                }
            }
        }
        // All-zero readings carry no signal.
        let sol = solve_pixel(&[[0.0; 3]; 4], &lights, &VIEW, &robust());
        assert_eq!(sol.status, PixelStatus::NoSignal);
    }

    /// The distant lights a `ps_scene` was rendered under.
    fn scene_lights(scene: &super::super::ps_scene::Scene) -> DirectionalLights {
        DirectionalLights {
            lights: scene
                .directions
                .iter()
                .zip(&scene.intensities)
                .map(|(d, i)| LightSample {
                    direction: *d,
                    irradiance: *i,
                })
                .collect(),
            view: VIEW,
        }
    }

    #[test]
    fn robust_beats_least_squares_clearly_on_a_scene_with_shadows_and_highlights() {
        let scene = super::super::ps_scene::render(&super::super::ps_scene::SceneParams {
            width: 64,
            height: 64,
            lights: 8,
            ..Default::default()
        });
        let lights = scene_lights(&scene);
        let refs: Vec<_> = scene.images.iter().collect();
        let errors = |params: &PsParams| {
            let map = solve_images(&refs, &lights, Some(&scene.mask), params).unwrap();
            angular_errors(&map.normal_image(), &scene.normals, Some(&scene.mask)).unwrap()
        };
        let (r, l) = (errors(&robust()), errors(&least_squares()));
        assert!(r.mean_deg < 2.0 && r.median_deg < 0.6, "robust {r:?}");
        assert!(
            l.mean_deg > 3.0 * r.mean_deg,
            "least squares {l:?} vs robust {r:?}"
        );
        assert!(r.pixels as f64 > 0.95 * scene.mask.iter().filter(|m| **m).count() as f64);
    }

    #[test]
    fn factors_shared_across_pixels_give_the_per_pixel_solutions_exactly() {
        // Distant lights let `solve_images` factor each light set once per thread; a pixel
        // solved on its own (`solve_pixel`, factoring per pixel) must come out bit for bit the
        // same, through shadows, highlights and leave-one-out subsets. (Least squares under
        // distant lights has its own f32 path, checked against `solve_pixel` in its module.)
        let scene = super::super::ps_scene::render(&super::super::ps_scene::SceneParams {
            width: 48,
            height: 40,
            lights: 6,
            seed: 5,
            ..Default::default()
        });
        let lights = scene_lights(&scene);
        assert!(lights.uniform());
        let refs: Vec<_> = scene.images.iter().collect();
        for params in [robust()] {
            let map = solve_images(&refs, &lights, Some(&scene.mask), &params).unwrap();
            let mut solved = 0;
            for (p, pixel) in map.pixels.iter().enumerate() {
                if !scene.mask[p] {
                    continue;
                }
                let readings: Vec<[f32; 3]> = refs
                    .iter()
                    .map(|im| {
                        let raw = im.as_raw();
                        [raw[p * 3], raw[p * 3 + 1], raw[p * 3 + 2]]
                    })
                    .collect();
                let alone = solve_pixel(&readings, &lights.lights, &VIEW, &params);
                assert_eq!(*pixel, alone, "pixel {p}");
                solved += usize::from(alone.status == PixelStatus::Ok);
            }
            assert!(solved > 500, "{solved} pixels solved");
        }
    }
}

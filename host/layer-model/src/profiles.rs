//! Slit radiance profiles (DESIGN stage 6): for each camera pixel, the global radiance under each
//! slit frame of the sweep against the signed distance (mm, on the surface) from the pixel to the
//! centre of the nearest lit slit, along x (vertical slits) and along y (horizontal slits).
//!
//! Conventions
//! - As [`super::surface`]; projector coordinates `(u, v)` in projector pixels, centres at integers
//!   (as `capture::patterns`), so a slit lighting columns `o .. o + w - 1` is centred at
//!   `o + (w - 1) / 2`.
//! - The profile axis on the surface is the surface gradient of the projector coordinate (`u` for
//!   vertical slits, `v` for horizontal ones): `s = (u - u_slit) / |grad_s u|`, `s_hat` along
//!   `grad_s u`. Slit width and period convert to mm the same way.
//! - Irradiance of a projector at a point, in the model's units: `cos(theta_i) (r_ref / r)^2` with
//!   `r_ref` = 1000 mm (a projector lighting a point head-on from 1 m gives 1); projectors are
//!   assumed equally bright after photometric calibration.
//!
//! Profiles are built on demand per pixel (a full-size capture would need gigabytes to hold them
//! all); the per-pixel geometry is computed once.

use nalgebra::{Matrix2, Vector2, Vector3};
use rayon::prelude::*;

use super::inline_floor;
use super::mixture::{Profile, Sample};
use super::surface::{Footprint, Surface, ViewRay, shift_per_depth};
use mlsss_core::capture::{Axis, FrameNoise, Pattern};

/// Reference distance of the irradiance unit (mm).
pub const IRRADIANCE_REFERENCE_MM: f64 = 1000.0;

/// Errors building profiles.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum ProfileError {
    /// A frame handed to the profile builder is not a slit pattern.
    #[error("frame {index} is a {label} pattern, not a slit")]
    NotASlit { index: usize, label: String },
    /// A frame or coordinate map does not have the surface's size.
    #[error("{what} has {got} pixels; the surface has {want}")]
    SizeMismatch {
        what: &'static str,
        got: usize,
        want: usize,
    },
}

/// How a projector's irradiance falls off around it.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Falloff {
    /// Isotropic point source: `cos(theta_i) (r_ref / r)^2`, `r_ref` =
    /// [`IRRADIANCE_REFERENCE_MM`].
    #[default]
    Isotropic,
    /// A projector's flat pixel grid (as the normals stage and the virtual booth): intensity
    /// `scale / cos^3(alpha)` at angle `alpha` off the optical `axis` (unit, pointing out of the
    /// lens), so `cos(theta_i) scale / (r^2 cos^3(alpha))`. `scale` = the squared distance to the
    /// subject's nominal centre makes every projector give 1 there: they are assumed equally
    /// bright after photometric calibration.
    Projector { axis: [f64; 3], scale: f64 },
}

/// How one projector illuminates the camera's pixels, as the profile stage sees it: where it is,
/// how its light falls off, and which projector pixel lights each camera pixel.
#[derive(Debug, Clone, Copy)]
pub struct ProjectorIllumination<'a> {
    /// Optical centre (world, mm).
    pub centre: Vector3<f64>,
    pub falloff: Falloff,
    /// Projector coordinates of each camera pixel's surface point; `None` where unlit/undecoded.
    pub coords: &'a [Option<(f32, f32)>],
}

/// One slit frame's global component (RGB per pixel).
#[derive(Debug, Clone, Copy)]
pub struct SlitFrame<'a> {
    pub pattern: Pattern,
    pub global: &'a [[f32; 3]],
}

/// Irradiance (model units) of a light at `centre` on a surface point; 0 when the point faces
/// away or lies behind the projector.
pub fn irradiance(
    point: &Vector3<f64>,
    normal: &Vector3<f64>,
    centre: &Vector3<f64>,
    falloff: &Falloff,
) -> f64 {
    let to_light = centre - point;
    let r2 = to_light.norm_squared();
    if r2 <= 0.0 {
        return 0.0;
    }
    let dir = to_light / r2.sqrt();
    let cos = dir.dot(normal);
    if cos <= 0.0 {
        return 0.0;
    }
    match *falloff {
        Falloff::Isotropic => cos * IRRADIANCE_REFERENCE_MM * IRRADIANCE_REFERENCE_MM / r2,
        Falloff::Projector { axis, scale } => {
            let cos_axis = -dir.dot(&Vector3::from(axis));
            if cos_axis <= 1e-6 {
                0.0
            } else {
                cos * scale / (r2 * cos_axis.powi(3))
            }
        }
    }
}

/// Geometry of one pixel for one projector and axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisGeometry {
    /// Projector pixels per mm along the profile axis on the surface (`|grad_s u|`).
    pub px_per_mm: f64,
    /// `(t_i + t_o) . s_hat`.
    pub shift_per_depth: f64,
}

/// Geometry of one pixel for one projector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelGeometry {
    pub coords: (f64, f64),
    pub irradiance: f64,
    /// Index 0: profile along x (vertical slits, coordinate u); 1: along y (v).
    pub axes: [AxisGeometry; 2],
    /// `t_i + t_o` (3-D, tangent to the surface).
    pub shift: Vector3<f64>,
}

fn coord_at(
    view: &ProjectorIllumination,
    surface: &Surface,
    x: i64,
    y: i64,
) -> Option<Vector2<f64>> {
    if x < 0 || y < 0 || x as usize >= surface.width || y as usize >= surface.height {
        return None;
    }
    let i = y as usize * surface.width + x as usize;
    if !surface.mask[i] {
        return None;
    }
    view.coords[i].map(|(u, v)| Vector2::new(f64::from(u), f64::from(v)))
}

/// `d(u, v)/d(x, y)` at pixel `i` by central (or one-sided) differences.
fn coord_jacobian(
    view: &ProjectorIllumination,
    surface: &Surface,
    i: usize,
) -> Option<Matrix2<f64>> {
    let (x, y) = ((i % surface.width) as i64, (i / surface.width) as i64);
    let here = coord_at(view, surface, x, y)?;
    let diff = |dx: i64, dy: i64| -> Option<Vector2<f64>> {
        match (
            coord_at(view, surface, x - dx, y - dy),
            coord_at(view, surface, x + dx, y + dy),
        ) {
            (Some(a), Some(b)) => Some((b - a) * 0.5),
            (None, Some(b)) => Some(b - here),
            (Some(a), None) => Some(here - a),
            (None, None) => None,
        }
    };
    let gx = diff(1, 0)?;
    let gy = diff(0, 1)?;
    // Columns: derivative along x, along y; rows: u, v.
    Some(Matrix2::new(gx.x, gy.x, gx.y, gy.y))
}

/// Surface gradient of a scalar with image partials `g` on footprint `fp`: `J G^-1 g`.
fn surface_gradient(fp: &Footprint, g: Vector2<f64>) -> Option<Vector3<f64>> {
    let gram = Matrix2::new(
        fp.dx.dot(&fp.dx),
        fp.dx.dot(&fp.dy),
        fp.dy.dot(&fp.dx),
        fp.dy.dot(&fp.dy),
    );
    let a = gram.try_inverse()? * g;
    Some(fp.dx * a.x + fp.dy * a.y)
}

/// One projector's [`PixelGeometry`] per camera pixel, stored only where there is one.
///
/// Why not `Vec<Option<PixelGeometry>>`: that takes 88 bytes for every pixel, lit or not
/// (125 MB per projector at full size, where fewer than half the pixels are lit and three or four
/// projectors' maps are held together at the fit's peaks); here an unlit pixel takes the 4 bytes
/// of its slot.
///
/// The lit pixels' geometry is kept in runs of `GeometryMap::CHUNK` pixels, each filled by
/// one task of [`GeometryMap::from_fn`], not gathered into one vector. Why: the gathering was a
/// serial copy into 47 MB of fresh pages after the parallel computation, 0.01-0.13 s a map with
/// one core idle (full size: 4 maps in the profiles stage, 0.33 s; 7 in a fit run alone). The
/// full-size profiles stage run alone (`process --until profiles`, earlier stages cached, 4
/// alternated pairs): 1.25-2.76 -> 0.85-1.08 s wall, 2.07-3.51 -> 1.54-1.83 CPU-s, peak
/// 829-896 -> 796-828 MB; outputs identical.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GeometryMap {
    /// Per camera pixel, its index in its run (`runs[i / CHUNK]`), or [`GeometryMap::UNLIT`].
    slots: Vec<u32>,
    /// The geometry of the lit pixels of each run of [`GeometryMap::CHUNK`] pixels, in order.
    runs: Vec<Vec<PixelGeometry>>,
}

impl GeometryMap {
    /// The slot of a pixel without geometry.
    const UNLIT: u32 = u32::MAX;

    /// Pixels per run (and per parallel task of [`GeometryMap::from_fn`]).
    const CHUNK: usize = 1 << 14;

    /// The map of `len` pixels whose geometry is `geometry(i)`, computed in parallel runs.
    pub fn from_fn(len: usize, geometry: impl Fn(usize) -> Option<PixelGeometry> + Sync) -> Self {
        // Zeroed memory from the system: each task writes its own slots.
        let mut slots = vec![0u32; len];
        let runs: Vec<Vec<PixelGeometry>> = slots
            .par_chunks_mut(Self::CHUNK)
            .enumerate()
            .map(|(k, run_slots)| {
                let first = k * Self::CHUNK;
                let mut values = Vec::new();
                for (offset, slot) in run_slots.iter_mut().enumerate() {
                    *slot = match geometry(first + offset) {
                        Some(g) => {
                            values.push(g);
                            // Below CHUNK: fits in a u32 and is never UNLIT.
                            (values.len() - 1) as u32
                        }
                        None => Self::UNLIT,
                    };
                }
                values.shrink_to_fit();
                values
            })
            .collect();
        Self { slots, runs }
    }

    /// The geometry of pixel `i`; `None` where it has none or lies outside the map.
    #[inline]
    pub fn get(&self, i: usize) -> Option<&PixelGeometry> {
        match *self.slots.get(i)? {
            Self::UNLIT => None,
            slot => self.runs.get(i / Self::CHUNK)?.get(slot as usize),
        }
    }

    /// Pixels covered (lit or not).
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Whether the map covers no pixel.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Pixels with geometry.
    pub fn lit_count(&self) -> usize {
        self.runs.iter().map(Vec::len).sum()
    }
}

impl FromIterator<Option<PixelGeometry>> for GeometryMap {
    fn from_iter<I: IntoIterator<Item = Option<PixelGeometry>>>(pixels: I) -> Self {
        let dense: Vec<Option<PixelGeometry>> = pixels.into_iter().collect();
        Self::from_fn(dense.len(), |i| dense[i])
    }
}

/// Per-pixel geometry of a projector: none where the pixel is off the subject, undecoded,
/// shadowed or at grazing incidence.
pub fn pixel_geometry(
    surface: &Surface,
    view: &ProjectorIllumination,
    eta: f64,
    view_ray: ViewRay,
) -> Result<GeometryMap, ProfileError> {
    if view.coords.len() != surface.len() {
        return Err(ProfileError::SizeMismatch {
            what: "projector coordinates",
            got: view.coords.len(),
            want: surface.len(),
        });
    }
    // Pixels are independent: split them across threads.
    Ok(GeometryMap::from_fn(surface.len(), |i| {
        let (u, v) = view.coords[i]?;
        let fp = surface.footprint(i)?;
        let jac = coord_jacobian(view, surface, i)?;
        let (p, n) = (&surface.points[i], &surface.normals[i]);
        let shift = shift_per_depth(p, n, &view.centre, &surface.camera_centre, eta, view_ray)?;
        let e = irradiance(p, n, &view.centre, &view.falloff);
        if e <= 0.0 {
            return None;
        }
        let axis = |row: usize| -> Option<AxisGeometry> {
            let grad = surface_gradient(&fp, Vector2::new(jac[(row, 0)], jac[(row, 1)]))?;
            let norm = grad.norm();
            (norm > 1e-9).then(|| AxisGeometry {
                px_per_mm: norm,
                shift_per_depth: shift.dot(&(grad / norm)),
            })
        };
        Some(PixelGeometry {
            coords: (f64::from(u), f64::from(v)),
            irradiance: e,
            axes: [axis(0)?, axis(1)?],
            shift,
        })
    }))
}

/// Signed distance (projector px) from `coord` to the centre of the nearest slit of a comb with
/// slits `width` px wide every `period` px starting at `offset`, in `[-period/2, period/2)`.
pub fn slit_distance_px(coord: f64, width: u32, period: u32, offset: u32) -> f64 {
    let centre = f64::from(offset) + (f64::from(width) - 1.0) / 2.0;
    let p = f64::from(period);
    euclid_mod(coord - centre + p / 2.0, p) - p / 2.0
}

/// `x.rem_euclid(p)` bit for bit for an integer period `p >= 1` (up to the sign of a zero
/// remainder, which the `- p / 2` of [`slit_distance_px`] makes irrelevant), without `fmod`: a
/// software routine in Rust's builtins, 1.2 % of the full-size pipeline's CPU at one call per
/// profile sample. Why it is exact: `n = floor(x / p)` is the true quotient's floor, or one more
/// when `x / p` rounds up to an integer; `n p` is an integer, so `x - n p` is a multiple of
/// `x`'s ulp no larger than `|x|` (exact) when `x` and `n` share a sign, and otherwise one
/// rounding of the exact `x - n p`, the same single rounding that `fmod`'s exact remainder plus
/// `p` makes; the fix-up `r + p` of a tiny negative `r` rounds that same exact value.
#[inline]
fn euclid_mod(x: f64, p: f64) -> f64 {
    let r = x - inline_floor::floor(x / p) * p;
    if r < 0.0 { r + p } else { r }
}

/// One checked slit frame: width, period, offset (projector px) and the global image.
type SweepFrame<'a> = (u32, u32, u32, SweepImage<'a>);

/// Where a sweep reads a slit frame's global light: a camera-sized image, or frame `j` of a
/// [`SlitStack`].
#[derive(Debug, Clone, Copy)]
enum SweepImage<'a> {
    Dense(&'a [[f32; 3]]),
    Stacked(&'a SlitStack, usize),
}

impl SweepImage<'_> {
    /// Channel `c` of pixel `i`; `None` for a pixel the stack does not hold.
    #[inline]
    fn value(&self, i: usize, c: usize) -> Option<f32> {
        match *self {
            SweepImage::Dense(img) => Some(img[i][c]),
            SweepImage::Stacked(stack, j) => stack.value(i, j, c),
        }
    }
}

/// The global slit light of one projector's sweep at the pixels that can have a profile only
/// (those with projector coordinates: about 40 % of a full-size frame), all frames of a pixel
/// side by side. Why: the fit holds every training projector's slits until the spatial prior
/// and the dipole baseline are done, and as camera-sized images they were 1 GB of the fit's
/// peak at full size; a profile also reads its samples from one place instead of one image per
/// slit. The values are the images' own, so profiles are bit for bit those of the images.
#[derive(Debug, Clone, Default)]
pub struct SlitStack {
    patterns: Vec<Pattern>,
    /// Per camera pixel: its row in `values`, or [`SlitStack::NO_ROW`].
    rows: Vec<u32>,
    /// Row `r`, frame `j`, channel `c` at `(r * frames + j) * 3 + c`.
    values: Vec<f32>,
}

impl SlitStack {
    const NO_ROW: u32 = u32::MAX;

    /// The `frames` (camera-sized, `pixels` each) at the pixels `keep` accepts.
    pub fn new(
        frames: &[SlitFrame],
        pixels: usize,
        keep: impl Fn(usize) -> bool,
    ) -> Result<Self, ProfileError> {
        for f in frames {
            if f.global.len() != pixels {
                return Err(ProfileError::SizeMismatch {
                    what: "slit frame",
                    got: f.global.len(),
                    want: pixels,
                });
            }
        }
        let kept_pixels: Vec<usize> = (0..pixels).filter(|&i| keep(i)).collect();
        let patterns = frames.iter().map(|f| f.pattern).collect();
        Ok(Self::gathered(patterns, pixels, kept_pixels, |j, i| {
            frames[j].global[i]
        }))
    }

    /// The stack of `patterns.len()` frames at the camera pixels `kept_pixels` (ascending,
    /// below `pixels`), every value 0 until [`SlitStack::fill_frames`] writes it. Why: a stage
    /// that makes the values pixel by pixel writes them in place, without a frame-sized buffer
    /// per frame to allocate and gather from.
    pub fn zeros(
        patterns: Vec<Pattern>,
        pixels: usize,
        kept_pixels: Vec<usize>,
    ) -> Result<Self, ProfileError> {
        Self::check_kept(&kept_pixels, pixels)?;
        Ok(Self::unfilled(patterns, pixels, &kept_pixels))
    }

    /// The stack of `patterns.len()` frames over `pixels` camera pixels holding `kept_pixels`
    /// (ascending, at most [`SlitStack::NO_ROW`] of them are numbered), every value 0.
    fn unfilled(patterns: Vec<Pattern>, pixels: usize, kept_pixels: &[usize]) -> Self {
        let kept_pixels = &kept_pixels[..kept_pixels.len().min(Self::NO_ROW as usize)];
        let mut rows = vec![Self::NO_ROW; pixels];
        for (row, &i) in kept_pixels.iter().enumerate() {
            rows[i] = row as u32;
        }
        let values = vec![0.0f32; kept_pixels.len() * patterns.len() * 3];
        Self {
            patterns,
            rows,
            values,
        }
    }

    /// Refuses kept pixels that are not ascending or lie outside `pixels`.
    fn check_kept(kept_pixels: &[usize], pixels: usize) -> Result<(), ProfileError> {
        let ascending_inside = kept_pixels.windows(2).all(|w| w[0] < w[1])
            && kept_pixels.last().is_none_or(|&i| i < pixels);
        if ascending_inside {
            Ok(())
        } else {
            Err(ProfileError::SizeMismatch {
                what: "kept pixels (ascending, inside the frame)",
                got: kept_pixels.last().map_or(0, |&i| i + 1),
                want: pixels,
            })
        }
    }

    /// Writes the frames `frames` (indices into the patterns) at every pixel the stack holds:
    /// `fill(i, values)` gets camera pixel `i` and its values of those frames (3 a frame, in
    /// order) to write; rows in parallel. Stops at the first error of `fill`; refuses a range
    /// past the patterns.
    pub fn fill_frames<E: From<ProfileError> + Send>(
        &mut self,
        frames: std::ops::Range<usize>,
        fill: impl Fn(usize, &mut [f32]) -> Result<(), E> + Sync,
    ) -> Result<(), E> {
        let n = self.patterns.len();
        if frames.start > frames.end || frames.end > n {
            return Err(ProfileError::SizeMismatch {
                what: "frame range",
                got: frames.end,
                want: n,
            }
            .into());
        }
        // Rows are numbered in pixel order: the kept pixels, ascending, are the rows' pixels.
        let kept: Vec<usize> = (0..self.rows.len())
            .filter(|&i| self.rows[i] != Self::NO_ROW)
            .collect();
        let columns = 3 * frames.start..3 * frames.end;
        self.values
            .par_chunks_mut((n * 3).max(1))
            .zip(kept.par_iter())
            .try_for_each(|(row, &i)| fill(i, &mut row[columns.clone()]))
    }

    /// The stack of `patterns.len()` frames over `pixels` camera pixels holding `kept_pixels`
    /// (ascending, at most [`SlitStack::NO_ROW`] of them are numbered), whose values `value(j, i)`
    /// gives for frame `j` at camera pixel `i`.
    fn gathered(
        patterns: Vec<Pattern>,
        pixels: usize,
        kept_pixels: Vec<usize>,
        value: impl Fn(usize, usize) -> [f32; 3] + Sync,
    ) -> Self {
        let mut stack = Self::unfilled(patterns, pixels, &kept_pixels);
        let n = stack.patterns.len();
        // Row by row (in parallel): each row gathers its pixel from every frame.
        stack
            .values
            .par_chunks_mut((n * 3).max(1))
            .zip(kept_pixels.par_iter())
            .for_each(|(row, &i)| {
                for j in 0..n {
                    row[j * 3..j * 3 + 3].copy_from_slice(&value(j, i));
                }
            });
        stack
    }

    /// Frame `j` as a camera-sized image, zero at the pixels the stack does not hold (`None`
    /// past the last frame).
    pub fn frame(&self, j: usize) -> Option<Vec<[f32; 3]>> {
        if j >= self.patterns.len() {
            return None;
        }
        Some(
            self.rows
                .par_iter()
                .enumerate()
                .map(|(i, _)| {
                    let at = |c| self.value(i, j, c).unwrap_or(0.0);
                    [at(0), at(1), at(2)]
                })
                .collect(),
        )
    }

    /// The frames' patterns, in the order given.
    pub fn patterns(&self) -> &[Pattern] {
        &self.patterns
    }

    /// Camera pixels the stack was made for.
    pub fn pixels(&self) -> usize {
        self.rows.len()
    }

    /// Channel `c` of frame `j` at camera pixel `i`; `None` where the stack holds no row.
    #[inline]
    pub fn value(&self, i: usize, j: usize, c: usize) -> Option<f32> {
        let row = *self.rows.get(i)?;
        if row == Self::NO_ROW {
            return None;
        }
        let n = self.patterns.len();
        self.values.get((row as usize * n + j) * 3 + c).copied()
    }
}

/// The slit frames of one projector, checked, split by axis.
#[derive(Debug, Clone)]
pub struct SlitSweep<'a> {
    frames: [Vec<SweepFrame<'a>>; 2],
    /// Camera noise of the frames, handed to every profile ([`Profile::noise`]).
    noise: Option<FrameNoise>,
    /// The stack's slit sums that [`SlitSweep::flux`] reads ([`SlitSweep::with_flux_totals`]).
    totals: Option<FluxTotals<'a>>,
}

/// Per row of a [`SlitStack`], per axis and channel: the sum of the axis' slit values clamped
/// at 0, in frame order, as [`SlitSweep::flux`] sums them. Why: the shading regression, the
/// EM's amplitudes and the spatial prior's each ask every pixel's flux under every training
/// projector (~4 million pixel-channel-projectors at full size, 20 slit values each, read one
/// by one through the stack's row index); summed once per row they are read once.
#[derive(Debug, Clone)]
struct FluxTotals<'a> {
    stack: &'a SlitStack,
    sums: Vec<[[f64; 3]; 2]>,
}

impl<'a> FluxTotals<'a> {
    /// The sums of `stack`'s rows over the frames `axes[a]` (indices into its patterns).
    fn new(stack: &'a SlitStack, axes: &[Vec<usize>; 2]) -> Self {
        let n = stack.patterns.len();
        let rows = if n == 0 {
            0
        } else {
            stack.values.len() / (n * 3)
        };
        let sums = (0..rows)
            .into_par_iter()
            .map(|r| {
                let row = &stack.values[r * n * 3..(r + 1) * n * 3];
                std::array::from_fn(|a| {
                    std::array::from_fn(|c| {
                        axes[a]
                            .iter()
                            .map(|&j| f64::from(row[j * 3 + c]).max(0.0))
                            .sum()
                    })
                })
            })
            .collect();
        Self { stack, sums }
    }

    /// Pixel `i`'s sum along axis `a` in channel `c`; `None` where the stack holds no row.
    #[inline]
    fn get(&self, i: usize, a: usize, c: usize) -> Option<f64> {
        let row = *self.stack.rows.get(i)?;
        Some(self.sums.get(row as usize)?[a][c])
    }
}

impl<'a> SlitSweep<'a> {
    pub fn new(frames: &[SlitFrame<'a>], pixels: usize) -> Result<Self, ProfileError> {
        for f in frames {
            if f.global.len() != pixels {
                return Err(ProfileError::SizeMismatch {
                    what: "slit frame",
                    got: f.global.len(),
                    want: pixels,
                });
            }
        }
        Self::from_images(
            frames
                .iter()
                .map(|f| (f.pattern, SweepImage::Dense(f.global))),
        )
    }

    /// The sweep over the frames of `stack` (a pixel it does not hold has no profile), with
    /// the same profiles as [`SlitSweep::new`] of its frames wherever it holds the pixel.
    pub fn from_stack(stack: &'a SlitStack, pixels: usize) -> Result<Self, ProfileError> {
        if stack.pixels() != pixels {
            return Err(ProfileError::SizeMismatch {
                what: "slit stack",
                got: stack.pixels(),
                want: pixels,
            });
        }
        Self::from_images(
            stack
                .patterns()
                .iter()
                .enumerate()
                .map(|(j, p)| (*p, SweepImage::Stacked(stack, j))),
        )
    }

    fn from_images(
        frames: impl Iterator<Item = (Pattern, SweepImage<'a>)>,
    ) -> Result<Self, ProfileError> {
        let mut out: [Vec<_>; 2] = Default::default();
        for (index, (pattern, image)) in frames.enumerate() {
            let Pattern::Slit {
                axis,
                width,
                period,
                offset,
            } = pattern
            else {
                return Err(ProfileError::NotASlit {
                    index,
                    label: pattern.label(),
                });
            };
            let a = match axis {
                Axis::X => 0,
                Axis::Y => 1,
            };
            out[a].push((width, period, offset, image));
        }
        Ok(Self {
            frames: out,
            noise: None,
            totals: None,
        })
    }

    /// The sweep with the camera noise of its frames (the global parts carry the frames' noise;
    /// the direct part taken off them is smooth and adds little).
    pub fn with_noise(self, noise: FrameNoise) -> Self {
        Self {
            noise: Some(noise),
            ..self
        }
    }

    /// The sweep with its slits' sums per pixel made once (in parallel), so that
    /// [`SlitSweep::flux`] reads one number instead of every slit's value; the same fluxes bit
    /// for bit. Unchanged unless every frame is of one [`SlitStack`] ([`SlitSweep::from_stack`]).
    pub fn with_flux_totals(self) -> Self {
        let Some(stack) = self.single_stack() else {
            return self;
        };
        let axes: [Vec<usize>; 2] = std::array::from_fn(|a| {
            self.frames[a]
                .iter()
                .filter_map(|f| match f.3 {
                    SweepImage::Stacked(_, j) => Some(j),
                    SweepImage::Dense(_) => None,
                })
                .collect()
        });
        Self {
            totals: Some(FluxTotals::new(stack, &axes)),
            ..self
        }
    }

    /// The stack every frame is read from, if there is one.
    fn single_stack(&self) -> Option<&'a SlitStack> {
        let mut frames = self.frames.iter().flatten();
        let SweepImage::Stacked(stack, _) = frames.next()?.3 else {
            return None;
        };
        frames
            .all(|f| matches!(f.3, SweepImage::Stacked(s, _) if std::ptr::eq(s, stack)))
            .then_some(stack)
    }

    /// The profile of pixel `i`, channel `c`, along axis `a` (0 = x, 1 = y), or `None` when this
    /// projector swept no slit along that axis.
    pub fn profile(&self, i: usize, c: usize, a: usize, geo: &PixelGeometry) -> Option<Profile> {
        let frames = &self.frames[a];
        let &(width, period, _, _) = frames.first()?;
        let ax = geo.axes[a];
        let coord = if a == 0 { geo.coords.0 } else { geo.coords.1 };
        // Sized up front: a collect into `Option<Vec>` knows no size and grows the vector
        // three times (a measurable part of the shading regression, which builds every pixel's).
        let mut samples = Vec::with_capacity(frames.len());
        for &(w, p, o, img) in frames {
            samples.push(Sample {
                s: slit_distance_px(coord, w, p, o) / ax.px_per_mm,
                y: f64::from(img.value(i, c)?),
            });
        }
        Some(Profile {
            noise: self.noise,
            samples,
            slit_width: f64::from(width) / ax.px_per_mm,
            period: Some(f64::from(period) / ax.px_per_mm),
            shift_per_depth: ax.shift_per_depth,
        })
    }

    /// The samples of [`SlitSweep::profile`]'s profiles of pixel `i` along axis `a` in all three
    /// channels at once, as `(s, [y; 3])`, without building the profiles (`None` where it gives
    /// none): the same numbers bit for bit. Why: the spatial prior's width statistics read
    /// every fitted tile's profiles in every channel, and building them was half its choice.
    pub fn samples_rgb<'s>(
        &'s self,
        i: usize,
        a: usize,
        geo: &PixelGeometry,
    ) -> Option<impl Iterator<Item = (f64, [f64; 3])> + 's> {
        let frames = &self.frames[a];
        frames.first()?;
        // A profile is all or nothing: a stack holds all of a pixel's slits or none.
        if frames.iter().any(|f| f.3.value(i, 0).is_none()) {
            return None;
        }
        let ax = geo.axes[a];
        let coord = if a == 0 { geo.coords.0 } else { geo.coords.1 };
        Some(frames.iter().map(move |&(w, p, o, img)| {
            let y = std::array::from_fn(|c| img.value(i, c).map_or(0.0, f64::from));
            (slit_distance_px(coord, w, p, o) / ax.px_per_mm, y)
        }))
    }

    /// `(flux, slit width)` (radiance x mm, mm) of [`SlitSweep::profile`]'s profile, the same
    /// numbers as its [`Profile::flux`] and `slit_width`, without building the samples: the
    /// amplitudes of every pixel need them, and building ~25 million profiles at full size for
    /// that was a measurable part of the fit.
    pub fn flux(&self, i: usize, c: usize, a: usize, geo: &PixelGeometry) -> Option<(f64, f64)> {
        let frames = &self.frames[a];
        let &(width, period, _, _) = frames.first()?;
        let px_per_mm = geo.axes[a].px_per_mm;
        let total: f64 = match &self.totals {
            Some(totals) => totals.get(i, a, c)?,
            None => frames
                .iter()
                .map(|&(_, _, _, img)| img.value(i, c).map(|v| f64::from(v).max(0.0)))
                .sum::<Option<f64>>()?,
        };
        let period_mm = f64::from(period) / px_per_mm;
        Some((
            total / frames.len() as f64 * period_mm,
            f64::from(width) / px_per_mm,
        ))
    }

    /// Per axis with slits, `(flux, E W)` of pixel `i`, channel `c` ([`SlitSweep::flux`] and its
    /// irradiance times slit width): what an amplitude `sum F / sum E W` sums.
    pub fn fluxes<'g>(
        &'g self,
        i: usize,
        c: usize,
        geo: &'g PixelGeometry,
    ) -> impl Iterator<Item = (f64, f64)> + 'g {
        (0..2).filter_map(move |a| {
            let (flux, width) = self.flux(i, c, a, geo)?;
            Some((flux, geo.irradiance * width))
        })
    }
}

/// The profiles of pixel `i`, channel `c` from every training projector that lights it, with the
/// `E W` product of each (for absolute weights).
pub(crate) fn pixel_profiles(
    i: usize,
    c: usize,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
) -> (Vec<Profile>, Vec<f64>) {
    let mut profiles = Vec::new();
    let mut ew = Vec::new();
    for (geo, sweep) in geometries.iter().zip(sweeps) {
        let Some(&g) = geo.get(i) else { continue };
        for a in 0..2 {
            if let Some(p) = sweep.profile(i, c, a, &g) {
                ew.push(g.irradiance * p.slit_width);
                profiles.push(p);
            }
        }
    }
    (profiles, ew)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sparse map holds exactly what the dense per-pixel vector held: lit patterns that
    /// cross the parallel chunks' borders, all lit, none lit, and an empty map.
    #[test]
    fn the_geometry_map_answers_as_the_dense_vector_it_replaces() {
        let geometry = |i: usize| PixelGeometry {
            coords: (i as f64, -(i as f64)),
            irradiance: 1.0 + i as f64,
            axes: [AxisGeometry {
                px_per_mm: 2.0,
                shift_per_depth: 0.5 * i as f64,
            }; 2],
            shift: Vector3::new(i as f64, 0.0, 1.0),
        };
        let len = 3 * GeometryMap::CHUNK + 17;
        let patterns: [&dyn Fn(usize) -> bool; 4] = [
            &|i| (i * 7919) % 13 < 5,
            &|i| i % GeometryMap::CHUNK > GeometryMap::CHUNK - 3,
            &|_| true,
            &|_| false,
        ];
        for lit in patterns {
            let dense: Vec<Option<PixelGeometry>> =
                (0..len).map(|i| lit(i).then(|| geometry(i))).collect();
            let map = GeometryMap::from_fn(len, |i| dense[i]);
            assert_eq!(map.len(), len);
            assert_eq!(map.lit_count(), dense.iter().flatten().count());
            assert!(
                (0..len)
                    .map(|i| map.get(i))
                    .eq(dense.iter().map(Option::as_ref))
            );
            assert_eq!(map.get(len), None);
            assert_eq!(dense.iter().copied().collect::<GeometryMap>(), map);
        }
        let empty = GeometryMap::from_fn(0, |i| Some(geometry(i)));
        assert!(empty.is_empty() && empty.get(0).is_none());
    }

    #[test]
    fn sweep_flux_is_the_profile_flux_bit_for_bit() {
        let n = 4;
        let frames_x: Vec<Vec<[f32; 3]>> = (0..10)
            .map(|j| {
                (0..n)
                    .map(|i| [j as f32 * 0.1 - 0.3, i as f32, 1.0])
                    .collect()
            })
            .collect();
        let frames: Vec<SlitFrame> = frames_x
            .iter()
            .enumerate()
            .map(|(j, g)| SlitFrame {
                pattern: Pattern::Slit {
                    axis: Axis::X,
                    width: 3,
                    period: 30,
                    offset: 3 * j as u32,
                },
                global: g,
            })
            .collect();
        let sweep = SlitSweep::new(&frames, n).unwrap();
        let axis = AxisGeometry {
            px_per_mm: 1.7,
            shift_per_depth: 0.3,
        };
        let geo = PixelGeometry {
            coords: (12.3, 4.0),
            irradiance: 0.8,
            axes: [axis; 2],
            shift: Vector3::zeros(),
        };
        for c in 0..3 {
            let p = sweep.profile(2, c, 0, &geo).unwrap();
            assert_eq!(sweep.flux(2, c, 0, &geo), Some((p.flux(), p.slit_width)));
        }
        assert_eq!(sweep.flux(2, 0, 1, &geo), None, "no slit along y");
    }

    /// The flux sums made once per row give every pixel's flux bit for bit as the dense sweep
    /// sums it slit by slit (the reference), on random stacks: axes interleaved in any order or
    /// one of them without slits, negative values (clamped), pixels the stack does not hold, and
    /// a dense sweep, which keeps summing itself.
    #[test]
    fn flux_totals_give_the_slit_by_slit_flux_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(29);
        let geo = PixelGeometry {
            coords: (3.1, 8.6),
            irradiance: 0.7,
            axes: [AxisGeometry {
                px_per_mm: 1.9,
                shift_per_depth: 0.1,
            }; 2],
            shift: Vector3::zeros(),
        };
        let mut compared = 0;
        for _ in 0..50 {
            let n = rng.gen_range(1..40);
            let frames_count = rng.gen_range(1..12);
            let y_share = [0.0, 0.5, 1.0][rng.gen_range(0..3)];
            let images: Vec<Vec<[f32; 3]>> = (0..frames_count)
                .map(|_| {
                    (0..n)
                        .map(|_| std::array::from_fn(|_| rng.gen_range(-0.3f32..2.0)))
                        .collect()
                })
                .collect();
            let frames: Vec<SlitFrame> = images
                .iter()
                .enumerate()
                .map(|(j, g)| SlitFrame {
                    pattern: Pattern::Slit {
                        axis: if rng.gen_bool(y_share) {
                            Axis::Y
                        } else {
                            Axis::X
                        },
                        width: 2,
                        period: 10,
                        offset: j as u32,
                    },
                    global: g,
                })
                .collect();
            let held: Vec<bool> = (0..n).map(|_| rng.gen_bool(0.7)).collect();
            let stack = SlitStack::new(&frames, n, |i| held[i]).unwrap();
            let dense = SlitSweep::new(&frames, n).unwrap();
            let summed = SlitSweep::from_stack(&stack, n).unwrap().with_flux_totals();
            assert!(summed.totals.is_some());
            let dense_summed = SlitSweep::new(&frames, n).unwrap().with_flux_totals();
            assert!(
                dense_summed.totals.is_none(),
                "a dense sweep has no stack to sum"
            );
            for (i, &holds) in held.iter().enumerate() {
                for (c, a) in (0..3).flat_map(|c| (0..2).map(move |a| (c, a))) {
                    let want = dense.flux(i, c, a, &geo);
                    let got = summed.flux(i, c, a, &geo);
                    if holds {
                        assert_eq!(
                            got.map(|(f, w)| (f.to_bits(), w.to_bits())),
                            want.map(|(f, w)| (f.to_bits(), w.to_bits())),
                            "pixel {i} channel {c} axis {a}"
                        );
                        compared += usize::from(want.is_some());
                    } else {
                        assert_eq!(got, None, "pixel {i} is not in the stack");
                    }
                    assert_eq!(dense_summed.flux(i, c, a, &geo), want);
                }
            }
        }
        assert!(compared > 1000, "only {compared} fluxes compared");
    }

    #[test]
    fn stacked_sweep_gives_the_dense_sweeps_profiles_bit_for_bit_where_it_holds_the_pixel() {
        let n = 6;
        // Two axes, interleaved as a capture orders them; values that differ per frame, pixel
        // and channel (and a negative one, which the flux clamps).
        let images: Vec<Vec<[f32; 3]>> = (0..8)
            .map(|j| {
                (0..n)
                    .map(|i| {
                        let v = (j * 7 + i * 3) as f32 * 0.013 - 0.05;
                        [v, v * 1.7 + 0.001, -v]
                    })
                    .collect()
            })
            .collect();
        let frames: Vec<SlitFrame> = images
            .iter()
            .enumerate()
            .map(|(j, g)| SlitFrame {
                pattern: Pattern::Slit {
                    axis: if j % 2 == 0 { Axis::X } else { Axis::Y },
                    width: 3,
                    period: 12,
                    offset: 3 * (j / 2) as u32,
                },
                global: g,
            })
            .collect();
        let keep = |i: usize| i % 3 != 1;
        let stack = SlitStack::new(&frames, n, keep).unwrap();
        let dense = SlitSweep::new(&frames, n).unwrap();
        let stacked = SlitSweep::from_stack(&stack, n).unwrap();
        let axis = AxisGeometry {
            px_per_mm: 1.3,
            shift_per_depth: 0.2,
        };
        let geo = PixelGeometry {
            coords: (7.4, 2.2),
            irradiance: 0.6,
            axes: [axis; 2],
            shift: Vector3::zeros(),
        };
        for i in 0..n {
            for c in 0..3 {
                for a in 0..2 {
                    let (d, s) = (dense.profile(i, c, a, &geo), stacked.profile(i, c, a, &geo));
                    if keep(i) {
                        let (d, s) = (d.unwrap(), s.unwrap());
                        assert_eq!(d.samples.len(), 4);
                        for (x, y) in d.samples.iter().zip(&s.samples) {
                            assert_eq!(
                                (x.s.to_bits(), x.y.to_bits()),
                                (y.s.to_bits(), y.y.to_bits())
                            );
                        }
                        assert_eq!(dense.flux(i, c, a, &geo), stacked.flux(i, c, a, &geo));
                    } else {
                        assert!(d.is_some() && s.is_none(), "pixel {i} is not in the stack");
                        assert_eq!(stacked.flux(i, c, a, &geo), None);
                    }
                }
            }
        }
        assert!(SlitSweep::from_stack(&stack, n + 1).is_err());
        // Frames back as images: the values where held, zero elsewhere.
        for (j, image) in images.iter().enumerate() {
            let back = stack.frame(j).unwrap();
            for i in 0..n {
                let want = if keep(i) { image[i] } else { [0.0; 3] };
                assert_eq!(back[i], want, "frame {j} pixel {i}");
            }
        }
        assert!(stack.frame(images.len()).is_none());
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let kept: Vec<usize> = (0..n).filter(|&i| keep(i)).collect();
        let patterns: Vec<Pattern> = frames.iter().map(|f| f.pattern).collect();
        let mut swapped = kept.clone();
        swapped.swap(0, 1);
        let mut outside = kept.clone();
        *outside.last_mut().unwrap() = n;
        // Filled in place, in two ranges of frames: the same stack; the filler's error stops
        // it, and a range past the frames or kept pixels out of order or outside are refused.
        let mut filled = SlitStack::zeros(patterns.clone(), n, kept.clone()).unwrap();
        assert!(filled.values.iter().all(|v| *v == 0.0));
        for frames in [0..3, 3..8] {
            filled
                .fill_frames(frames.clone(), |i, out| {
                    for (j, o) in frames.clone().zip(out.chunks_exact_mut(3)) {
                        o.copy_from_slice(&images[j][i]);
                    }
                    Ok::<(), ProfileError>(())
                })
                .unwrap();
        }
        assert_eq!(filled.rows, stack.rows);
        assert_eq!(bits(&filled.values), bits(&stack.values));
        let failing = filled.fill_frames(0..1, |i, _| {
            if i == kept[2] {
                Err(ProfileError::NotASlit {
                    index: i,
                    label: "test".into(),
                })
            } else {
                Ok(())
            }
        });
        assert!(matches!(failing, Err(ProfileError::NotASlit { .. })));
        assert!(
            filled
                .fill_frames(7..9, |_, _| Ok::<(), ProfileError>(()))
                .is_err()
        );
        assert!(SlitStack::zeros(patterns.clone(), n, swapped).is_err());
        assert!(SlitStack::zeros(patterns, n, outside).is_err());
    }

    #[test]
    fn euclid_mod_less_half_a_period_is_rem_euclids_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        for p in [1.0f64, 3.0, 30.0, 32.0, 1000.0] {
            let check = |x: f64| {
                assert_eq!(
                    (euclid_mod(x, p) - p / 2.0).to_bits(),
                    (x.rem_euclid(p) - p / 2.0).to_bits(),
                    "{x} mod {p}"
                )
            };
            for _ in 0..200_000 {
                check(rng.gen_range(-5000.0..5000.0));
            }
            // Around multiples of the period, where x / p rounds to an integer.
            for n in -200..200 {
                let m = f64::from(n) * p;
                let mut x = m;
                for _ in 0..8 {
                    check(x);
                    x = x.next_down();
                }
                x = m;
                for _ in 0..8 {
                    check(x);
                    x = x.next_up();
                }
            }
            for x in [0.0, -0.0, 1e-300, -1e-300, -1e-20, 4.9e-324, -4.9e-324] {
                check(x);
            }
        }
    }

    #[test]
    fn slit_distance_wraps_into_half_periods() {
        // Slit on columns 6, 7, 8 (centre 7), period 30.
        assert_eq!(slit_distance_px(7.0, 3, 30, 6), 0.0);
        assert_eq!(slit_distance_px(10.0, 3, 30, 6), 3.0);
        assert_eq!(slit_distance_px(4.0, 3, 30, 6), -3.0);
        assert_eq!(slit_distance_px(22.0, 3, 30, 6), -15.0);
        assert_eq!(slit_distance_px(21.5, 3, 30, 6), 14.5);
        assert_eq!(slit_distance_px(37.0 + 300.0, 3, 30, 6), 0.0);
    }

    #[test]
    fn plane_geometry_gives_mm_per_projector_pixel_and_the_shift() {
        // Plane z = 0 seen on a 0.2 mm grid; the projector maps u = 2 x_mm... i.e. u = 0.4 x_px.
        let (w, h) = (20, 10);
        let surface = Surface {
            width: w,
            height: h,
            points: (0..w * h)
                .map(|i| Vector3::new((i % w) as f64 * 0.2, (i / w) as f64 * 0.2, 0.0))
                .collect(),
            normals: vec![Vector3::z(); w * h],
            mask: vec![true; w * h],
            camera_centre: Vector3::new(2.0, 1.0, 1000.0),
        };
        let coords: Vec<Option<(f32, f32)>> = (0..w * h)
            .map(|i| Some((0.4 * (i % w) as f32, 0.5 * (i / w) as f32)))
            .collect();
        let view = ProjectorIllumination {
            centre: Vector3::new(-998.0, 1.0, 1000.0),
            falloff: Falloff::Isotropic,
            coords: &coords,
        };
        let geo = pixel_geometry(&surface, &view, 1.4, ViewRay::Refracted).unwrap();
        let g = *geo.get(5 * w + 10).unwrap();
        // u changes 0.4 px per 0.2 mm = 2 px/mm; v 0.5 px per 0.2 mm = 2.5 px/mm.
        assert!((g.axes[0].px_per_mm - 2.0).abs() < 1e-6);
        assert!((g.axes[1].px_per_mm - 2.5).abs() < 1e-6);
        // Light from -x at 45 degrees, camera overhead: shift along +x is tan(asin(sin45/1.4)).
        let want = ((45f64.to_radians().sin() / 1.4).asin()).tan();
        assert!((g.axes[0].shift_per_depth - want).abs() < 1e-3, "{g:?}");
        assert!(g.axes[1].shift_per_depth.abs() < 1e-3);
        // Irradiance at 45 degrees from sqrt(2) m: cos 45 / 2.
        assert!((g.irradiance - 45f64.to_radians().cos() / 2.0).abs() < 1e-3);
    }
}

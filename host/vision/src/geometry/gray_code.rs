//! Gray-code decoding: projector column and row for every camera pixel (DESIGN section 4, stage 1).
//!
//! Conventions
//! - Camera pixel `(x, y)` is column `x`, row `y`, origin top-left; images are row-major
//!   (`index = y * width + x`), one channel, linear values (any scale: thresholds are relative or
//!   follow [`DecodeParams`]'s noise model in the frames' own units).
//! - Projector coordinates follow `capture::patterns`: column `u`, row `v`, pixel centres at integer
//!   coordinates, so integer code `n` means the projector pixel centred at `n` (covering
//!   `[n - 0.5, n + 0.5)`). Sub-pixel coordinates use the same origin.
//! - Bit pairs are given MSB first (the capture order); bit `k` of the reflected Gray code of the
//!   coordinate is lit in the pattern and dark in its inverse.
//!
//! Algorithm
//! 1. Lit mask: `white - black` (or, with no black frame, the largest pattern/inverse difference of
//!    the coarse bits) must exceed `min_amplitude`.
//! 2. Each bit is decided by the sign of `pattern - inverse`. The bit is *reliable* when the
//!    difference exceeds both `min_bit_snr` standard deviations of the sensor noise and
//!    `min_bit_contrast` of the pixel's amplitude. Subsurface scattering washes out the finest
//!    stripes, so low bits are the ones that fail.
//! 3. Pixels with at most `max_repaired_bits` unreliable bits are repaired: among the codes the
//!    unreliable bits allow, the one closest to a plane fitted to the decoded neighbours is kept if
//!    it is within `repair_tolerance_px`; otherwise the pixel is flagged. This covers both the
//!    blurred fine bits and any bit seen right at its own stripe edge (where either value gives
//!    one of the two adjacent codes).
//! 4. Every decoded pixel is checked against a robust plane through its neighbours' codes; a pixel
//!    off by more than `outlier_px` is flagged (interreflections, specular glints, noise). The same
//!    local plane, fitted with the pixel itself, gives the sub-pixel coordinate: integer codes are
//!    a staircase of the smooth projector coordinate and the fit averages the quantisation out.
//!
//! Flagging is preferred to guessing: a pixel that is not clearly decodable is reported with a
//! [`PixelStatus`] saying why, never given a silently wrong code.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use mlsss_core::capture::patterns::gray_decode;

/// Errors of the Gray-code decoder.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GrayCodeError {
    /// A frame has a different number of pixels than `width * height`.
    #[error("frame `{frame}` has {len} pixels, expected {width}x{height} = {}", width * height)]
    FrameSize {
        frame: String,
        len: usize,
        width: usize,
        height: usize,
    },
    /// The sequence has too few bit pairs to address every projector column or row.
    #[error(
        "{axis} axis: {bits} Gray-code bits cannot address {size} projector pixels (need {needed})"
    )]
    TooFewBits {
        axis: &'static str,
        bits: usize,
        size: u32,
        needed: u32,
    },
    /// More than 16 bits per axis (codes are stored in 16 bits).
    #[error("{axis} axis: {bits} Gray-code bits is more than the 16 supported")]
    TooManyBits { axis: &'static str, bits: usize },
    /// No camera pixel is lit: all frames dark, a wrong bit depth, or the projector was off.
    #[error(
        "no camera pixel is lit (largest white-black difference {max_amplitude:.4}, threshold \
         {min_amplitude}): are the frames all dark, or were 8-bit frames read as 12-bit?"
    )]
    NothingLit {
        max_amplitude: f32,
        min_amplitude: f32,
    },
}

/// One bit of the code: the camera frame under the pattern and under its inverse.
#[derive(Debug, Clone, PartialEq)]
pub struct BitPair {
    pub pattern: Vec<f32>,
    pub inverse: Vec<f32>,
}

/// The camera frames of one projector's Gray-code sequence, reduced to one channel.
#[derive(Debug, Clone, PartialEq)]
pub struct GrayCodeFrames {
    /// Camera width and height in pixels.
    pub width: u32,
    pub height: u32,
    /// Full-field white, if captured (lit mask and contrast reference).
    pub white: Option<Vec<f32>>,
    /// Full-field black, if captured (ambient and projector black level).
    pub black: Option<Vec<f32>>,
    /// Column-code bits, MSB first.
    pub x: Vec<BitPair>,
    /// Row-code bits, MSB first.
    pub y: Vec<BitPair>,
}

/// Thresholds of the decoder. Noise terms are in the frames' units (linear, full scale 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecodeParams {
    /// Smallest `white - black` for a pixel to count as lit.
    pub min_amplitude: f32,
    /// Smallest |pattern - inverse| relative to the pixel's amplitude for a reliable bit.
    pub min_bit_contrast: f32,
    /// Smallest |pattern - inverse| in noise standard deviations for a reliable bit.
    pub min_bit_snr: f32,
    /// Shot noise: variance per unit of signal (1 / full-well electrons for a linear sensor).
    pub shot_noise_gain: f32,
    /// Read (and quantisation) noise standard deviation per frame.
    pub read_noise: f32,
    /// Most unreliable bits a pixel may have and still be repaired from its neighbours.
    pub max_repaired_bits: u32,
    /// Half-size of the square neighbourhood used for repair, consistency and sub-pixel fits.
    pub window_radius: u32,
    /// Largest distance between a repaired code and the neighbours' plane, projector pixels.
    pub repair_tolerance_px: f32,
    /// Largest distance between a decoded code and the neighbours' plane, projector pixels.
    pub outlier_px: f32,
    /// Smallest number of decoded neighbours for a pixel to be trusted.
    pub min_neighbours: u32,
}

impl Default for DecodeParams {
    fn default() -> Self {
        Self {
            min_amplitude: 0.02,
            min_bit_contrast: 0.03,
            min_bit_snr: 3.0,
            shot_noise_gain: 1.0 / 12_000.0,
            read_noise: 2.0 / 4095.0,
            max_repaired_bits: 4,
            window_radius: 2,
            repair_tolerance_px: 1.0,
            outlier_px: 2.0,
            min_neighbours: 5,
        }
    }
}

impl DecodeParams {
    /// Parameters for 8-bit frames (quantisation dominates the read noise).
    pub fn for_8_bit() -> Self {
        Self {
            read_noise: 1.5 / 255.0,
            ..Self::default()
        }
    }
}

/// Why a pixel has (or has no) code, per axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum PixelStatus {
    /// Every bit was reliable and the code agrees with the neighbours.
    Decoded = 0,
    /// Low bits were unreliable and were repaired from the neighbours.
    Repaired = 1,
    /// The projector does not light this pixel (shadow, background, outside its field).
    Unlit = 2,
    /// A bit above the repairable ones was unreliable.
    UnreliableBits = 3,
    /// Low bits were unreliable and no candidate code fits the neighbours.
    RepairFailed = 4,
    /// The code disagrees with its neighbours, or too few neighbours were decoded.
    Inconsistent = 5,
    /// The code is beyond the projector's width or height.
    OutOfRange = 6,
}

impl PixelStatus {
    /// True when the pixel has a code.
    pub fn is_valid(self) -> bool {
        matches!(self, PixelStatus::Decoded | PixelStatus::Repaired)
    }
}

/// The decoded coordinate along one projector axis for every camera pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisDecode {
    /// Integer projector coordinate, or -1 where the status is not valid.
    pub code: Vec<i32>,
    /// Sub-pixel projector coordinate, NaN where the status is not valid.
    pub coord: Vec<f32>,
    pub status: Vec<PixelStatus>,
}

/// Result of decoding one projector's sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct ProjectorDecode {
    /// Camera size.
    pub width: u32,
    pub height: u32,
    /// Projector size.
    pub projector_width: u32,
    pub projector_height: u32,
    /// Column coordinate (`u`).
    pub u: AxisDecode,
    /// Row coordinate (`v`).
    pub v: AxisDecode,
    /// Per-pixel confidence in [0, 1]: mean relative bit contrast, halved for repaired pixels,
    /// 0 where either axis is not valid.
    pub confidence: Vec<f32>,
}

impl ProjectorDecode {
    /// True when both axes decoded at pixel index `i`.
    pub fn is_valid(&self, i: usize) -> bool {
        self.u.status[i].is_valid() && self.v.status[i].is_valid()
    }

    /// Sub-pixel `(u, v)` at pixel index `i`, when both axes decoded.
    pub fn coords(&self, i: usize) -> Option<(f32, f32)> {
        self.is_valid(i).then(|| (self.u.coord[i], self.v.coord[i]))
    }

    /// Pixel counts per outcome.
    pub fn summary(&self) -> DecodeSummary {
        let n = self.u.status.len();
        let mut s = DecodeSummary {
            pixels: n,
            ..DecodeSummary::default()
        };
        for i in 0..n {
            let (a, b) = (self.u.status[i], self.v.status[i]);
            if a == PixelStatus::Unlit {
                s.unlit += 1;
            } else if self.is_valid(i) {
                s.valid += 1;
                if a == PixelStatus::Repaired || b == PixelStatus::Repaired {
                    s.repaired += 1;
                }
            } else {
                s.flagged += 1;
            }
        }
        s
    }
}

/// Pixel counts of a decode.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DecodeSummary {
    pub pixels: usize,
    /// Both axes decoded (including repaired).
    pub valid: usize,
    /// Valid pixels where at least one axis needed repair.
    pub repaired: usize,
    /// Not lit by the projector.
    pub unlit: usize,
    /// Lit but not decodable (unreliable, inconsistent, out of range).
    pub flagged: usize,
}

impl DecodeSummary {
    /// Valid pixels over all camera pixels.
    pub fn valid_fraction(&self) -> f64 {
        self.valid as f64 / self.pixels.max(1) as f64
    }

    /// Flagged pixels over lit pixels.
    pub fn flagged_fraction(&self) -> f64 {
        self.flagged as f64 / (self.pixels - self.unlit).max(1) as f64
    }
}

/// Decodes one projector's Gray-code sequence.
pub fn decode(
    frames: &GrayCodeFrames,
    projector_size: (u32, u32),
    params: &DecodeParams,
) -> Result<ProjectorDecode, GrayCodeError> {
    frames.validate(projector_size)?;
    let amplitude = frames.amplitude();
    let max_amplitude = amplitude.iter().copied().fold(0.0f32, f32::max);
    if max_amplitude < params.min_amplitude {
        return Err(GrayCodeError::NothingLit {
            max_amplitude,
            min_amplitude: params.min_amplitude,
        });
    }
    let grid = Grid {
        width: frames.width as usize,
        height: frames.height as usize,
    };
    let (u_bits, u_conf) = decide_bits(&frames.x, &amplitude, params);
    let (v_bits, v_conf) = decide_bits(&frames.y, &amplitude, params);
    let u = decode_axis(
        grid,
        &u_bits,
        frames.x.len() as u32,
        projector_size.0,
        params,
    );
    let v = decode_axis(
        grid,
        &v_bits,
        frames.y.len() as u32,
        projector_size.1,
        params,
    );
    let nbits = (frames.x.len() + frames.y.len()).max(1) as f32;
    let confidence = (0..grid.len())
        .map(|i| {
            if !(u.status[i].is_valid() && v.status[i].is_valid()) {
                return 0.0;
            }
            let c = (u_conf[i] + v_conf[i]) / nbits;
            let repaired =
                u.status[i] == PixelStatus::Repaired || v.status[i] == PixelStatus::Repaired;
            if repaired { 0.5 * c } else { c }
        })
        .collect();
    Ok(ProjectorDecode {
        width: frames.width,
        height: frames.height,
        projector_width: projector_size.0,
        projector_height: projector_size.1,
        u,
        v,
        confidence,
    })
}

/// Number of Gray-code bits needed to address `size` pixels.
pub fn bits_for(size: u32) -> u32 {
    u32::BITS - size.saturating_sub(1).leading_zeros()
}

impl GrayCodeFrames {
    /// The frames cropped to the camera rectangle at `(x0, y0)` of size `width` x `height`
    /// (clipped to the image), e.g. to decode around a calibration corner only.
    pub fn crop(&self, x0: u32, y0: u32, width: u32, height: u32) -> Self {
        let x0 = x0.min(self.width);
        let y0 = y0.min(self.height);
        let w = width.min(self.width - x0);
        let h = height.min(self.height - y0);
        let cut = |f: &Vec<f32>| -> Vec<f32> {
            (y0..y0 + h)
                .flat_map(|y| {
                    let start = (y * self.width + x0) as usize;
                    f.get(start..start + w as usize)
                        .unwrap_or(&[])
                        .iter()
                        .copied()
                })
                .collect()
        };
        let cut_pairs = |pairs: &Vec<BitPair>| {
            pairs
                .iter()
                .map(|p| BitPair {
                    pattern: cut(&p.pattern),
                    inverse: cut(&p.inverse),
                })
                .collect()
        };
        Self {
            width: w,
            height: h,
            white: self.white.as_ref().map(cut),
            black: self.black.as_ref().map(cut),
            x: cut_pairs(&self.x),
            y: cut_pairs(&self.y),
        }
    }

    fn validate(&self, projector_size: (u32, u32)) -> Result<(), GrayCodeError> {
        let (w, h) = (self.width as usize, self.height as usize);
        let check = |name: String, f: &Vec<f32>| {
            if f.len() == w * h {
                Ok(())
            } else {
                Err(GrayCodeError::FrameSize {
                    frame: name,
                    len: f.len(),
                    width: w,
                    height: h,
                })
            }
        };
        if let Some(f) = &self.white {
            check("white".into(), f)?;
        }
        if let Some(f) = &self.black {
            check("black".into(), f)?;
        }
        for (axis, pairs, size) in [
            ("x", &self.x, projector_size.0),
            ("y", &self.y, projector_size.1),
        ] {
            if pairs.len() > 16 {
                return Err(GrayCodeError::TooManyBits {
                    axis,
                    bits: pairs.len(),
                });
            }
            let needed = bits_for(size);
            if (pairs.len() as u32) < needed {
                return Err(GrayCodeError::TooFewBits {
                    axis,
                    bits: pairs.len(),
                    size,
                    needed,
                });
            }
            for (i, p) in pairs.iter().enumerate() {
                let bit = pairs.len() - 1 - i;
                check(format!("{axis} bit {bit}"), &p.pattern)?;
                check(format!("{axis} bit {bit} inverse"), &p.inverse)?;
            }
        }
        Ok(())
    }

    /// Per-pixel modulation: white - black, or without black the largest coarse-bit difference.
    fn amplitude(&self) -> Vec<f32> {
        match (&self.white, &self.black) {
            (Some(white), Some(black)) => white
                .par_iter()
                .zip(black.par_iter())
                .map(|(w, b)| w - b)
                .collect(),
            _ => {
                // Without a black frame, the coarse stripes (wide, hardly blurred) show the full
                // modulation on one side or the other.
                let coarse: Vec<&BitPair> =
                    self.x.iter().take(3).chain(self.y.iter().take(3)).collect();
                let n = self.width as usize * self.height as usize;
                (0..n)
                    .into_par_iter()
                    .map(|i| {
                        coarse
                            .iter()
                            .map(|p| (p.pattern[i] - p.inverse[i]).abs())
                            .fold(0.0, f32::max)
                    })
                    .collect()
            }
        }
    }
}

/// Bits of one axis at one pixel: the raw Gray code and which bits are reliable.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct PixelBits {
    gray: u16,
    reliable: u16,
    lit: bool,
}

/// Decides every bit of every pixel against its inverse. Also returns the summed relative contrast
/// of the bits (for the confidence).
fn decide_bits(
    pairs: &[BitPair],
    amplitude: &[f32],
    params: &DecodeParams,
) -> (Vec<PixelBits>, Vec<f32>) {
    let nbits = pairs.len();
    amplitude
        .par_iter()
        .enumerate()
        .map(|(i, &amp)| {
            let lit = amp >= params.min_amplitude;
            let mut bits = PixelBits {
                lit,
                ..PixelBits::default()
            };
            let mut contrast = 0.0;
            if !lit {
                return (bits, contrast);
            }
            for (j, pair) in pairs.iter().enumerate() {
                let bit = nbits - 1 - j;
                let (p, q) = (pair.pattern[i], pair.inverse[i]);
                let d = p - q;
                let sigma = (params.shot_noise_gain * (p + q).max(0.0)
                    + 2.0 * params.read_noise * params.read_noise)
                    .sqrt();
                let relative = d.abs() / amp;
                if d > 0.0 {
                    bits.gray |= 1 << bit;
                }
                if d.abs() >= params.min_bit_snr * sigma && relative >= params.min_bit_contrast {
                    bits.reliable |= 1 << bit;
                }
                contrast += relative.min(1.0);
            }
            (bits, contrast)
        })
        .unzip()
}

#[derive(Debug, Clone, Copy)]
struct Grid {
    width: usize,
    height: usize,
}

impl Grid {
    fn len(&self) -> usize {
        self.width * self.height
    }

    /// Indices and offsets of the pixels in the window around `i`, excluding `i`.
    fn window(&self, i: usize, radius: usize) -> impl Iterator<Item = (usize, f64, f64)> + '_ {
        let (x, y) = ((i % self.width) as isize, (i / self.width) as isize);
        let r = radius as isize;
        let (w, h) = (self.width as isize, self.height as isize);
        (-r..=r)
            .flat_map(move |dy| (-r..=r).map(move |dx| (dx, dy)))
            .filter(move |&(dx, dy)| {
                (dx, dy) != (0, 0) && (0..w).contains(&(x + dx)) && (0..h).contains(&(y + dy))
            })
            .map(move |(dx, dy)| (((y + dy) * w + x + dx) as usize, dx as f64, dy as f64))
    }
}

/// Integer codes of one axis: direct decode, repair of low bits, consistency and sub-pixel fit.
fn decode_axis(
    grid: Grid,
    bits: &[PixelBits],
    nbits: u32,
    size: u32,
    params: &DecodeParams,
) -> AxisDecode {
    // Pass 1: pixels whose bits are all reliable.
    let first: Vec<(i32, PixelStatus)> = bits
        .par_iter()
        .map(|b| initial_code(b, nbits, size, params))
        .collect();
    // Pass 2: repair from the neighbours, growing into regions where most pixels need it: each
    // round uses the codes decoded or repaired by the previous one.
    let mut repaired = first;
    for _ in 0..REPAIR_ROUNDS {
        let previous = repaired;
        repaired = (0..grid.len())
            .into_par_iter()
            .map(|i| match previous[i].1 {
                PixelStatus::RepairFailed => {
                    repair(grid, i, &bits[i], nbits, &previous, size, params)
                }
                _ => previous[i],
            })
            .collect();
    }
    // Pass 3: consistency with the neighbours, and sub-pixel coordinate.
    let checked: Vec<(i32, f32, PixelStatus)> = (0..grid.len())
        .into_par_iter()
        .map(|i| check_and_refine(grid, i, &repaired, params))
        .collect();
    let mut out = AxisDecode {
        code: Vec::with_capacity(grid.len()),
        coord: Vec::with_capacity(grid.len()),
        status: Vec::with_capacity(grid.len()),
    };
    for (code, coord, status) in checked {
        out.code.push(code);
        out.coord.push(coord);
        out.status.push(status);
    }
    out
}

/// Rounds of neighbour repair (each can reach `2 * window_radius` further into a blurred region).
const REPAIR_ROUNDS: usize = 3;

/// Pass 1 for one pixel. Pixels that need repair are marked `RepairFailed` until pass 2 succeeds.
fn initial_code(b: &PixelBits, nbits: u32, size: u32, params: &DecodeParams) -> (i32, PixelStatus) {
    if !b.lit {
        return (-1, PixelStatus::Unlit);
    }
    let unreliable = !b.reliable & bit_mask(nbits);
    if unreliable == 0 {
        return in_range(gray_decode(b.gray as u32), size, PixelStatus::Decoded);
    }
    if unreliable.count_ones() > params.max_repaired_bits {
        return (-1, PixelStatus::UnreliableBits);
    }
    (-1, PixelStatus::RepairFailed)
}

fn in_range(code: u32, size: u32, status: PixelStatus) -> (i32, PixelStatus) {
    if code < size {
        (code as i32, status)
    } else {
        (-1, PixelStatus::OutOfRange)
    }
}

fn bit_mask(bits: u32) -> u16 {
    if bits >= 16 {
        u16::MAX
    } else {
        (1u16 << bits) - 1
    }
}

/// Pass 2 for one pixel: the candidate code closest to the neighbours' plane, if close enough.
fn repair(
    grid: Grid,
    i: usize,
    b: &PixelBits,
    nbits: u32,
    first: &[(i32, PixelStatus)],
    size: u32,
    params: &DecodeParams,
) -> (i32, PixelStatus) {
    // A wider window than for the checks: in blurred regions the reliable pixels are sparse.
    let radius = 2 * params.window_radius as usize;
    let Some(predicted) = neighbour_prediction(grid, i, radius, first, params) else {
        return (-1, PixelStatus::RepairFailed);
    };
    let unreliable = !b.reliable & bit_mask(nbits);
    let fixed = b.gray & !unreliable;
    // Enumerate every setting of the unreliable bits (at most 2^max_repaired_bits).
    let mut best: Option<(f64, u32)> = None;
    let mut subset: u16 = 0;
    loop {
        let code = gray_decode((fixed | subset) as u32);
        let distance = (code as f64 - predicted).abs();
        if code < size && best.is_none_or(|(d, _)| distance < d) {
            best = Some((distance, code));
        }
        // Next subset of `unreliable` (standard subset enumeration).
        subset = subset.wrapping_sub(unreliable) & unreliable;
        if subset == 0 {
            break;
        }
    }
    match best {
        Some((d, code)) if d <= params.repair_tolerance_px as f64 => {
            (code as i32, PixelStatus::Repaired)
        }
        _ => (-1, PixelStatus::RepairFailed),
    }
}

/// Pass 3 for one pixel: flag codes that disagree with the neighbours, fit the sub-pixel value.
fn check_and_refine(
    grid: Grid,
    i: usize,
    codes: &[(i32, PixelStatus)],
    params: &DecodeParams,
) -> (i32, f32, PixelStatus) {
    let (code, status) = codes[i];
    if !status.is_valid() {
        return (-1, f32::NAN, status);
    }
    let radius = params.window_radius as usize;
    let stats = WindowStats::new(grid, i, radius, codes);
    if stats.is_full_and_smooth(radius) {
        // Fast path: over a complete symmetric window the least-squares plane's value at the
        // centre is the mean, so no fit is needed.
        let predicted = stats.sum / stats.count as f64;
        if (code as f64 - predicted).abs() > params.outlier_px as f64 {
            return (-1, f32::NAN, PixelStatus::Inconsistent);
        }
        let refined = ((stats.sum + code as f64) / (stats.count + 1) as f64)
            .clamp(code as f64 - 0.5, code as f64 + 0.5);
        return (code, refined as f32, status);
    }
    let samples: Vec<(f64, f64, f64)> = grid
        .window(i, radius)
        .filter(|&(j, _, _)| codes[j].1.is_valid())
        .map(|(j, dx, dy)| (dx, dy, codes[j].0 as f64))
        .collect();
    if samples.len() < params.min_neighbours as usize {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    }
    let Some(predicted) = robust_plane_at_centre(&samples, params) else {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    };
    if (code as f64 - predicted).abs() > params.outlier_px as f64 {
        return (-1, f32::NAN, PixelStatus::Inconsistent);
    }
    // The fit with the pixel itself, restricted to the same inliers, gives the sub-pixel value.
    let mut with_self: Vec<(f64, f64, f64)> = samples
        .iter()
        .copied()
        .filter(|&(_, _, c)| (c - code as f64).abs() <= jump_limit(params))
        .collect();
    with_self.push((0.0, 0.0, code as f64));
    // The code says which projector pixel is seen: keep the refined value inside it.
    let refined = robust_plane_at_centre(&with_self, params)
        .map(|p| p.clamp(code as f64 - 0.5, code as f64 + 0.5))
        .unwrap_or(code as f64);
    (code, refined as f32, status)
}

/// The neighbours' plane value at pixel `i` (valid neighbours within `radius`), if there are
/// enough of them.
fn neighbour_prediction(
    grid: Grid,
    i: usize,
    radius: usize,
    codes: &[(i32, PixelStatus)],
    params: &DecodeParams,
) -> Option<f64> {
    let stats = WindowStats::new(grid, i, radius, codes);
    if stats.is_full_and_smooth(radius) {
        return Some(stats.sum / stats.count as f64);
    }
    if stats.count < params.min_neighbours as usize {
        return None;
    }
    let samples: Vec<(f64, f64, f64)> = grid
        .window(i, radius)
        .filter(|&(j, _, _)| codes[j].1.is_valid())
        .map(|(j, dx, dy)| (dx, dy, codes[j].0 as f64))
        .collect();
    // Interpolate, never extrapolate: a plane through integer codes on one side only (image
    // border, shadow edge) is biased by the staircase of the codes.
    let has = |side: fn(f64, f64) -> bool| samples.iter().any(|s| side(s.0, s.1));
    let surrounded = has(|dx, _| dx < 0.0)
        && has(|dx, _| dx > 0.0)
        && has(|_, dy| dy < 0.0)
        && has(|_, dy| dy > 0.0);
    if !surrounded {
        return None;
    }
    robust_plane_at_centre(&samples, params)
}

/// Count, sum and range of the valid codes around a pixel (itself excluded), without allocating.
#[derive(Debug, Clone, Copy)]
struct WindowStats {
    count: usize,
    sum: f64,
    min: i32,
    max: i32,
    /// Pixels of the window inside the image (excluding the centre).
    size: usize,
}

impl WindowStats {
    fn new(grid: Grid, i: usize, radius: usize, codes: &[(i32, PixelStatus)]) -> Self {
        let (x, y) = (i % grid.width, i / grid.width);
        let (x0, x1) = (x.saturating_sub(radius), (x + radius).min(grid.width - 1));
        let (y0, y1) = (y.saturating_sub(radius), (y + radius).min(grid.height - 1));
        let mut s = Self {
            count: 0,
            sum: 0.0,
            min: i32::MAX,
            max: i32::MIN,
            size: (x1 - x0 + 1) * (y1 - y0 + 1) - 1,
        };
        for row in y0..=y1 {
            for (j, &(code, status)) in codes[row * grid.width + x0..=row * grid.width + x1]
                .iter()
                .enumerate()
            {
                if status.is_valid() && row * grid.width + x0 + j != i {
                    s.count += 1;
                    s.sum += code as f64;
                    s.min = s.min.min(code);
                    s.max = s.max.max(code);
                }
            }
        }
        s
    }

    /// Every pixel of the full square window is decoded and the codes span no more than a surface
    /// with a gradient of about one projector pixel per camera pixel would.
    fn is_full_and_smooth(&self, radius: usize) -> bool {
        let full = (2 * radius + 1).pow(2) - 1;
        self.size == full && self.count == full && self.max - self.min <= 2 * radius as i32 + 2
    }
}

/// Largest code difference to a neighbour that can still be on the same smooth surface.
fn jump_limit(params: &DecodeParams) -> f64 {
    // Up to ~2 projector pixels per camera pixel on steep surfaces, plus the repair tolerance.
    2.0 * params.window_radius as f64 + 2.0 + params.repair_tolerance_px as f64
}

/// Value at (0, 0) of a plane `c = a + b dx + e dy` fitted to `samples` (dx, dy, c), robustly:
/// samples far from the median are dropped, then the plane is refitted without its worst outliers.
/// Falls back to the inliers' mean when they do not span a plane.
fn robust_plane_at_centre(samples: &[(f64, f64, f64)], params: &DecodeParams) -> Option<f64> {
    let mut values: Vec<f64> = samples.iter().map(|s| s.2).collect();
    if values.is_empty() {
        return None;
    }
    // The element a full sort would put in the middle, found without sorting.
    let middle = values.len() / 2;
    let median = *values.select_nth_unstable_by(middle, f64::total_cmp).1;
    let limit = jump_limit(params);
    let mut inliers: Vec<(f64, f64, f64)> = samples
        .iter()
        .copied()
        .filter(|s| (s.2 - median).abs() <= limit)
        .collect();
    for _ in 0..2 {
        let plane = fit_plane(&inliers)?;
        let before = inliers.len();
        inliers.retain(|s| (plane.eval(s.0, s.1) - s.2).abs() <= 1.5);
        if inliers.len() == before {
            return Some(plane.a);
        }
        if inliers.len() < 3 {
            return None;
        }
    }
    fit_plane(&inliers).map(|p| p.a)
}

#[derive(Debug, Clone, Copy)]
struct Plane {
    a: f64,
    b: f64,
    c: f64,
}

impl Plane {
    fn eval(&self, dx: f64, dy: f64) -> f64 {
        self.a + self.b * dx + self.c * dy
    }
}

/// Least-squares plane through `(dx, dy, value)` samples; the mean when they are collinear.
fn fit_plane(samples: &[(f64, f64, f64)]) -> Option<Plane> {
    let n = samples.len() as f64;
    if samples.is_empty() {
        return None;
    }
    let (mut sx, mut sy, mut sv, mut sxx, mut syy, mut sxy, mut sxv, mut syv) =
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for &(x, y, v) in samples {
        sx += x;
        sy += y;
        sv += v;
        sxx += x * x;
        syy += y * y;
        sxy += x * y;
        sxv += x * v;
        syv += y * v;
    }
    let m = nalgebra::Matrix3::new(n, sx, sy, sx, sxx, sxy, sy, sxy, syy);
    let rhs = nalgebra::Vector3::new(sv, sxv, syv);
    // Samples on a line leave the plane undetermined (determinant ~0 relative to n^3).
    let well_posed = samples.len() >= 3 && m.determinant().abs() > 1e-6 * n * n * n;
    match m.lu().solve(&rhs) {
        Some(p) if well_posed && p.iter().all(|x| x.is_finite()) => Some(Plane {
            a: p[0],
            b: p[1],
            c: p[2],
        }),
        _ => Some(Plane {
            a: sv / n,
            b: 0.0,
            c: 0.0,
        }),
    }
}

/// Decoded coordinates compared with the true ones (simulated captures, synthetic frames).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthComparison {
    /// Valid pixels whose integer codes equal the rounded true coordinates (both axes).
    pub exact_fraction: f64,
    /// Valid pixels off by more than 0.5 projector pixel on either axis, or unlit in truth.
    pub wrong_fraction: f64,
    /// Mean |decoded - true| over both axes of valid pixels lit in truth, projector pixels.
    pub mean_abs_error_px: f64,
    /// Pixels lit in truth that the decoder flagged or called unlit, over pixels lit in truth.
    pub missed_fraction: f64,
}

impl TruthComparison {
    /// Compares `decoded` with `truth[i]` = true (u, v) at camera pixel index `i`, `None` where the
    /// projector does not light it.
    pub fn new(decoded: &ProjectorDecode, truth: &[Option<(f64, f64)>]) -> Self {
        let (mut valid, mut exact, mut wrong, mut lit, mut missed) = (0usize, 0, 0, 0, 0);
        let mut abs_sum = 0.0;
        let mut abs_count = 0usize;
        for (i, t) in truth.iter().enumerate() {
            let decoded_here = decoded.coords(i);
            if t.is_some() {
                lit += 1;
            }
            match (decoded_here, t) {
                (None, Some(_)) => missed += 1,
                (None, None) => {}
                (Some(_), None) => {
                    valid += 1;
                    wrong += 1;
                }
                (Some((u, v)), Some((tu, tv))) => {
                    valid += 1;
                    let (du, dv) = ((u as f64 - tu).abs(), (v as f64 - tv).abs());
                    abs_sum += du + dv;
                    abs_count += 2;
                    if du > 0.5 || dv > 0.5 {
                        wrong += 1;
                    }
                    if decoded.u.code[i] as f64 == tu.round()
                        && decoded.v.code[i] as f64 == tv.round()
                    {
                        exact += 1;
                    }
                }
            }
        }
        let frac = |a: usize, b: usize| a as f64 / b.max(1) as f64;
        Self {
            exact_fraction: frac(exact, valid),
            wrong_fraction: frac(wrong, valid),
            mean_abs_error_px: abs_sum / abs_count.max(1) as f64,
            missed_fraction: frac(missed, lit),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::synthetic::SyntheticGrayScene;

    fn truth_of(scene: &SyntheticGrayScene) -> Vec<Option<(f64, f64)>> {
        let (w, h) = scene.camera_size;
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| scene.projector_coords(x, y))
            .collect()
    }

    fn decode_scene(scene: &SyntheticGrayScene) -> (ProjectorDecode, TruthComparison) {
        let frames = scene.render();
        let decoded = decode(&frames, scene.projector_size, &DecodeParams::default()).unwrap();
        let cmp = TruthComparison::new(&decoded, &truth_of(scene));
        (decoded, cmp)
    }

    #[test]
    fn sharp_frames_decode_every_lit_pixel_to_the_true_column_and_row() {
        // About 2 camera pixels per projector pixel, as in the booth.
        let mut scene = SyntheticGrayScene::new((160, 120), (256, 192));
        scene.u = [40.3, 0.47, 0.03];
        scene.v = [30.6, -0.02, 0.52];
        let (decoded, cmp) = decode_scene(&scene);
        let summary = decoded.summary();
        assert_eq!(summary.unlit, 0);
        assert!(summary.valid_fraction() > 0.99, "{summary:?}");
        assert_eq!(cmp.wrong_fraction, 0.0, "{cmp:?}");
        assert!(cmp.exact_fraction > 0.95, "{cmp:?}");
        // Sub-pixel refinement beats the 0.25 px mean error of integer codes.
        assert!(cmp.mean_abs_error_px < 0.12, "{cmp:?}");
    }

    #[test]
    fn shadowed_pixels_are_unlit_and_never_decoded() {
        let mut scene = SyntheticGrayScene::new((120, 90), (256, 192));
        scene.shadow_disc = Some([60.0, 45.0, 20.0]);
        let (decoded, cmp) = decode_scene(&scene);
        for (i, t) in truth_of(&scene).iter().enumerate() {
            if t.is_none() {
                assert_eq!(decoded.u.status[i], PixelStatus::Unlit, "pixel {i}");
                assert!(decoded.coords(i).is_none());
            }
        }
        // Integer codes are all right; sub-pixel fits at the shadow's rim may stray a little.
        assert_eq!(cmp.exact_fraction, 1.0, "{cmp:?}");
        assert!(cmp.wrong_fraction < 0.002, "{cmp:?}");
    }

    #[test]
    fn subsurface_blur_of_fine_bits_is_repaired_or_flagged_never_silently_wrong() {
        // 70% of the light is blurred over 3 projector pixels: the two finest bits (2- and 4-px
        // stripes) lose most of their contrast, with 12-bit-like noise on top.
        let mut scene = SyntheticGrayScene::new((160, 120), (256, 192));
        scene.u = [40.3, 0.47, 0.03];
        scene.v = [30.6, -0.02, 0.52];
        scene.direct_fraction = 0.06;
        scene.global_blur_px = 3.0;
        scene.albedo = 0.5;
        scene.seed = 7;
        let (decoded, cmp) = decode_scene(&scene);
        let summary = decoded.summary();
        eprintln!("{summary:?} {cmp:?}");
        assert!(
            summary.repaired > 0,
            "the blur must make some bits unreliable: {summary:?}"
        );
        assert!(summary.valid_fraction() > 0.8, "{summary:?}");
        assert!(
            cmp.wrong_fraction * (summary.valid as f64) < summary.flagged as f64,
            "wrong must be rarer than flagged: {cmp:?} {summary:?}"
        );
        assert!(cmp.wrong_fraction < 0.005, "{cmp:?}");
        assert!(cmp.mean_abs_error_px < 0.2, "{cmp:?}");
    }

    #[test]
    fn frames_without_black_use_the_coarse_pairs_for_the_lit_mask() {
        let mut scene = SyntheticGrayScene::new((120, 90), (256, 192));
        scene.shadow_disc = Some([30.0, 30.0, 15.0]);
        let mut frames = scene.render();
        frames.black = None;
        frames.white = None;
        let decoded = decode(&frames, scene.projector_size, &DecodeParams::default()).unwrap();
        let cmp = TruthComparison::new(&decoded, &truth_of(&scene));
        assert!(cmp.wrong_fraction < 0.002, "{cmp:?}");
        assert!(decoded.summary().valid_fraction() > 0.9);
        assert!(decoded.summary().unlit > 500);
    }

    #[test]
    fn bad_inputs_are_errors_naming_the_problem() {
        let scene = SyntheticGrayScene::new((40, 30), (256, 192));
        let frames = scene.render();
        let params = DecodeParams::default();

        let mut short = frames.clone();
        short.x[3].inverse.truncate(100);
        let err = decode(&short, (256, 192), &params).unwrap_err();
        assert!(err.to_string().contains("x bit 4 inverse"), "{err}");

        let err = decode(&frames, (1024, 192), &params).unwrap_err();
        assert!(
            matches!(err, GrayCodeError::TooFewBits { needed: 10, .. }),
            "{err}"
        );

        // 8-bit codes read as 12-bit: everything 16 times too dark.
        let mut dark = frames.clone();
        let scale = |f: &mut Vec<f32>| f.iter_mut().for_each(|v| *v /= 16.0 * 4.0);
        dark.white.as_mut().map(scale);
        dark.black.as_mut().map(scale);
        let err = decode(&dark, (256, 192), &params).unwrap_err();
        assert!(err.to_string().contains("8-bit"), "{err}");
    }

    #[test]
    fn bits_for_counts_code_bits() {
        assert_eq!(bits_for(1024), 10);
        assert_eq!(bits_for(768), 10);
        assert_eq!(bits_for(1025), 11);
        assert_eq!(bits_for(256), 8);
        assert_eq!(bits_for(192), 8);
    }
}

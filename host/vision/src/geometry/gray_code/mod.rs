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
//! 1. Lit mask, relative to each pixel's noise (`lit_test`): the pattern/inverse differences of
//!    every pair (and `white - black` when a black frame exists), each divided by its standard
//!    deviation under the sensor noise model, are summed in squares and tested as a chi-square
//!    variable at the false-alarm probability `lit_false_alarm`. Pixels significant only at
//!    `dim_false_alarm` are flagged as [`PixelStatus::Dim`], never called unlit. The absolute
//!    `min_amplitude` only guards the whole sequence (frames all dark: an error).
//! 2. Each bit is decided by the sign of `pattern - inverse`. The bit is *reliable* when the
//!    difference exceeds both `min_bit_snr` standard deviations of the sensor noise and
//!    `min_bit_contrast` of the pixel's amplitude. Subsurface scattering washes out the finest
//!    stripes, so low bits are the ones that fail. The noise threshold is low (1 standard
//!    deviation) on purpose: on dark skin most bits of a lit pixel sit a few standard deviations
//!    above the noise, and a stricter rule left whole regions without reliable pixels to repair
//!    from (issue 18); a wrong sign that passes it is caught by steps 3 and 4, and blurred bits
//!    by the contrast rule.
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

mod axis;
mod bits;
mod lit_test;
mod plane;
#[cfg(test)]
mod tests;
mod window_columns;
mod window_fit;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use axis::{Grid, decode_axis};
use bits::{first_pass, mask_unlit};
use lit_test::demote_partly_lit;
use mlsss_core::capture::FrameNoise;

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
    /// No pattern can be told from its inverse because the frames are saturated (white and
    /// black both at the top of the sensor's range).
    #[error(
        "no camera pixel is lit above the black frame, and {saturated_percent:.0} % of the white \
         frame is saturated: the frames are overexposed (lower the exposure), not dark"
    )]
    Saturated { saturated_percent: f32 },
    /// A decoder parameter is out of its range.
    #[error("decoder parameter `{key}`: {reason}")]
    BadParams { key: &'static str, reason: String },
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
    /// Smallest `white - black` (or coarse-pair difference) of the brightest pixel: below it the
    /// whole sequence is dark ([`GrayCodeError::NothingLit`]). Not a per-pixel threshold: each
    /// pixel is judged against its own noise (`lit_false_alarm`).
    pub min_amplitude: f32,
    /// Probability that a pixel the projector does not light is called lit (chi-square test of
    /// its pair differences against the sensor noise).
    #[serde(default = "default_lit_false_alarm")]
    pub lit_false_alarm: f32,
    /// Probability that such a pixel is flagged dim (significant, too weak to call lit).
    #[serde(default = "default_dim_false_alarm")]
    pub dim_false_alarm: f32,
    /// A lit pixel whose amplitude is below this fraction of the brightest lit pixel within
    /// `window_radius` is flagged dim: lit in part (silhouette, shadow edge) or only through the
    /// skin. 0 turns the check off.
    #[serde(default)]
    pub min_neighbour_ratio: f32,
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
            lit_false_alarm: default_lit_false_alarm(),
            dim_false_alarm: default_dim_false_alarm(),
            min_neighbour_ratio: 0.5,
            min_bit_contrast: 0.03,
            min_bit_snr: 1.0,
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

fn default_lit_false_alarm() -> f32 {
    1e-7
}

fn default_dim_false_alarm() -> f32 {
    1e-4
}

/// Largest `window_radius`: the repair window is `4 * radius + 1` pixels a side.
pub const MAX_WINDOW_RADIUS: u32 = 64;
/// Largest `max_repaired_bits`: a repair tries `2^bits` codes per pixel.
pub const MAX_REPAIRED_BITS: u32 = 8;

impl DecodeParams {
    /// Checks every threshold is finite and in its range (a NaN threshold accepts or refuses
    /// every bit, a huge window never ends).
    pub fn check(&self) -> Result<(), GrayCodeError> {
        let bad = |key, reason: String| Err(GrayCodeError::BadParams { key, reason });
        for (key, value) in [
            ("min_amplitude", self.min_amplitude),
            ("min_neighbour_ratio", self.min_neighbour_ratio),
            ("min_bit_contrast", self.min_bit_contrast),
            ("min_bit_snr", self.min_bit_snr),
            ("shot_noise_gain", self.shot_noise_gain),
            ("read_noise", self.read_noise),
            ("repair_tolerance_px", self.repair_tolerance_px),
            ("outlier_px", self.outlier_px),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(key, format!("must be a finite number >= 0, got {value}"));
            }
        }
        for (key, value) in [
            ("lit_false_alarm", self.lit_false_alarm),
            ("dim_false_alarm", self.dim_false_alarm),
        ] {
            if !(value > 0.0 && value < 1.0) {
                return bad(key, format!("must be a probability in (0, 1), got {value}"));
            }
        }
        if self.window_radius == 0 || self.window_radius > MAX_WINDOW_RADIUS {
            return bad(
                "window_radius",
                format!(
                    "must be 1..={MAX_WINDOW_RADIUS}, got {}",
                    self.window_radius
                ),
            );
        }
        if self.max_repaired_bits > MAX_REPAIRED_BITS {
            return bad(
                "max_repaired_bits",
                format!(
                    "must be 0..={MAX_REPAIRED_BITS}, got {}",
                    self.max_repaired_bits
                ),
            );
        }
        let window = (2 * self.window_radius + 1).pow(2);
        if self.min_neighbours >= window {
            return bad(
                "min_neighbours",
                format!(
                    "must be below the {window} pixels of the window (window_radius {})",
                    self.window_radius
                ),
            );
        }
        Ok(())
    }

    /// These thresholds with a camera's noise model ([`FrameNoise`], from the camera and the
    /// exposure the frames were taken at, in the nominal units `Capture::read_frame` returns).
    pub fn with_camera_noise(self, noise: FrameNoise) -> Self {
        Self {
            shot_noise_gain: noise.shot_gain as f32,
            read_noise: noise.read_sigma as f32,
            ..self
        }
    }

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
    /// The projector probably lights the pixel, but too weakly to decode (significant against
    /// the noise only at the dim level).
    Dim = 7,
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

/// Wall seconds of the decoder's steps, for reports and for the comparison with OpenCV's
/// decoding (`scripts/peers.py`), which does the work of `bits_s` only.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct DecodePhases {
    /// Steps 1 and 2 and the codes of the pixels whose bits are all reliable: the lit test,
    /// every bit against its inverse, Gray to binary and the range check.
    pub bits_s: f64,
    /// Step 3: repair of unreliable bits from the neighbours.
    pub repair_s: f64,
    /// Step 4: the consistency check and the sub-pixel fit, and the confidence.
    pub check_s: f64,
}

/// Decodes one projector's Gray-code sequence.
pub fn decode(
    frames: &GrayCodeFrames,
    projector_size: (u32, u32),
    params: &DecodeParams,
) -> Result<ProjectorDecode, GrayCodeError> {
    decode_timed(frames, projector_size, params).map(|(decoded, _)| decoded)
}

/// [`decode`], with the time each step took.
pub fn decode_timed(
    frames: &GrayCodeFrames,
    projector_size: (u32, u32),
    params: &DecodeParams,
) -> Result<(ProjectorDecode, DecodePhases), GrayCodeError> {
    let start = std::time::Instant::now();
    let mut phases = DecodePhases::default();
    params.check()?;
    frames.validate(projector_size)?;
    let amplitude = frames.amplitude();
    let max_amplitude = amplitude.iter().copied().fold(0.0f32, f32::max);
    if max_amplitude < params.min_amplitude {
        if let Some(saturated_percent) = frames.saturated_white_percent()
            && saturated_percent > 50.0
        {
            return Err(GrayCodeError::Saturated { saturated_percent });
        }
        return Err(GrayCodeError::NothingLit {
            max_amplitude,
            min_amplitude: params.min_amplitude,
        });
    }
    let grid = Grid {
        width: frames.width as usize,
        height: frames.height as usize,
    };
    let white_black = match (&frames.white, &frames.black) {
        (Some(w), Some(b)) => Some((w.as_slice(), b.as_slice())),
        _ => None,
    };
    let (mut lighting, (mut u_bits, mut u_conf), (mut v_bits, mut v_conf)) =
        first_pass(&frames.x, &frames.y, white_black, &amplitude, params);
    demote_partly_lit(
        &mut lighting,
        &amplitude,
        grid.width,
        params.window_radius as usize,
        params.min_neighbour_ratio,
    );
    mask_unlit(&mut u_bits, &mut u_conf, &lighting);
    mask_unlit(&mut v_bits, &mut v_conf, &lighting);
    phases.bits_s = start.elapsed().as_secs_f64();
    let u = decode_axis(
        grid,
        &u_bits,
        frames.x.len() as u32,
        projector_size.0,
        params,
        &mut phases,
    );
    let v = decode_axis(
        grid,
        &v_bits,
        frames.y.len() as u32,
        projector_size.1,
        params,
        &mut phases,
    );
    let confidence_start = std::time::Instant::now();
    let nbits = (frames.x.len() + frames.y.len()).max(1) as f32;
    let confidence = (0..grid.len())
        .into_par_iter()
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
    phases.check_s += confidence_start.elapsed().as_secs_f64();
    let decoded = ProjectorDecode {
        width: frames.width,
        height: frames.height,
        projector_width: projector_size.0,
        projector_height: projector_size.1,
        u,
        v,
        confidence,
    };
    Ok((decoded, phases))
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

    /// Every frame's buffer (white, black, then the pairs), to be read into again.
    pub fn into_buffers(self) -> Vec<Vec<f32>> {
        let pairs = self
            .x
            .into_iter()
            .chain(self.y)
            .flat_map(|p| [p.pattern, p.inverse]);
        self.white
            .into_iter()
            .chain(self.black)
            .chain(pairs)
            .collect()
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

    /// Share of the white frame (or, without one, of the brighter of the first bit pair) at
    /// the top of the range, percent; `None` when there are no frames.
    fn saturated_white_percent(&self) -> Option<f32> {
        /// A linear value this close to full scale counts as saturated.
        const SATURATED: f32 = 0.99;
        let brightest: Vec<f32> = match (&self.white, self.x.first()) {
            (Some(white), _) => white.clone(),
            (None, Some(pair)) => pair
                .pattern
                .iter()
                .zip(&pair.inverse)
                .map(|(a, b)| a.max(*b))
                .collect(),
            (None, None) => return None,
        };
        if brightest.is_empty() {
            return None;
        }
        let saturated = brightest.iter().filter(|&&v| v >= SATURATED).count();
        Some(100.0 * saturated as f32 / brightest.len() as f32)
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

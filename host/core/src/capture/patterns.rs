//! The projected patterns and their rasterisation at projector pixels.
//!
//! Conventions: projector pixel `(u, v)` is column `u`, row `v`, origin top-left; a pattern value is
//! the *requested* level in [0, 1] (before the projector's response curve).

use serde::{Deserialize, Serialize};

use crate::booth::PatternSpec;

/// The image axis a pattern codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    /// Columns: stripes are vertical lines, the code varies along x.
    X,
    /// Rows: stripes are horizontal lines, the code varies along y.
    Y,
}

/// One projected pattern. Variants are append-only: the names are part of the capture format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Pattern {
    /// Full field at level 1.
    White,
    /// Full field at level 0 (the projector's black level still emits light).
    Black,
    /// Bit `bit` (0 = least significant) of the reflected binary Gray code of the column (`X`) or
    /// row (`Y`); `inverted` swaps lit and unlit.
    Gray {
        axis: Axis,
        bit: u32,
        inverted: bool,
    },
    /// Lines `width` px wide every `period` px, starting at `offset` px: the slit sweep.
    Slit {
        axis: Axis,
        width: u32,
        period: u32,
        offset: u32,
    },
    /// Vertical stripes `stripe` px on, `stripe` px off, shifted right by `shift` px.
    HighFrequency { stripe: u32, shift: u32 },
    /// Full field at level `level_milli / 1000` (photometric calibration).
    Grey { level_milli: u32 },
}

/// The reflected binary Gray code of `n`.
pub fn gray_code(n: u32) -> u32 {
    n ^ (n >> 1)
}

/// Inverse of [`gray_code`]: bit `k` of the value is the XOR of the code's bits `k` and above,
/// taken as a prefix XOR in five shifts. Why not one shift per bit: the decoder's repair decodes
/// up to `2^max_repaired_bits` candidate codes per pixel.
#[inline]
pub fn gray_decode(g: u32) -> u32 {
    let mut n = g;
    n ^= n >> 1;
    n ^= n >> 2;
    n ^= n >> 4;
    n ^= n >> 8;
    n ^= n >> 16;
    n
}

impl Pattern {
    /// Requested level in [0, 1] at projector pixel (`u`, `v`).
    pub fn value(&self, u: u32, v: u32) -> f32 {
        let on = |b: bool| if b { 1.0 } else { 0.0 };
        match *self {
            Pattern::White => 1.0,
            Pattern::Black => 0.0,
            Pattern::Gray {
                axis,
                bit,
                inverted,
            } => {
                // A bit beyond the code is 0 (a plain `>>` would wrap it to `bit % 32`).
                let coord = pick(axis, u, v);
                let set = gray_code(coord).checked_shr(bit).unwrap_or(0) & 1 == 1;
                on(set != inverted)
            }
            Pattern::Slit {
                axis,
                width,
                period,
                offset,
            } => {
                // A period of 0 (refused by the readers) lights nothing instead of dividing by 0.
                let coord = pick(axis, u, v) as i64;
                on(period > 0 && (coord - offset as i64).rem_euclid(period as i64) < width as i64)
            }
            Pattern::HighFrequency { stripe, shift } => on(stripe > 0
                && (u as i64 - shift as i64).rem_euclid(2 * stripe as i64) < stripe as i64),
            Pattern::Grey { level_milli } => level_milli as f32 / 1000.0,
        }
    }

    /// A short, file-name-safe label, e.g. `gray-x-b9-inv`.
    pub fn label(&self) -> String {
        let axis = |a: Axis| match a {
            Axis::X => "x",
            Axis::Y => "y",
        };
        match *self {
            Pattern::White => "white".into(),
            Pattern::Black => "black".into(),
            Pattern::Gray {
                axis: a,
                bit,
                inverted,
            } => format!(
                "gray-{}-b{bit}{}",
                axis(a),
                if inverted { "-inv" } else { "" }
            ),
            Pattern::Slit {
                axis: a, offset, ..
            } => format!("slit-{}-o{offset}", axis(a)),
            Pattern::HighFrequency { shift, .. } => format!("hf-s{shift}"),
            Pattern::Grey { level_milli } => format!("grey-{level_milli}"),
        }
    }

    /// Whether this pattern is one of `spec`'s: a Gray-code bit below the axis's bit count, the
    /// spec's slit width and period with an offset inside the period, the spec's stripe width with
    /// a shift inside its period, a grey level in [0, 1000]. The reason when it is not.
    pub fn check_against(&self, spec: &PatternSpec) -> Result<(), String> {
        match *self {
            Pattern::White | Pattern::Black => Ok(()),
            Pattern::Gray { axis, bit, .. } => {
                let bits = match axis {
                    Axis::X => spec.gray_bits_x,
                    Axis::Y => spec.gray_bits_y,
                };
                if bit < bits {
                    Ok(())
                } else {
                    Err(format!(
                        "Gray-code bit {bit} does not exist: the booth has {bits} bits along \
                         this axis (bits 0..={})",
                        bits.saturating_sub(1)
                    ))
                }
            }
            Pattern::Slit {
                width,
                period,
                offset,
                ..
            } => {
                if (width, period) != (spec.slit_width_px, spec.slit_period_px) {
                    Err(format!(
                        "slit {width} px every {period} px, the booth's slits are {} px every {} px",
                        spec.slit_width_px, spec.slit_period_px
                    ))
                } else if offset >= period || offset % width.max(1) != 0 {
                    Err(format!(
                        "slit offset {offset} is not one of the sweep's (0, {width}, ... below \
                         {period})"
                    ))
                } else {
                    Ok(())
                }
            }
            Pattern::HighFrequency { stripe, shift } => {
                if stripe != spec.hf_stripe_px {
                    Err(format!(
                        "stripes {stripe} px wide, the booth's are {} px",
                        spec.hf_stripe_px
                    ))
                } else if shift >= spec.hf_shifts() {
                    Err(format!(
                        "stripe shift {shift} is not one of the booth's (0..{})",
                        spec.hf_shifts()
                    ))
                } else {
                    Ok(())
                }
            }
            Pattern::Grey { level_milli } if level_milli <= 1000 => Ok(()),
            Pattern::Grey { level_milli } => Err(format!(
                "grey level {level_milli} is above 1000 (full white)"
            )),
        }
    }

    /// Rasterises the pattern at a projector resolution, row-major.
    pub fn render(&self, width: u32, height: u32) -> Vec<f32> {
        let mut out = Vec::with_capacity(width as usize * height as usize);
        for v in 0..height {
            for u in 0..width {
                out.push(self.value(u, v));
            }
        }
        out
    }
}

fn pick(axis: Axis, u: u32, v: u32) -> u32 {
    match axis {
        Axis::X => u,
        Axis::Y => v,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The prefix XOR is the XOR of every shift of the code (the definition, one shift per
    /// bit): on every 16-bit code and on codes with the top bits set.
    #[test]
    fn gray_decode_is_the_xor_of_every_shift() {
        let by_definition = |g: u32| (0..32).fold(0, |n, k| n ^ (g >> k));
        for g in (0..=u32::from(u16::MAX)).chain((0..4096).map(|i| u32::MAX - i * 1_048_573)) {
            assert_eq!(gray_decode(g), by_definition(g), "{g}");
        }
    }

    #[test]
    fn gray_code_neighbours_differ_in_one_bit_and_decode_inverts() {
        for n in 0..2048u32 {
            assert_eq!(gray_decode(gray_code(n)), n);
            assert_eq!((gray_code(n) ^ gray_code(n + 1)).count_ones(), 1);
        }
    }

    #[test]
    fn gray_patterns_encode_the_column() {
        // Reading the 10 bits of column 437 back from the patterns gives 437.
        let u = 437;
        let code = (0..10).fold(0, |acc, bit| {
            let p = Pattern::Gray {
                axis: Axis::X,
                bit,
                inverted: false,
            };
            acc | ((p.value(u, 5) as u32) << bit)
        });
        assert_eq!(gray_decode(code), u);
    }

    #[test]
    fn slit_sweep_lights_every_pixel_exactly_once() {
        let (width, period) = (3, 30);
        for u in 0..90 {
            let lit = (0..period / width)
                .filter(|k| {
                    Pattern::Slit {
                        axis: Axis::X,
                        width,
                        period,
                        offset: k * width,
                    }
                    .value(u, 0)
                        == 1.0
                })
                .count();
            assert_eq!(lit, 1, "column {u}");
        }
    }

    #[test]
    fn high_frequency_is_half_on_and_each_pixel_lit_half_the_shifts() {
        let stripe = 3;
        for u in 0..12 {
            let lit = (0..2 * stripe)
                .filter(|&s| Pattern::HighFrequency { stripe, shift: s }.value(u, 0) == 1.0)
                .count();
            assert_eq!(lit, 3);
        }
    }
}

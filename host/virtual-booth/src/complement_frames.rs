//! Frames derived from others by the linearity of light transport: a pattern and its complement
//! (the Gray-code bit and its inverse, a high-frequency shift and the shift half a period on)
//! together emit exactly what white and black emit, so the complement's noise-free frame is
//! `white + black - frame = (1 + black / white) * white - frame` and needs no render of its own.
//!
//! Exact in real arithmetic (the emission's response curve maps 0 to the black level and 1 to the
//! white level, the lens blur and every step after it are linear); in `f32` the derived values
//! differ from a direct render by rounding only, far below one frame's camera noise.

use mlsss_core::capture::Pattern;

use super::frame_render::FrameRadiance;

/// The pattern whose light added to `pattern`'s is white + black, if the capture format has
/// one: lit where `pattern` is unlit and the reverse, everywhere in the projector image.
pub fn complement(pattern: &Pattern) -> Option<Pattern> {
    match *pattern {
        Pattern::Gray {
            axis,
            bit,
            inverted,
        } => Some(Pattern::Gray {
            axis,
            bit,
            inverted: !inverted,
        }),
        Pattern::HighFrequency { stripe, shift } if stripe > 0 => Some(Pattern::HighFrequency {
            stripe,
            shift: (shift + stripe) % (2 * stripe),
        }),
        _ => None,
    }
}

/// How one frame of a batch is obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Recipe {
    /// Rendered from its emission.
    Render,
    /// `(1 + black / white) * frame[white] - frame[of]` (indices into the batch).
    Complement { of: usize, white: usize },
}

/// The recipe of every frame of a batch: a frame is derived when the batch shows white and,
/// earlier, the frame's complement, itself rendered; every other frame is rendered.
pub fn recipes(patterns: &[Pattern]) -> Vec<Recipe> {
    let white = patterns.iter().position(|p| *p == Pattern::White);
    let mut out: Vec<Recipe> = Vec::with_capacity(patterns.len());
    for (i, p) in patterns.iter().enumerate() {
        let partner = complement(p).and_then(|c| patterns[..i].iter().position(|q| *q == c));
        let recipe = match (white, partner) {
            (Some(white), Some(of)) if out[of] == Recipe::Render => {
                Recipe::Complement { of, white }
            }
            _ => Recipe::Render,
        };
        out.push(recipe);
    }
    out
}

/// The complement of `frame` given the batch's `white`; `white_plus_black` is
/// `1 + black level / white level` of the projector's emission. Rounding can leave a value a
/// hair below zero where both are equal: those are clamped to 0 (light is never negative).
pub fn derive(
    white: &FrameRadiance,
    frame: &FrameRadiance,
    white_plus_black: f32,
) -> FrameRadiance {
    let rest = |w: f32, f: f32| (white_plus_black * w - f).max(0.0);
    FrameRadiance {
        direct: white
            .direct
            .iter()
            .zip(&frame.direct)
            .map(|(&w, &f)| rest(w, f))
            .collect(),
        global: match (&white.global, &frame.global) {
            // Without a subsurface operator neither has a global part, nor has the complement.
            (None, None) => None,
            // Either may be black (`FrameRadiance::black`): a missing part is zero.
            (w, f) => {
                let missing = if w.is_none() || f.is_none() {
                    white.direct.len()
                } else {
                    0
                };
                let zeros = vec![[0.0f32; 3]; missing];
                let (w, f) = (
                    w.as_deref().unwrap_or(&zeros),
                    f.as_deref().unwrap_or(&zeros),
                );
                Some(
                    w.iter()
                        .zip(f)
                        .map(|(w, f)| [0, 1, 2].map(|c| rest(w[c], f[c])))
                        .collect(),
                )
            }
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::booth::Booth;
    use mlsss_core::capture::Axis;
    use mlsss_core::capture::frame_plan::scan_patterns;

    /// Hand-derived: the complement is `white_plus_black * white - frame`, clamped at zero, in
    /// both parts; frames without a global part (not skin) give a complement without one, and a
    /// black frame's missing part counts as zero beside a skin frame's.
    #[test]
    fn complements_subtract_from_the_white_with_or_without_a_global_part() {
        let frame = |direct: [f32; 2], global: Option<[[f32; 3]; 2]>| FrameRadiance {
            direct: direct.to_vec(),
            global: global.map(|g| g.to_vec()),
        };
        let white = frame([1.0, 0.5], Some([[0.25, 0.5, 0.75], [0.125, 0.0, 0.25]]));
        let lit = frame([0.25, 0.5], Some([[0.125; 3], [0.0625, 0.25, 0.125]]));
        let c = derive(&white, &lit, 1.5);
        assert_eq!(c.direct, vec![1.25, 0.25]);
        assert_eq!(c.global, Some(vec![[0.25, 0.625, 1.0], [0.125, 0.0, 0.25]]));

        let board = derive(&frame([1.0, 0.5], None), &frame([0.25, 0.5], None), 1.5);
        assert_eq!((board.direct, board.global), (vec![1.25, 0.25], None));

        let against_black = derive(&white, &FrameRadiance::black(2), 1.5);
        assert_eq!(
            against_black.global,
            Some(vec![[0.375, 0.75, 1.125], [0.1875, 0.0, 0.375]])
        );
    }

    /// Property: a pattern and its complement light every projector pixel exactly once (their
    /// requested levels sum to 1), checked on every pixel of a projector image.
    #[test]
    fn a_pattern_and_its_complement_light_every_pixel_once() {
        let spec = Booth::builtin(true).patterns;
        let (w, h) = (256, 192);
        let mut checked = 0;
        for p in scan_patterns(&spec) {
            let Some(c) = complement(&p) else { continue };
            assert_eq!(complement(&c), Some(p), "{p:?}");
            for v in 0..h {
                for u in 0..w {
                    assert_eq!(p.value(u, v) + c.value(u, v), 1.0, "{p:?} at ({u}, {v})");
                }
            }
            checked += 1;
        }
        // Every Gray-code frame and every high-frequency shift has its complement.
        assert_eq!(
            checked,
            2 * (spec.gray_bits_x + spec.gray_bits_y) + spec.hf_shifts()
        );
    }

    #[test]
    fn each_pair_renders_one_and_derives_the_other_only_beside_white() {
        let g = |inverted| Pattern::Gray {
            axis: Axis::X,
            bit: 3,
            inverted,
        };
        assert_eq!(
            recipes(&[Pattern::White, g(false), g(true)]),
            vec![
                Recipe::Render,
                Recipe::Render,
                Recipe::Complement { of: 1, white: 0 }
            ]
        );
        // No white in the batch (split batches): everything is rendered.
        assert_eq!(recipes(&[g(false), g(true)]), vec![Recipe::Render; 2]);
    }
}

//! A pattern as the 8-bit pixels a projector window shows: no scaling, no colour management.
//!
//! The requested level `value` in [0, 1] becomes the 8-bit code `round(255 * value)` on all three
//! channels (the projector's own response curve is calibrated separately, DESIGN section 4), so a
//! projector pixel `(u, v)` shows exactly `Pattern::value(u, v)` quantised once.

use mlsss_core::capture::Pattern;

/// The 8-bit code of a requested level (clamped to [0, 1]).
pub fn level_code(value: f32) -> u8 {
    (value.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// A grey 8-bit code as a `0x00RRGGBB` word (softbuffer's pixel format).
pub fn grey_word(code: u8) -> u32 {
    let c = u32::from(code);
    (c << 16) | (c << 8) | c
}

/// Fills `frame` (row-major, `frame_width` x `frame_height` words) with `pattern` at the
/// projector's native `width` x `height` from the top-left corner, one frame pixel per projector
/// pixel; frame pixels outside the projector's raster are black.
pub fn rasterise(
    pattern: &Pattern,
    (width, height): (u32, u32),
    (frame_width, frame_height): (u32, u32),
    frame: &mut [u32],
) {
    for (y, row) in frame
        .chunks_exact_mut(frame_width as usize)
        .take(frame_height as usize)
        .enumerate()
    {
        let y = y as u32;
        for (x, px) in row.iter_mut().enumerate() {
            let x = x as u32;
            *px = if x < width && y < height {
                grey_word(level_code(pattern.value(x, y)))
            } else {
                0
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::capture::Axis;

    #[test]
    fn levels_quantise_to_the_nearest_code() {
        assert_eq!(level_code(0.0), 0);
        assert_eq!(level_code(1.0), 255);
        assert_eq!(level_code(0.5), 128); // 127.5 rounds away from zero
        assert_eq!(level_code(0.125), 32); // 31.875
        assert_eq!(level_code(-0.2), 0);
        assert_eq!(level_code(3.0), 255);
    }

    #[test]
    fn grey_words_repeat_the_code_on_every_channel() {
        assert_eq!(grey_word(0x7f), 0x007f_7f7f);
        assert_eq!(grey_word(255), 0x00ff_ffff);
    }

    #[test]
    fn a_frame_larger_than_the_projector_is_black_outside_its_raster() {
        // Gray bit 0 of x: columns 1 and 2 lit (gray codes 1, 3), 0 and 3 dark (0, 2).
        let pattern = Pattern::Gray {
            axis: Axis::X,
            bit: 0,
            inverted: false,
        };
        let mut frame = vec![0xdead_beef; 5 * 3];
        rasterise(&pattern, (4, 2), (5, 3), &mut frame);
        let w = 0x00ff_ffff;
        #[rustfmt::skip]
        let expected = [
            0, w, w, 0, 0,
            0, w, w, 0, 0,
            0, 0, 0, 0, 0,
        ];
        assert_eq!(frame, expected);
    }
}

//! The order of frames in a capture (DESIGN section 3). The rig, the virtual booth and every reader
//! derive the order from here.

use serde::{Deserialize, Serialize};

use super::patterns::{Axis, Pattern};
use crate::booth::PatternSpec;

/// One frame: which projector shows which pattern (all others show black).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameSpec {
    /// Position in the capture, from 0.
    pub index: u32,
    /// The lit projector, or `None` when every projector is dark.
    pub projector: Option<u8>,
    pub pattern: Pattern,
}

/// The ordered frames of a capture.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FramePlan {
    pub frames: Vec<FrameSpec>,
}

/// The patterns one projector shows during a scan, in order: white, Gray code (x bits then y bits,
/// MSB first, each followed by its inverse), slit sweep (x then y), high frequency.
pub fn scan_patterns(spec: &PatternSpec) -> Vec<Pattern> {
    let mut out = vec![Pattern::White];
    out.extend(gray_patterns(spec));
    for axis in [Axis::X, Axis::Y] {
        for k in 0..spec.slit_shifts() {
            out.push(Pattern::Slit {
                axis,
                width: spec.slit_width_px,
                period: spec.slit_period_px,
                offset: k * spec.slit_width_px,
            });
        }
    }
    for shift in 0..spec.hf_shifts() {
        out.push(Pattern::HighFrequency {
            stripe: spec.hf_stripe_px,
            shift,
        });
    }
    out
}

/// Gray-code frames: x bits then y bits, MSB first, each bit followed by its inverse.
pub fn gray_patterns(spec: &PatternSpec) -> Vec<Pattern> {
    let mut out = Vec::new();
    for (axis, bits) in [(Axis::X, spec.gray_bits_x), (Axis::Y, spec.gray_bits_y)] {
        for bit in (0..bits).rev() {
            for inverted in [false, true] {
                out.push(Pattern::Gray {
                    axis,
                    bit,
                    inverted,
                });
            }
        }
    }
    out
}

/// Grey levels shown on the calibration board for the projector response (in thousandths).
pub const RESPONSE_LEVELS_MILLI: [u32; 8] = [0, 125, 250, 375, 500, 625, 750, 875];

impl FramePlan {
    /// A scan: each projector in turn shows [`scan_patterns`] (67 frames each for the default booth).
    pub fn scan(spec: &PatternSpec, projectors: usize) -> Self {
        Self::per_projector(&scan_patterns(spec), projectors)
    }

    /// One calibration pose: each projector in turn shows white, black, its Gray code, and the
    /// grey levels used to estimate its response curve.
    pub fn calibration(spec: &PatternSpec, projectors: usize) -> Self {
        let mut patterns = vec![Pattern::White, Pattern::Black];
        patterns.extend(gray_patterns(spec));
        patterns.extend(
            RESPONSE_LEVELS_MILLI
                .iter()
                .map(|&level_milli| Pattern::Grey { level_milli }),
        );
        Self::per_projector(&patterns, projectors)
    }

    fn per_projector(patterns: &[Pattern], projectors: usize) -> Self {
        let frames = (0..projectors)
            .flat_map(|k| patterns.iter().map(move |&p| (k, p)))
            .enumerate()
            .map(|(index, (k, pattern))| FrameSpec {
                index: index as u32,
                projector: Some(k as u8),
                pattern,
            })
            .collect();
        Self { frames }
    }

    /// The frames lit by projector `k`, in capture order.
    pub fn for_projector(&self, k: u8) -> impl Iterator<Item = &FrameSpec> {
        self.frames.iter().filter(move |f| f.projector == Some(k))
    }

    /// The first frame of projector `k` showing `pattern`.
    pub fn find(&self, k: u8, pattern: &Pattern) -> Option<&FrameSpec> {
        self.for_projector(k).find(|f| &f.pattern == pattern)
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::booth::Booth;

    #[test]
    fn default_scan_has_67_frames_per_projector_in_design_order() {
        let booth = Booth::builtin(false);
        let plan = FramePlan::scan(&booth.patterns, 4);
        assert_eq!(plan.len(), 268);
        let p1: Vec<_> = plan.for_projector(1).collect();
        assert_eq!(p1.len(), 67);
        assert_eq!(p1[0].index, 67);
        assert_eq!(p1[0].pattern, Pattern::White);
        assert_eq!(
            p1[1].pattern,
            Pattern::Gray {
                axis: Axis::X,
                bit: 9,
                inverted: false
            }
        );
        assert_eq!(
            p1[2].pattern,
            Pattern::Gray {
                axis: Axis::X,
                bit: 9,
                inverted: true
            }
        );
        assert!(matches!(
            p1[21].pattern,
            Pattern::Gray {
                axis: Axis::Y,
                bit: 9,
                inverted: false
            }
        ));
        assert!(matches!(
            p1[41].pattern,
            Pattern::Slit {
                axis: Axis::X,
                offset: 0,
                ..
            }
        ));
        assert!(matches!(
            p1[51].pattern,
            Pattern::Slit {
                axis: Axis::Y,
                offset: 0,
                ..
            }
        ));
        assert!(matches!(
            p1[61].pattern,
            Pattern::HighFrequency { shift: 0, .. }
        ));
        assert!(matches!(
            p1[66].pattern,
            Pattern::HighFrequency { shift: 5, .. }
        ));
    }
}

//! Patterns named by their capture label (`Pattern::label`, as in `mlsss render` and the frame
//! file names), for showing one pattern on a projector by hand.

use crate::RigError;
use mlsss_core::booth::PatternSpec;
use mlsss_core::capture::{FramePlan, Pattern};

/// The pattern `label` names, with the booth's geometry (slit width and period, stripe width):
/// any pattern of the booth's scan or calibration plan, or `grey-N` for any level N in
/// thousandths (0..=1000).
pub fn pattern_by_label(spec: &PatternSpec, label: &str) -> Result<Pattern, RigError> {
    let planned = FramePlan::scan(spec, 1)
        .frames
        .into_iter()
        .chain(FramePlan::calibration(spec, 1).frames)
        .map(|f| f.pattern)
        .find(|p| p.label() == label);
    if let Some(pattern) = planned {
        return Ok(pattern);
    }
    label
        .strip_prefix("grey-")
        .and_then(|level| level.parse::<u32>().ok())
        .filter(|level| *level <= 1000)
        .map(|level_milli| Pattern::Grey { level_milli })
        .ok_or_else(|| RigError::UnknownPattern {
            label: label.to_owned(),
            examples: examples(spec),
        })
}

/// A few labels of each kind, for the error message.
fn examples(spec: &PatternSpec) -> String {
    let labels: Vec<String> = FramePlan::scan(spec, 1)
        .frames
        .iter()
        .map(|f| f.pattern.label())
        .collect();
    let first_of = |prefix: &str| labels.iter().find(|l| l.starts_with(prefix)).cloned();
    let mut out = vec![
        "white".to_owned(),
        "black".to_owned(),
        "grey-500".to_owned(),
    ];
    out.extend(
        ["gray-x-", "gray-y-", "slit-x-", "slit-y-", "hf-"]
            .iter()
            .filter_map(|p| first_of(p)),
    );
    out.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::booth::Booth;
    use mlsss_core::capture::Axis;

    #[test]
    fn every_scan_and_calibration_label_names_its_own_pattern() {
        let spec = Booth::builtin(true).patterns;
        let plans = [FramePlan::scan(&spec, 1), FramePlan::calibration(&spec, 1)];
        for frame in plans.iter().flat_map(|p| &p.frames) {
            let label = frame.pattern.label();
            assert_eq!(
                pattern_by_label(&spec, &label).unwrap(),
                frame.pattern,
                "{label}"
            );
        }
    }

    #[test]
    fn labels_take_the_booths_geometry() {
        let spec = Booth::builtin(true).patterns;
        assert_eq!(
            pattern_by_label(&spec, "slit-y-o0").unwrap(),
            Pattern::Slit {
                axis: Axis::Y,
                width: spec.slit_width_px,
                period: spec.slit_period_px,
                offset: 0
            }
        );
        assert_eq!(
            pattern_by_label(&spec, "grey-333").unwrap(),
            Pattern::Grey { level_milli: 333 }
        );
    }

    #[test]
    fn an_unknown_label_is_an_error_with_examples() {
        let spec = Booth::builtin(true).patterns;
        for bad in ["grey-1001", "gray-x-b99", "purple", "slit-x-o99999"] {
            let err = pattern_by_label(&spec, bad).unwrap_err().to_string();
            assert!(err.contains(bad) && err.contains("gray-x-b"), "{err}");
        }
    }
}

//! Property tests of the two readers users feed by hand, the booth file and `capture.json`
//! (issue 21): whatever a field is changed to, reading never panics, and what is accepted is
//! safe for every consumer (no division by zero, no absurd allocation, a frame plan that matches
//! the booth's).

use std::path::Path;

use proptest::prelude::*;

use crate::booth::{Booth, MAX_IMAGE_PIXELS};
use crate::capture::folder::{CaptureKind, CaptureManifest};
use crate::capture::{FramePlan, Pattern};

const QUICK_BOOTH: &str = include_str!("../../../hardware/booth-quick.toml");

/// Values a careless or hostile user writes into a numeric field.
fn hostile_number() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("0".to_owned()),
        Just("-1".to_owned()),
        Just("nan".to_owned()),
        Just("inf".to_owned()),
        Just("-inf".to_owned()),
        Just("4000000000".to_owned()),
        Just("40".to_owned()),
        Just("1e300".to_owned()),
        any::<i64>().prop_map(|v| v.to_string()),
        any::<u32>().prop_map(|v| v.to_string()),
        (-1e6f64..1e6).prop_map(|v| format!("{v:?}")),
    ]
}

/// Every `key = number` line of the booth file (the line index and key).
fn numeric_lines(text: &str) -> Vec<(usize, String)> {
    text.lines()
        .enumerate()
        .filter_map(|(i, line)| {
            let (key, value) = line.split_once(" = ")?;
            let value = value.split('#').next()?.trim();
            let numeric = value
                .chars()
                .next()
                .is_some_and(|c| c.is_ascii_digit() || c == '-')
                || value == "inf";
            numeric.then(|| (i, key.trim().to_owned()))
        })
        .collect()
}

/// The booth file with the numeric line `pick` (modulo their count) set to `value`.
fn booth_with(pick: usize, value: &str) -> String {
    let lines = numeric_lines(QUICK_BOOTH);
    let (index, key) = &lines[pick % lines.len()];
    QUICK_BOOTH
        .lines()
        .enumerate()
        .map(|(i, line)| {
            if i == *index {
                format!("{key} = {value}")
            } else {
                line.to_owned()
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// What every consumer of an accepted booth relies on.
fn assert_safe_booth(booth: &Booth) {
    let p = &booth.patterns;
    assert!(p.slit_shifts() > 0 && p.hf_shifts() > 0, "{p:?}");
    let c = &booth.camera;
    assert!(c.width as u64 * c.height as u64 <= MAX_IMAGE_PIXELS);
    let calibration = booth.calibration();
    let finite = |d: &crate::calibration::DeviceCalibration| {
        d.extrinsics
            .rotation
            .iter()
            .flatten()
            .chain(&d.extrinsics.translation)
            .all(|v| v.is_finite())
    };
    assert!(finite(&calibration.camera));
    assert!(calibration.projectors.iter().all(|p| finite(&p.device)));
    // Rasterising any pattern of the plan at a few pixels must not panic.
    for pattern in crate::capture::frame_plan::scan_patterns(p) {
        for (u, v) in [(0, 0), (7, 3), (1023, 767)] {
            let value = pattern.value(u, v);
            assert!((0.0..=1.0).contains(&value));
        }
    }
}

/// A valid manifest of the quick booth, as JSON.
fn quick_manifest_json(kind: CaptureKind) -> serde_json::Value {
    let booth = Booth::builtin(true);
    let plan = match kind {
        CaptureKind::Scan => FramePlan::scan(&booth.patterns, booth.projectors.len()),
        CaptureKind::Calibration => FramePlan::calibration(&booth.patterns, booth.projectors.len()),
    };
    serde_json::to_value(CaptureManifest::new(kind, booth, plan)).expect("manifest to JSON")
}

/// One edit of a manifest: a number somewhere set to a hostile value, two plan entries
/// swapped, or the plan cut short.
#[derive(Debug, Clone)]
enum ManifestEdit {
    Number {
        pick: usize,
        value: serde_json::Value,
    },
    Swap(usize, usize),
    Truncate(usize),
}

fn manifest_edit() -> impl Strategy<Value = ManifestEdit> {
    let number = prop_oneof![
        any::<i64>().prop_map(serde_json::Value::from),
        any::<u32>().prop_map(serde_json::Value::from),
        Just(serde_json::Value::from(0)),
        Just(serde_json::Value::from(99)),
        (-1e9f64..1e9).prop_map(serde_json::Value::from),
    ];
    prop_oneof![
        (any::<usize>(), number).prop_map(|(pick, value)| ManifestEdit::Number { pick, value }),
        (0usize..300, 0usize..300).prop_map(|(a, b)| ManifestEdit::Swap(a, b)),
        (0usize..300).prop_map(ManifestEdit::Truncate),
    ]
}

/// Every number in `value` (as mutable references), depth first.
fn numbers_mut(value: &mut serde_json::Value) -> Vec<&mut serde_json::Value> {
    match value {
        serde_json::Value::Number(_) => vec![value],
        serde_json::Value::Array(items) => items.iter_mut().flat_map(numbers_mut).collect(),
        serde_json::Value::Object(map) => map.values_mut().flat_map(numbers_mut).collect(),
        _ => Vec::new(),
    }
}

fn apply(edit: &ManifestEdit, manifest: &mut serde_json::Value) {
    match edit {
        ManifestEdit::Number { pick, value } => {
            let mut numbers = numbers_mut(manifest);
            let count = numbers.len();
            *numbers[pick % count] = value.clone();
        }
        ManifestEdit::Swap(a, b) => {
            // A plan already cut to nothing has no entries to swap.
            if let Some(frames) = manifest["plan"]["frames"].as_array_mut()
                && !frames.is_empty()
            {
                let n = frames.len();
                frames.swap(a % n, b % n);
            }
        }
        ManifestEdit::Truncate(len) => {
            if let Some(frames) = manifest["plan"]["frames"].as_array_mut() {
                frames.truncate(*len);
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn the_booth_reader_never_panics_and_accepts_only_safe_booths(
        pick in any::<usize>(),
        value in hostile_number(),
    ) {
        let text = booth_with(pick, &value);
        if let Ok(booth) = Booth::from_toml_str(&text, Path::new("booth.toml")) {
            assert_safe_booth(&booth);
        }
    }

    #[test]
    fn the_manifest_reader_never_panics_and_accepts_only_consistent_captures(
        scan in any::<bool>(),
        edits in proptest::collection::vec(manifest_edit(), 1..4),
    ) {
        let kind = if scan { CaptureKind::Scan } else { CaptureKind::Calibration };
        let mut json = quick_manifest_json(kind);
        for edit in &edits {
            apply(edit, &mut json);
        }
        let parsed: Result<CaptureManifest, _> = serde_json::from_value(json);
        if let Ok(manifest) = parsed
            && manifest.validate(Path::new("capture.json")).is_ok()
        {
            assert_safe_booth(&manifest.booth);
            prop_assert!((1..=16).contains(&manifest.bit_depth));
            for (position, frame) in manifest.plan.frames.iter().enumerate() {
                prop_assert_eq!(frame.index as usize, position);
                let k = frame.projector.map_or(0, usize::from);
                prop_assert!(k < manifest.booth.projectors.len());
                prop_assert!(frame.pattern.check_against(&manifest.booth.patterns).is_ok());
            }
        }
    }
}

#[test]
fn an_untouched_manifest_is_accepted_and_a_bit_beyond_the_code_is_dark() {
    for kind in [CaptureKind::Scan, CaptureKind::Calibration] {
        let manifest: CaptureManifest =
            serde_json::from_value(quick_manifest_json(kind)).expect("parse");
        manifest
            .validate(Path::new("capture.json"))
            .expect("valid manifest");
    }
    // `gray-x-b99` once rendered bit 3 (a shift wraps modulo 32).
    let beyond = Pattern::Gray {
        axis: crate::capture::Axis::X,
        bit: 99,
        inverted: false,
    };
    assert!((0..64).all(|u| beyond.value(u, 0) == 0.0));
    let spec = Booth::builtin(true).patterns;
    assert!(beyond.check_against(&spec).is_err());
    // Zero periods light nothing instead of dividing by zero.
    let slit = Pattern::Slit {
        axis: crate::capture::Axis::X,
        width: 3,
        period: 0,
        offset: 0,
    };
    assert_eq!(slit.value(5, 0), 0.0);
    let stripes = Pattern::HighFrequency {
        stripe: 0,
        shift: 0,
    };
    assert_eq!(stripes.value(5, 0), 0.0);
}

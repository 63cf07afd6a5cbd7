//! Number arguments that must be finite and in range (`--tolerance`, `--depth-spacing`, ...):
//! clap parses them, these refuse NaN, infinities and values out of range with the flag named.

/// A finite number > 0 (`--tolerance 1e-5`; refuses `NaN`, `inf`, 0 and negatives).
pub fn positive_finite(s: &str) -> Result<f64, String> {
    let value: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number"))?;
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(format!("must be a finite number > 0, got {s}"))
    }
}

/// A finite number >= 0 (`--noise 0`; refuses `NaN`, infinities and negatives).
pub fn non_negative_finite(s: &str) -> Result<f64, String> {
    let value = finite(s).map_err(|_| format!("must be a finite number >= 0, got {s}"))?;
    if value >= 0.0 {
        Ok(value)
    } else {
        Err(format!("must be a finite number >= 0, got {s}"))
    }
}

/// Any finite number (`--gain-db -3`; refuses `NaN` and infinities).
pub fn finite(s: &str) -> Result<f64, String> {
    let value: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number"))?;
    if value.is_finite() {
        Ok(value)
    } else {
        Err(format!("must be a finite number, got {s}"))
    }
}

/// A finite number in `range` (`--inner-band-px 4` in `3..=16`; refuses `NaN` and what lies
/// outside).
pub fn finite_in(s: &str, range: std::ops::RangeInclusive<f64>) -> Result<f64, String> {
    let value = finite(s)?;
    if range.contains(&value) {
        Ok(value)
    } else {
        Err(format!(
            "must be a number in {}..={}, got {s}",
            range.start(),
            range.end()
        ))
    }
}

/// [`positive_finite`] for `f32` arguments.
pub fn positive_finite_f32(s: &str) -> Result<f32, String> {
    let value = positive_finite(s)?;
    let narrow = value as f32;
    if narrow.is_finite() && narrow > 0.0 {
        Ok(narrow)
    } else {
        Err(format!("{s} is out of the range of a 32-bit float"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_nan_infinities_zero_and_negatives() {
        assert_eq!(positive_finite("1e-5"), Ok(1e-5));
        for bad in ["NaN", "nan", "inf", "-inf", "0", "-0.1", "abc", ""] {
            assert!(positive_finite(bad).is_err(), "{bad}");
        }
        assert!(positive_finite_f32("1e300").is_err());
        assert_eq!(positive_finite_f32("0.5"), Ok(0.5));
    }

    #[test]
    fn non_negative_accepts_zero_and_finite_accepts_negatives() {
        assert_eq!(non_negative_finite("0"), Ok(0.0));
        assert_eq!(non_negative_finite("2.5"), Ok(2.5));
        for bad in ["-1", "-1e-9", "NaN", "inf"] {
            assert!(non_negative_finite(bad).is_err(), "{bad}");
        }
        assert_eq!(finite("-3"), Ok(-3.0));
        assert_eq!(finite_in("3", 3.0..=16.0), Ok(3.0));
        assert_eq!(finite_in("16", 3.0..=16.0), Ok(16.0));
        for bad in ["2.99", "16.5", "NaN", "inf", "x"] {
            assert!(finite_in(bad, 3.0..=16.0).is_err(), "{bad}");
        }
        for bad in ["NaN", "-inf", "x"] {
            assert!(finite(bad).is_err(), "{bad}");
        }
    }
}

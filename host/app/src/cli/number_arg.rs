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
}

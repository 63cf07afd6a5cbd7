//! `WIDTHxHEIGHT` arguments (`--board 9x7`, `--projector 1024x768`), shared by the subcommands.

/// Parses `WIDTHxHEIGHT` (or `COLSxROWS`) into two positive integers.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}` is not WIDTHxHEIGHT (e.g. 1024x768 or 9x7)"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("`{v}` in `{s}` is not a positive integer"))
    };
    Ok((parse(w)?, parse(h)?))
}

#[cfg(test)]
mod tests {
    use super::parse_size;

    #[test]
    fn parses_both_separators_and_rejects_zero_and_garbage() {
        assert_eq!(parse_size("1024x768"), Ok((1024, 768)));
        assert_eq!(parse_size("9X7"), Ok((9, 7)));
        assert!(parse_size("9x0").is_err());
        assert!(parse_size("9*7").is_err());
        assert!(parse_size("ax7").is_err());
    }
}

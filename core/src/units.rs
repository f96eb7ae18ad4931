//! Values people type into flags, parsed the same way by every binary: byte sizes ("512MiB",
//! "2G": binary multiples either way) and rates ("100MiB/s").

/// A byte size.
pub fn parse_bytes(s: &str) -> Result<u64, String> {
    parse_size::Config::new()
        .with_binary()
        .parse_size(s)
        .map_err(|e| format!("{s:?} is not a byte size ({e}); try 512MiB or 2GiB"))
}

/// A bandwidth: a byte size per second, "100MiB/s" (the "/s" may be left out); never zero.
pub fn parse_rate(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let size = t.strip_suffix("/s").unwrap_or(t).trim();
    let rate = parse_bytes(size)
        .map_err(|_| format!("{s:?} is not a bandwidth; try 100MiB/s or 1GiB/s"))?;
    if rate == 0 {
        return Err(format!("bandwidth {s:?} must be more than zero"));
    }
    Ok(rate)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_rates_are_binary_and_rates_never_zero() {
        assert_eq!(parse_bytes("2MB"), Ok(2 << 20));
        assert_eq!(parse_bytes("512MiB"), Ok(512 << 20));
        assert_eq!(parse_rate("100MiB/s"), Ok(100 << 20));
        assert_eq!(parse_rate("1GiB"), Ok(1 << 30));
        assert!(parse_rate("fast").unwrap_err().contains("100MiB/s"));
        assert!(parse_rate("0/s").unwrap_err().contains("more than zero"));
    }
}

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

/// Formats a byte count for people: "512 B", "1.5 GiB".
pub fn format_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = bytes as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{bytes} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
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

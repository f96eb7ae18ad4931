//! Command-line values: human-friendly byte sizes ("512MiB", "2G", "1000000") and X,Y,Z triples.

/// Parses a byte size for clap.
pub use rayfarm_core::units::parse_bytes as bytes;

/// Formats a byte count for tables.
pub fn human(bytes: u64) -> String {
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

/// Parses "X,Y,Z" for clap (volume dimensions, camera positions).
pub fn triple<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String>
where
    T::Err: std::fmt::Display,
{
    let v: Vec<T> = s
        .split(',')
        .map(|p| p.trim().parse::<T>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    <[T; 3]>::try_from(v).map_err(|v| format!("expected X,Y,Z, got {} numbers", v.len()))
}

//! Command-line values: human-friendly byte sizes ("512MiB", "2G", "1000000") and X,Y,Z triples.

/// Parses a byte size for clap.
pub use rayfarm_core::units::parse_bytes as bytes;

/// Formats a byte count for tables.
pub use rayfarm_core::units::format_bytes as human;

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

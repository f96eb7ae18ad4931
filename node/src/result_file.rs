//! A finished job's image file as a streamed fetch sees it: its size and the checksum the
//! coordinator announces first and the client checks once every byte is in.

use std::io::Read;
use std::path::Path;

/// Size and xxh3-64 (16 hex digits) of a file, read in 1 MiB pieces.
pub fn checksum(path: &Path) -> std::io::Result<(u64, String)> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = xxhash_rust::xxh3::Xxh3Default::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut total = 0u64;
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            return Ok((total, format!("{:016x}", hasher.digest())));
        }
        hasher.update(&buf[..n]);
        total += n as u64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_checksum_is_the_xxh3_of_the_whole_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let bytes: Vec<u8> = (0..3_000_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&path, &bytes).unwrap();
        let expected = format!("{:016x}", xxhash_rust::xxh3::xxh3_64(&bytes));
        assert_eq!(checksum(&path).unwrap(), (bytes.len() as u64, expected));
    }
}

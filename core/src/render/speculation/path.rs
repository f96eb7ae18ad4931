//! The domains with geometry along a waiting ray, nearest first, as its group keeps them:
//! in the group's own record up to [`INLINE`] domains, so that most groups are one
//! allocation-free record, and reading the path while settling a verdict touches no other
//! memory (a vector per group was one more cache miss per verdict and one more allocation
//! per ray born on the worker's event loop: perf, README "Benchmarks").

use std::ops::Deref;

/// Domains held in the record itself.
const INLINE: usize = 8;

/// See the module documentation.
pub(super) enum Path {
    /// At most [`INLINE`] domains: the first `len` of `domains`.
    Inline { len: u8, domains: [u32; INLINE] },
    /// More.
    Heap(Box<[u32]>),
}

impl Default for Path {
    /// No domain.
    fn default() -> Self {
        Path::Inline {
            len: 0,
            domains: [0; INLINE],
        }
    }
}

impl From<Vec<u32>> for Path {
    fn from(path: Vec<u32>) -> Self {
        if path.len() > INLINE {
            return Path::Heap(path.into_boxed_slice());
        }
        let mut domains = [0; INLINE];
        domains[..path.len()].copy_from_slice(&path);
        Path::Inline {
            len: path.len() as u8,
            domains,
        }
    }
}

impl Deref for Path {
    type Target = [u32];

    fn deref(&self) -> &[u32] {
        match self {
            Path::Inline { len, domains } => &domains[..usize::from(*len)],
            Path::Heap(domains) => domains,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_and_long_paths_read_back_as_given() {
        for n in [0, 1, INLINE - 1, INLINE, INLINE + 1, 300] {
            let given: Vec<u32> = (0..n as u32).map(|d| d * 7 + 1).collect();
            let path = Path::from(given.clone());
            assert_eq!(&path[..], &given[..], "{n} domains");
            assert_eq!(matches!(path, Path::Heap(_)), n > INLINE);
        }
        assert!(Path::default().is_empty());
    }
}

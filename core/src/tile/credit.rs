//! Frame completion: tile credit, epochs and the coordinator's ledger.
//!
//! Every tile owns a fixed integer credit, [`TILE_CREDIT`]. Its primary rays share it
//! ([`primary_credit`]); a ray that spawns children hands its credit on to them
//! ([`split_credit`], [`split_path_credit`]); a ray that retires sends its credit back with its
//! pixel sums in one message. The coordinator's [`TileLedger`](super::ledger::TileLedger) commits a tile once all of its
//! credit is back. Credit is only ever split, never created, so the returned total can reach
//! [`TILE_CREDIT`] only after every ray of the tile has retired and reported.
//!
//! # Why no ray may hold zero credit
//!
//! Summing to the right total is not enough. Suppose a ray with credit 1 gave its children
//! `[1, 0]`. The child holding 1 may retire on a fast worker and close the tile while the child
//! holding 0 is still in flight elsewhere: the tile commits early and that child's light is
//! lost (or, worse, lands after commit in an order-dependent way). Credit is what proves "this
//! ray's result is still to come", so every ray — and every message carrying sums — must hold
//! at least 1. The splitters therefore refuse ([`CreditError::Exhausted`]) rather than hand out
//! zero, and the ledger rejects zero-credit results ([`Reject::ZeroCredit`](super::ledger::Reject::ZeroCredit)).
//!
//! A ray that both reports sums itself and spawns children counts itself as one of the parts
//! it splits into, for the same reason.
//!
//! # Why credit does not run out
//!
//! [`TILE_CREDIT`] is `2^62`. A tile holds at most `2^32` primary rays (pixel and sample are
//! `u32` in the ray record), so each primary ray starts with at least `2^30`.
//!
//! Rayfarm's ray trees are paths: at each bounce a radiance ray spawns at most one
//! continuation plus up to [`MAX_LIGHTS`] shadow rays, which never split, and may keep one
//! part for its own report. [`split_path_credit`] gives every such leaf exactly 1 and the
//! continuation the rest, so a bounce costs at most `MAX_LIGHTS + 1 = 17` credits and a path of
//! [`MAX_DEPTH`] = 64 bounces at most 1088 — far below `2^30`. An even split would not do: it
//! divides by 17 per bounce and `17^64` is far beyond 64 bits.
//!
//! [`split_credit`] (even split) is for general branching; it divides the credit by the number
//! of parts at each level, so it is safe for a handful of levels only. If a caller still runs
//! out (it gets `Err`), it must end the path there and return the credit it holds, as if
//! Russian roulette had stopped it. Credits are a deterministic function of the tree, so that
//! choice is the same in every run and the image stays bit-identical across faults.

use std::error::Error;
use std::fmt;

/// Credit carried by one tile's primary rays together. `2^62`: large enough that paths of
/// [`MAX_DEPTH`] bounces never run out (see the module docs), and small enough that two valid
/// credits can be added in a `u64` without overflow, so workers may merge results.
pub const TILE_CREDIT: u64 = 1 << 62;

/// Deepest path the credit budget is sized for.
pub const MAX_DEPTH: u32 = 64;

/// Most shadow rays one bounce may spawn that the credit budget is sized for.
pub const MAX_LIGHTS: u32 = 16;

/// Credit given to a ray that will never split (a shadow ray, or a vertex's own report).
pub const LEAF_CREDIT: u64 = 1;

/// Why credit could not be split.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CreditError {
    /// Asked to split into zero parts: the credit would vanish and the tile never complete.
    NoParts,
    /// Fewer credits than parts: some part would get zero (see the module docs).
    Exhausted {
        /// Credit that was to be split.
        credit: u64,
        /// Number of parts that each needed at least 1.
        parts: u64,
    },
    /// A primary ray index at or past the number of rays in the tile.
    IndexOutOfRange {
        /// The index asked for.
        index: u64,
        /// Number of primary rays in the tile.
        rays: u64,
    },
}

impl fmt::Display for CreditError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NoParts => write!(f, "cannot split credit into zero parts"),
            Self::Exhausted { credit, parts } => {
                write!(
                    f,
                    "credit {credit} cannot give each of {parts} parts at least 1"
                )
            }
            Self::IndexOutOfRange { index, rays } => {
                write!(
                    f,
                    "primary ray {index} out of range for a tile of {rays} rays"
                )
            }
        }
    }
}

impl Error for CreditError {}

/// Share `index` of `credit` split evenly into `parts`; part 0 also takes the remainder.
/// Callers guarantee `parts > 0` and `index < parts`.
fn even_share(credit: u64, parts: u64, index: u64) -> u64 {
    let base = credit / parts;
    if index == 0 {
        base + credit % parts
    } else {
        base
    }
}

/// Checks that `credit` can give each of `parts` at least 1.
fn check_parts(credit: u64, parts: u64) -> Result<(), CreditError> {
    if parts == 0 {
        Err(CreditError::NoParts)
    } else if credit < parts {
        Err(CreditError::Exhausted { credit, parts })
    } else {
        Ok(())
    }
}

/// Splits `credit` evenly into `parts` shares, the first also taking the remainder.
///
/// The shares sum to `credit` exactly, each is at least 1, and the result depends only on the
/// arguments. Fails rather than produce a zero share (see the module docs).
pub fn split_credit(
    credit: u64,
    parts: usize,
) -> Result<impl Iterator<Item = u64> + Clone, CreditError> {
    let parts = parts as u64;
    check_parts(credit, parts)?;
    Ok((0..parts).map(move |i| even_share(credit, parts, i)))
}

/// The share of primary ray `index` out of `rays_in_tile`, splitting `tile_credit` the way
/// [`split_credit`] does. The shares of all indices sum to `tile_credit` exactly.
pub fn primary_credit(tile_credit: u64, rays_in_tile: u64, index: u64) -> Result<u64, CreditError> {
    check_parts(tile_credit, rays_in_tile)?;
    if index >= rays_in_tile {
        return Err(CreditError::IndexOutOfRange {
            index,
            rays: rays_in_tile,
        });
    }
    Ok(even_share(tile_credit, rays_in_tile, index))
}

/// How one path vertex splits its credit: see [`split_path_credit`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PathSplit {
    /// Credit of the one child that may split again (the bounce ray).
    pub continuation: u64,
    /// Credit of each leaf (shadow rays, and the vertex's own report if it has one).
    pub leaf: u64,
}

/// Splits `credit` between `leaves` parts that will never split again, each getting
/// [`LEAF_CREDIT`], and one continuation that gets the rest.
///
/// Used at each bounce of a path so that a path costs a constant number of credits per bounce
/// instead of a constant fraction (see the module docs). Sums to `credit` exactly.
pub fn split_path_credit(credit: u64, leaves: usize) -> Result<PathSplit, CreditError> {
    let leaves = leaves as u64;
    let parts = leaves.checked_add(1).ok_or(CreditError::Exhausted {
        credit,
        parts: u64::MAX,
    })?;
    check_parts(credit, parts)?;
    Ok(PathSplit {
        continuation: credit - leaves * LEAF_CREDIT,
        leaf: LEAF_CREDIT,
    })
}

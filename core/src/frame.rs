//! Frame completion: tile credit, epochs and the coordinator's ledger.
//!
//! Every tile owns a fixed integer credit, [`TILE_CREDIT`]. Its primary rays share it
//! ([`primary_credit`]); a ray that spawns children hands its credit on to them
//! ([`split_credit`], [`split_path_credit`]); a ray that retires sends its credit back with its
//! pixel sums in one message. The coordinator's [`FrameLedger`] commits a tile once all of its
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
//! zero, and the ledger rejects zero-credit results ([`Reject::ZeroCredit`]).
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

/// Tile side in pixels: the unit of credit, epochs and results.
pub const TILE_SIZE: u32 = 32;

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

/// A run of consecutive samples of every pixel: a progressive subframe's, or a whole frame's.
/// Sample numbers are the frame's own (the random numbers hash them), so the same sample
/// renders the same light whichever run it is in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Samples {
    /// The run's first sample.
    pub first: u32,
    /// Samples in the run (at least 1 in a frame).
    pub count: u32,
}

impl Samples {
    /// All `spp` samples of a frame rendered in one pass.
    pub fn all(spp: u32) -> Self {
        Samples {
            first: 0,
            count: spp,
        }
    }

    /// One past the run's last sample.
    pub fn end(&self) -> u32 {
        self.first.saturating_add(self.count)
    }

    /// The run's sample numbers.
    pub fn range(&self) -> std::ops::Range<u32> {
        self.first..self.end()
    }

    /// Where `sample` falls in the run (its index among the run's samples of a pixel).
    pub fn offset(&self, sample: u32) -> Option<u32> {
        self.range().contains(&sample).then(|| sample - self.first)
    }
}

/// How the image is cut into square tiles, numbered row-major; edge tiles may be smaller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    width: u32,
    height: u32,
    tile_size: u32,
    tiles_x: u32,
    tiles_y: u32,
}

impl TileGrid {
    /// A grid of `tile_size`-pixel tiles over a `width` x `height` image. `None` if any
    /// argument is zero or the pixel or tile count does not fit in a `u32` (the ray record's
    /// pixel and tile fields are `u32`).
    pub fn new(width: u32, height: u32, tile_size: u32) -> Option<Self> {
        if width == 0 || height == 0 || tile_size == 0 {
            return None;
        }
        width.checked_mul(height)?;
        let tiles_x = width.div_ceil(tile_size);
        let tiles_y = height.div_ceil(tile_size);
        tiles_x.checked_mul(tiles_y)?;
        Some(Self {
            width,
            height,
            tile_size,
            tiles_x,
            tiles_y,
        })
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Side of a full tile in pixels.
    pub fn tile_size(&self) -> u32 {
        self.tile_size
    }

    /// Tiles per row of tiles.
    pub fn tiles_x(&self) -> u32 {
        self.tiles_x
    }

    /// Rows of tiles.
    pub fn tiles_y(&self) -> u32 {
        self.tiles_y
    }

    /// Number of pixels in the image.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Number of tiles.
    pub fn count(&self) -> u32 {
        self.tiles_x * self.tiles_y
    }

    /// The tile holding `pixel` (`y * width + x`), or `None` if it is outside the image.
    pub fn tile_of(&self, pixel: u32) -> Option<u32> {
        let (x, y) = self.xy(pixel)?;
        Some((y / self.tile_size) * self.tiles_x + x / self.tile_size)
    }

    /// Pixel rectangle `(x0, y0, x1, y1)`, end-exclusive, of `tile`.
    fn rect(&self, tile: u32) -> Option<(u32, u32, u32, u32)> {
        if tile >= self.count() {
            return None;
        }
        let x0 = (tile % self.tiles_x) * self.tile_size;
        let y0 = (tile / self.tiles_x) * self.tile_size;
        let x1 = x0.saturating_add(self.tile_size).min(self.width);
        let y1 = y0.saturating_add(self.tile_size).min(self.height);
        Some((x0, y0, x1, y1))
    }

    fn xy(&self, pixel: u32) -> Option<(u32, u32)> {
        let (x, y) = (pixel % self.width, pixel / self.width);
        (y < self.height).then_some((x, y))
    }

    /// The pixels of `tile`, row by row; empty if there is no such tile.
    pub fn pixels(&self, tile: u32) -> impl Iterator<Item = u32> + '_ {
        let (x0, y0, x1, y1) = self.rect(tile).unwrap_or((0, 0, 0, 0));
        (y0..y1).flat_map(move |y| (x0..x1).map(move |x| y * self.width + x))
    }

    /// Number of pixels in `tile` (0 if there is no such tile).
    pub fn tile_pixel_count(&self, tile: u32) -> usize {
        self.rect(tile)
            .map_or(0, |(x0, y0, x1, y1)| ((x1 - x0) * (y1 - y0)) as usize)
    }

    /// Position of `pixel` in [`pixels`](Self::pixels)`(tile)`, or `None` if it is not in
    /// that tile.
    pub fn local_index(&self, tile: u32, pixel: u32) -> Option<usize> {
        let (x0, y0, x1, y1) = self.rect(tile)?;
        let (x, y) = self.xy(pixel)?;
        let inside = (x0..x1).contains(&x) && (y0..y1).contains(&y);
        inside.then(|| ((y - y0) * (x1 - x0) + (x - x0)) as usize)
    }
}

/// What became of an accepted tile result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accept {
    /// It belongs to an epoch the tile has left: ignored, nothing changed.
    Stale,
    /// Counted; the tile still waits for more credit.
    Pending,
    /// Counted, and it brought the last of the tile's credit: the tile is committed.
    Completed,
}

/// Why a tile result was refused. Each means a bug or a hostile peer; the ledger is unchanged.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reject {
    /// No tile with this number.
    UnknownTile {
        /// The tile named.
        tile: u32,
    },
    /// An epoch the coordinator has not issued yet.
    FutureEpoch {
        /// The tile named.
        tile: u32,
        /// The epoch named.
        epoch: u32,
        /// The tile's current epoch.
        current: u32,
    },
    /// Zero credit proves nothing about what is still in flight (see the module docs).
    ZeroCredit {
        /// The tile named.
        tile: u32,
    },
    /// More credit than the tile has outstanding (includes results for a committed tile).
    Overflow {
        /// The tile named.
        tile: u32,
        /// Credit already returned in this epoch.
        returned: u64,
        /// Credit the result carried.
        credit: u64,
        /// The tile's total credit.
        tile_credit: u64,
    },
    /// More credit than the pixels the result names can hold: credit without the sums it
    /// stands for (see [`FrameLedger::with_samples`]).
    Uncovered {
        /// The tile named.
        tile: u32,
        /// Credit the result carried.
        credit: u64,
        /// Distinct pixels the result named.
        pixels: usize,
        /// Most credit those pixels' rays hold together.
        bound: u64,
    },
    /// A pixel outside the tile.
    ForeignPixel {
        /// The tile named.
        tile: u32,
        /// The offending pixel.
        pixel: u32,
    },
}

impl fmt::Display for Reject {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::UnknownTile { tile } => write!(f, "result for unknown tile {tile}"),
            Self::FutureEpoch {
                tile,
                epoch,
                current,
            } => write!(
                f,
                "result for tile {tile} names epoch {epoch}, but the current epoch is {current}"
            ),
            Self::ZeroCredit { tile } => write!(f, "result for tile {tile} carries zero credit"),
            Self::Overflow {
                tile,
                returned,
                credit,
                tile_credit,
            } => write!(
                f,
                "result for tile {tile} returns {credit} credit with {returned} of \
                 {tile_credit} already back: more than was issued"
            ),
            Self::Uncovered {
                tile,
                credit,
                pixels,
                bound,
            } => write!(
                f,
                "result for tile {tile} returns {credit} credit but names {pixels} pixels, \
                 whose rays hold at most {bound}: credit without the sums it stands for"
            ),
            Self::ForeignPixel { tile, pixel } => {
                write!(f, "result for tile {tile} adds to pixel {pixel} outside it")
            }
        }
    }
}

impl Error for Reject {}

/// One tile's state in the ledger.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
struct TileState {
    epoch: u32,
    returned: u64,
    done: bool,
    /// Fixed-point sums per pixel of the tile, in [`TileGrid::pixels`] order. Empty until the
    /// first result, so tiles without results cost no memory.
    sums: Vec<[i64; 3]>,
}

/// The coordinator's record of which tiles are complete, per tile epoch, returned credit and
/// fixed-point pixel sums.
///
/// Sums are added with wrapping integer arithmetic: it is associative and commutative, so the
/// committed sums do not depend on the order results arrive in.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameLedger {
    grid: TileGrid,
    tile_credit: u64,
    tiles: Vec<TileState>,
    done: u32,
    /// Samples per pixel, when results must name the pixels their credit came from.
    spp: Option<u32>,
}

impl FrameLedger {
    /// A ledger with every tile at epoch 0 and nothing returned.
    ///
    /// # Panics
    /// If `tile_credit` is zero: no result could ever complete a tile.
    pub fn new(grid: TileGrid, tile_credit: u64) -> Self {
        assert!(tile_credit > 0, "tile credit must be positive");
        Self {
            grid,
            tile_credit,
            tiles: vec![TileState::default(); grid.count() as usize],
            done: 0,
            spp: None,
        }
    }

    /// Also refuses results whose credit is more than the rays of the pixels they name can
    /// hold ([`Reject::Uncovered`]), for frames of `spp` samples per pixel whose primary rays
    /// got [`primary_credit`] in pixel-major order (index `local pixel * spp + sample`).
    ///
    /// Why this is sound: every retiring ray names its pixel in its result (with zero sums if
    /// it added no light), and credit moves only with rays, which keep their pixel across
    /// splits and peer transfers. So the credit of any result is at most the credit its
    /// pixels' primary rays started with. A result of a whole tile's credit and no pixels,
    /// the forgery that would end a tile with nothing rendered, is refused.
    pub fn with_samples(mut self, spp: u32) -> Self {
        self.spp = Some(spp);
        self
    }

    /// Every tile starts at `epoch` instead of 0: a progressive frame's next subframe starts
    /// above every epoch the last one used, so nothing of it is taken for the new one's.
    pub fn starting_at(mut self, epoch: u32) -> Self {
        for t in &mut self.tiles {
            t.epoch = epoch;
        }
        self
    }

    /// Most credit the rays of `pixels` distinct pixels at the start of `tile` can hold, or
    /// `None` when no bound applies.
    fn pixel_bound(&self, tile: u32, locals: &[usize]) -> Option<(usize, u64)> {
        let spp = u64::from(self.spp?);
        let rays = self.grid.tile_pixel_count(tile) as u64 * spp;
        if rays == 0 || spp == 0 {
            return None;
        }
        let mut distinct = locals.to_vec();
        distinct.sort_unstable();
        distinct.dedup();
        let base = self.tile_credit / rays;
        // Index 0 (the first sample of local pixel 0) also takes the remainder.
        let first = distinct.first() == Some(&0);
        let bound = (distinct.len() as u64)
            .saturating_mul(spp)
            .saturating_mul(base)
            .saturating_add(if first { self.tile_credit % rays } else { 0 });
        Some((distinct.len(), bound))
    }

    /// The grid the ledger tracks.
    pub fn grid(&self) -> &TileGrid {
        &self.grid
    }

    /// Credit each tile must get back to complete.
    pub fn tile_credit(&self) -> u64 {
        self.tile_credit
    }

    /// Records a retired ray's (or a batch's) result for `tile` at `epoch`: `credit` returned
    /// and fixed-point `sums` added per pixel.
    ///
    /// Results of an older epoch are ignored. Anything malformed is refused with the ledger
    /// untouched: everything is checked before anything is changed.
    pub fn accept(
        &mut self,
        tile: u32,
        epoch: u32,
        credit: u64,
        sums: &[(u32, [i64; 3])],
    ) -> Result<Accept, Reject> {
        let state = self
            .tiles
            .get(tile as usize)
            .ok_or(Reject::UnknownTile { tile })?;
        if epoch < state.epoch {
            return Ok(Accept::Stale);
        }
        let returned = self.check(tile, epoch, credit, state)?;
        let locals = self.local_indices(tile, sums)?;
        if let Some((pixels, bound)) = self.pixel_bound(tile, &locals)
            && credit > bound
        {
            return Err(Reject::Uncovered {
                tile,
                credit,
                pixels,
                bound,
            });
        }
        Ok(self.commit(tile, returned, &locals, sums))
    }

    /// Checks epoch and credit of a result that is not stale; returns the new returned total.
    fn check(&self, tile: u32, epoch: u32, credit: u64, state: &TileState) -> Result<u64, Reject> {
        if epoch > state.epoch {
            return Err(Reject::FutureEpoch {
                tile,
                epoch,
                current: state.epoch,
            });
        }
        if credit == 0 {
            return Err(Reject::ZeroCredit { tile });
        }
        let overflow = Reject::Overflow {
            tile,
            returned: state.returned,
            credit,
            tile_credit: self.tile_credit,
        };
        match state.returned.checked_add(credit) {
            Some(total) if total <= self.tile_credit => Ok(total),
            _ => Err(overflow),
        }
    }

    /// Maps each summed pixel to its place in the tile, refusing pixels outside it.
    fn local_indices(&self, tile: u32, sums: &[(u32, [i64; 3])]) -> Result<Vec<usize>, Reject> {
        sums.iter()
            .map(|&(pixel, _)| {
                self.grid
                    .local_index(tile, pixel)
                    .ok_or(Reject::ForeignPixel { tile, pixel })
            })
            .collect()
    }

    /// Applies a result already checked by [`accept`](Self::accept).
    fn commit(
        &mut self,
        tile: u32,
        returned: u64,
        locals: &[usize],
        sums: &[(u32, [i64; 3])],
    ) -> Accept {
        let pixels = self.grid.tile_pixel_count(tile);
        let state = &mut self.tiles[tile as usize];
        if state.sums.is_empty() && !sums.is_empty() {
            state.sums = vec![[0; 3]; pixels];
        }
        for (&local, (_, add)) in locals.iter().zip(sums) {
            let acc = &mut state.sums[local];
            for (a, b) in acc.iter_mut().zip(add) {
                *a = a.wrapping_add(*b);
            }
        }
        state.returned = returned;
        if returned == self.tile_credit {
            state.done = true;
            self.done += 1;
            Accept::Completed
        } else {
            Accept::Pending
        }
    }

    /// Starts a new epoch for each unfinished tile in `tiles`: its returned credit and partial
    /// sums are dropped, and results of the old epoch will be ignored from now on. Finished,
    /// unknown and repeated tiles are skipped. Returns each bumped tile with its new epoch, in
    /// ascending tile order, for re-issuing its primary rays.
    ///
    /// # Panics
    /// If a tile's epoch would pass `u32::MAX` (four billion faults on one tile).
    pub fn bump(&mut self, tiles: &[u32]) -> Vec<(u32, u32)> {
        let mut tiles = tiles.to_vec();
        tiles.sort_unstable();
        tiles.dedup();
        tiles
            .into_iter()
            .filter_map(|tile| Some((tile, self.bump_one(tile)?)))
            .collect()
    }

    fn bump_one(&mut self, tile: u32) -> Option<u32> {
        let state = self.tiles.get_mut(tile as usize).filter(|s| !s.done)?;
        state.epoch = state.epoch.checked_add(1).expect("tile epoch overflow");
        state.returned = 0;
        // Free the memory too: a tile bumped after a fault may wait long for its re-run.
        state.sums = Vec::new();
        Some(state.epoch)
    }

    /// The tiles not yet complete, ascending.
    pub fn unfinished(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.grid.count()).filter(|&t| !self.tiles[t as usize].done)
    }

    /// Current epoch of `tile`, or `None` if there is no such tile.
    pub fn epoch(&self, tile: u32) -> Option<u32> {
        self.tiles.get(tile as usize).map(|s| s.epoch)
    }

    /// Credit returned to `tile` in its current epoch, or `None` if there is no such tile.
    pub fn returned(&self, tile: u32) -> Option<u64> {
        self.tiles.get(tile as usize).map(|s| s.returned)
    }

    /// Whether `tile` is committed (`false` for unknown tiles).
    pub fn is_tile_done(&self, tile: u32) -> bool {
        self.tiles.get(tile as usize).is_some_and(|s| s.done)
    }

    /// Number of committed tiles.
    pub fn tiles_done(&self) -> u32 {
        self.done
    }

    /// Whether every tile is committed.
    pub fn is_complete(&self) -> bool {
        self.done == self.grid.count()
    }

    /// Takes the fixed-point sums of a committed tile, in [`TileGrid::pixels`] order, out of
    /// the ledger (to the film file), so memory holds only the tiles in flight. Empty for a
    /// tile that got no light, is not committed, or was taken before.
    pub fn take_sums(&mut self, tile: u32) -> Vec<[i64; 3]> {
        match self.tiles.get_mut(tile as usize) {
            Some(state) if state.done => std::mem::take(&mut state.sums),
            _ => Vec::new(),
        }
    }

    /// Committed fixed-point sums (not yet taken) for the whole image, indexed by pixel;
    /// pixels of unfinished tiles are zero, since their partial sums may still be dropped.
    pub fn image_sums(&self) -> Vec<[i64; 3]> {
        let mut image = vec![[0; 3]; self.grid.pixel_count()];
        for (tile, state) in (0..).zip(&self.tiles) {
            if !state.done || state.sums.is_empty() {
                continue;
            }
            for (pixel, sum) in self.grid.pixels(tile).zip(&state.sums) {
                image[pixel as usize] = *sum;
            }
        }
        image
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn grid() -> TileGrid {
        TileGrid::new(5, 3, 2).unwrap()
    }

    // ---- credit splitting ----

    #[test]
    fn split_is_exact_and_never_zero() {
        for (credit, parts) in [(10, 3), (3, 3), (u64::MAX, 7), (TILE_CREDIT, 17), (1, 1)] {
            let shares: Vec<u64> = split_credit(credit, parts).unwrap().collect();
            assert_eq!(shares.len(), parts);
            assert_eq!(
                shares.iter().map(|&s| u128::from(s)).sum::<u128>(),
                credit.into()
            );
            assert!(shares.iter().all(|&s| s >= 1));
        }
        assert_eq!(split_credit(10, 3).unwrap().collect::<Vec<_>>(), [4, 3, 3]);
    }

    #[test]
    fn split_refuses_zero_shares_and_zero_parts() {
        assert_eq!(
            split_credit(2, 3).err(),
            Some(CreditError::Exhausted {
                credit: 2,
                parts: 3
            })
        );
        assert_eq!(split_credit(5, 0).err(), Some(CreditError::NoParts));
        assert_eq!(
            split_credit(0, 1).err(),
            Some(CreditError::Exhausted {
                credit: 0,
                parts: 1
            })
        );
    }

    #[test]
    fn primary_credit_sums_to_tile_credit() {
        let rays = 1000;
        let total: u64 = (0..rays)
            .map(|i| primary_credit(TILE_CREDIT, rays, i).unwrap())
            .sum();
        assert_eq!(total, TILE_CREDIT);
        assert_eq!(
            primary_credit(TILE_CREDIT, rays, rays),
            Err(CreditError::IndexOutOfRange { index: rays, rays })
        );
        assert_eq!(primary_credit(TILE_CREDIT, 0, 0), Err(CreditError::NoParts));
    }

    #[test]
    fn deepest_path_from_poorest_primary_never_runs_out() {
        // The largest tile the ray record can name has 2^32 primary rays.
        let rays = 1u64 << 32;
        let mut credit = primary_credit(TILE_CREDIT, rays, rays - 1).unwrap();
        let mut returned = 0;
        for _ in 0..MAX_DEPTH {
            // MAX_LIGHTS shadow rays plus the vertex's own report.
            let leaves = MAX_LIGHTS as usize + 1;
            let split = split_path_credit(credit, leaves).unwrap();
            returned += split.leaf * leaves as u64;
            credit = split.continuation;
        }
        assert!(credit >= 1 << 29);
        assert_eq!(returned + credit, TILE_CREDIT / rays);
    }

    #[test]
    fn path_split_is_exact_and_refuses_exhaustion() {
        let s = split_path_credit(20, 4).unwrap();
        assert_eq!(s.continuation + 4 * s.leaf, 20);
        assert_eq!(
            split_path_credit(4, 4),
            Err(CreditError::Exhausted {
                credit: 4,
                parts: 5
            })
        );
        assert_eq!(split_path_credit(5, 4).unwrap().continuation, 1);
    }

    // ---- tile grid ----

    #[test]
    fn grid_partitions_the_image() {
        let g = grid();
        assert_eq!(g.count(), 6);
        let mut seen = vec![0; g.pixel_count()];
        for tile in 0..g.count() {
            assert_eq!(g.pixels(tile).count(), g.tile_pixel_count(tile));
            for (i, p) in g.pixels(tile).enumerate() {
                seen[p as usize] += 1;
                assert_eq!(g.tile_of(p), Some(tile));
                assert_eq!(g.local_index(tile, p), Some(i));
            }
        }
        assert!(seen.iter().all(|&n| n == 1));
        assert_eq!(g.pixels(2).collect::<Vec<_>>(), [4, 9]);
        assert_eq!(g.tile_of(15), None);
        assert_eq!(g.local_index(0, 4), None);
        assert_eq!(g.pixels(6).count(), 0);
    }

    #[test]
    fn grid_rejects_degenerate_sizes() {
        assert!(TileGrid::new(0, 3, 2).is_none());
        assert!(TileGrid::new(3, 3, 0).is_none());
        assert!(TileGrid::new(1 << 16, 1 << 16, 8).is_none());
    }

    // ---- ledger ----

    #[test]
    fn tile_completes_when_all_credit_is_back() {
        let mut l = FrameLedger::new(grid(), 10);
        assert_eq!(l.accept(0, 0, 4, &[(0, [1, 2, 3])]), Ok(Accept::Pending));
        assert!(!l.is_tile_done(0));
        assert_eq!(l.accept(0, 0, 6, &[(0, [1, 0, 0])]), Ok(Accept::Completed));
        assert!(l.is_tile_done(0));
        assert_eq!(l.tiles_done(), 1);
        assert_eq!(l.image_sums()[0], [2, 2, 3]);
    }

    #[test]
    fn frame_completes_when_every_tile_does() {
        let mut l = FrameLedger::new(grid(), 1);
        for tile in 0..6 {
            assert!(!l.is_complete());
            assert_eq!(l.accept(tile, 0, 1, &[]), Ok(Accept::Completed));
        }
        assert!(l.is_complete());
        assert_eq!(l.unfinished().count(), 0);
    }

    #[test]
    fn stale_results_are_ignored() {
        let mut l = FrameLedger::new(grid(), 10);
        l.accept(1, 0, 3, &[(2, [5, 5, 5])]).unwrap();
        assert_eq!(l.bump(&[1]), [(1, 1)]);
        let before = l.clone();
        assert_eq!(l.accept(1, 0, 7, &[(2, [1, 1, 1])]), Ok(Accept::Stale));
        // Even a malformed stale result is simply dropped.
        assert_eq!(
            l.accept(1, 0, u64::MAX, &[(0, [1, 1, 1])]),
            Ok(Accept::Stale)
        );
        assert_eq!(l, before);
    }

    #[test]
    fn malformed_results_leave_the_ledger_unchanged() {
        let mut l = FrameLedger::new(grid(), 10);
        l.accept(0, 0, 9, &[(0, [1, 1, 1])]).unwrap();
        let before = l.clone();
        let cases = [
            (0, 0, 2, vec![(0, [7, 7, 7])]),
            (0, 0, u64::MAX, vec![]),
            (0, 1, 1, vec![]),
            (0, 0, 0, vec![(0, [7, 7, 7])]),
            (0, 0, 1, vec![(1, [7, 7, 7]), (2, [7, 7, 7])]),
            (6, 0, 1, vec![]),
        ];
        for (tile, epoch, credit, sums) in cases {
            let err = l.accept(tile, epoch, credit, &sums).unwrap_err();
            assert!(!err.to_string().is_empty());
            assert_eq!(l, before, "{err}");
        }
        assert!(matches!(
            l.accept(0, 0, 2, &[]),
            Err(Reject::Overflow { returned: 9, .. })
        ));
    }

    #[test]
    fn committed_tile_refuses_more_credit() {
        let mut l = FrameLedger::new(grid(), 1);
        l.accept(0, 0, 1, &[]).unwrap();
        assert!(matches!(
            l.accept(0, 0, 1, &[]),
            Err(Reject::Overflow { .. })
        ));
    }

    #[test]
    fn bump_resets_unfinished_and_spares_finished() {
        let mut l = FrameLedger::new(grid(), 10);
        l.accept(0, 0, 10, &[(0, [1, 1, 1])]).unwrap();
        l.accept(1, 0, 4, &[(2, [2, 2, 2])]).unwrap();
        assert_eq!(l.bump(&[1, 0, 1, 99]), [(1, 1)]);
        assert_eq!((l.epoch(0), l.epoch(1)), (Some(0), Some(1)));
        assert_eq!(l.returned(1), Some(0));
        assert!(l.is_tile_done(0));
        // The dropped partial sum must not reappear once the tile completes.
        l.accept(1, 1, 10, &[(3, [3, 3, 3])]).unwrap();
        let image = l.image_sums();
        assert_eq!((image[0], image[2], image[3]), ([1; 3], [0; 3], [3; 3]));
    }

    #[test]
    fn taken_sums_leave_the_ledger_once() {
        let mut l = FrameLedger::new(grid(), 2);
        l.accept(0, 0, 1, &[(0, [1, 2, 3])]).unwrap();
        assert!(l.take_sums(0).is_empty(), "not committed yet");
        l.accept(0, 0, 1, &[(1, [4, 5, 6])]).unwrap();
        assert_eq!(l.take_sums(0), vec![[1, 2, 3], [4, 5, 6], [0; 3], [0; 3]]);
        assert!(l.take_sums(0).is_empty());
        assert!(l.take_sums(99).is_empty());
        assert!(l.is_tile_done(0));
    }

    #[test]
    fn image_sums_hold_only_committed_tiles() {
        let mut l = FrameLedger::new(grid(), 10);
        l.accept(0, 0, 5, &[(0, [1, 1, 1])]).unwrap();
        assert!(l.image_sums().iter().all(|s| *s == [0; 3]));
    }

    // ---- simulated frames ----

    /// Small deterministic generator (splitmix64) so ray trees depend only on their seed.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }

        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }

        fn shuffle<T>(&mut self, items: &mut [T]) {
            for i in (1..items.len()).rev() {
                items.swap(i, self.below(i as u64 + 1) as usize);
            }
        }
    }

    #[test]
    fn credit_beyond_what_the_named_pixels_hold_is_refused() {
        // 2x1 pixels in one tile, 2 samples: 4 primary rays of 10 credit each (41 in all,
        // the first ray takes the remainder 1).
        let g = TileGrid::new(2, 1, 2).unwrap();
        let mut l = FrameLedger::new(g, 41).with_samples(2);
        let forged = l.accept(0, 0, 41, &[]);
        assert_eq!(
            forged,
            Err(Reject::Uncovered {
                tile: 0,
                credit: 41,
                pixels: 0,
                bound: 0
            })
        );
        // Pixel 1 holds 2 x 10; pixel 0 holds 21 with the remainder.
        assert!(matches!(
            l.accept(0, 0, 21, &[(1, [0; 3])]),
            Err(Reject::Uncovered { bound: 20, .. })
        ));
        assert_eq!(l.accept(0, 0, 20, &[(1, [0; 3])]), Ok(Accept::Pending));
        assert_eq!(l.accept(0, 0, 21, &[(0, [5; 3])]), Ok(Accept::Completed));
    }

    /// A retired ray's message to the coordinator.
    #[derive(Clone, Debug)]
    struct Msg {
        tile: u32,
        epoch: u32,
        credit: u64,
        sums: Vec<(u32, [i64; 3])>,
    }

    const MAX_TREE_DEPTH: u32 = 3;

    /// Traces one ray: it reports, splits among up to 5 children, or both.
    fn trace(ray: &Msg, pixel: u32, depth: u32, rng: &mut Rng, out: &mut Vec<Msg>) {
        let children = if depth >= MAX_TREE_DEPTH || rng.below(2) == 0 {
            0
        } else {
            1 + rng.below(5) as usize
        };
        let light = [0, 1, 2].map(|_| rng.below(1000) as i64 - 500);
        let reports = children == 0 || rng.below(2) == 0;
        let mut shares = split_credit(ray.credit, children + usize::from(reports)).unwrap();
        if reports {
            // A ray that adds no light still names its pixel (as workers do), so the
            // ledger's pixel bound holds.
            let sums = if rng.below(4) == 0 {
                vec![(pixel, [0; 3])]
            } else {
                vec![(pixel, light)]
            };
            let credit = shares.next().unwrap();
            out.push(Msg {
                credit,
                sums,
                ..ray.clone()
            });
        }
        for credit in shares {
            trace(
                &Msg {
                    credit,
                    ..ray.clone()
                },
                pixel,
                depth + 1,
                rng,
                out,
            );
        }
    }

    /// All result messages of one tile at `epoch`. The trees depend on `seed`, tile and ray
    /// only, never the epoch: rendering is deterministic.
    fn trace_tile(g: &TileGrid, tile: u32, epoch: u32, spp: u32, seed: u64) -> Vec<Msg> {
        let rays = g.tile_pixel_count(tile) as u64 * u64::from(spp);
        let mut out = Vec::new();
        for (i, pixel) in g.pixels(tile).enumerate() {
            for s in 0..u64::from(spp) {
                let index = i as u64 * u64::from(spp) + s;
                let credit = primary_credit(TILE_CREDIT, rays, index).unwrap();
                let mut rng = Rng(seed ^ (u64::from(tile) << 40) ^ index);
                let ray = Msg {
                    tile,
                    epoch,
                    credit,
                    sums: vec![],
                };
                trace(&ray, pixel, 0, &mut rng, &mut out);
            }
        }
        out
    }

    /// Delivers `msgs` in order, checking each verdict: stale exactly when its epoch is old,
    /// and a tile completes on its last current-epoch message and not a moment before.
    fn deliver(l: &mut FrameLedger, msgs: &[Msg], pending: &mut [usize]) {
        for m in msgs {
            let current = l.epoch(m.tile).unwrap();
            let expected = if m.epoch < current {
                Accept::Stale
            } else {
                assert!(!l.is_tile_done(m.tile), "tile {} committed early", m.tile);
                pending[m.tile as usize] -= 1;
                match pending[m.tile as usize] {
                    0 => Accept::Completed,
                    _ => Accept::Pending,
                }
            };
            assert_eq!(l.accept(m.tile, m.epoch, m.credit, &m.sums), Ok(expected));
        }
    }

    /// Number of messages per tile that belong to the tile's current epoch.
    fn current_counts(l: &FrameLedger, msgs: &[Msg]) -> Vec<usize> {
        let mut counts = vec![0; l.grid().count() as usize];
        for m in msgs.iter().filter(|m| Some(m.epoch) == l.epoch(m.tile)) {
            counts[m.tile as usize] += 1;
        }
        counts
    }

    fn trace_frame(g: &TileGrid, spp: u32, seed: u64) -> Vec<Msg> {
        (0..g.count())
            .flat_map(|t| trace_tile(g, t, 0, spp, seed))
            .collect()
    }

    fn clean_run(g: TileGrid, spp: u32, seed: u64, order: &mut Rng) -> Vec<[i64; 3]> {
        let mut msgs = trace_frame(&g, spp, seed);
        order.shuffle(&mut msgs);
        let mut l = FrameLedger::new(g, TILE_CREDIT).with_samples(spp);
        let mut pending = current_counts(&l, &msgs);
        deliver(&mut l, &msgs, &mut pending);
        assert!(l.is_complete());
        l.image_sums()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn frame_with_fault_commits_exactly_and_matches_clean_run(
            width in 1u32..9, height in 1u32..9, tile_size in 1u32..5, spp in 1u32..3,
            seed: u64, order_seed: u64, cut_permille in 0u64..1000, bump_mask: u64,
        ) {
            let g = TileGrid::new(width, height, tile_size).unwrap();
            let mut order = Rng(order_seed);
            let clean = clean_run(g, spp, seed, &mut order);

            // Epoch 0 is cut short by a fault after a random prefix.
            let mut first = trace_frame(&g, spp, seed);
            order.shuffle(&mut first);
            let mut l = FrameLedger::new(g, TILE_CREDIT).with_samples(spp);
            let mut pending = current_counts(&l, &first);
            let cut = first.len() * cut_permille as usize / 1000;
            deliver(&mut l, &first[..cut], &mut pending);

            // Bump a random set of tiles, finished ones included: those must be untouched.
            let chosen: Vec<u32> = (0..g.count()).filter(|t| bump_mask >> (t % 64) & 1 == 1).collect();
            let done_before: Vec<bool> = (0..g.count()).map(|t| l.is_tile_done(t)).collect();
            let bumped = l.bump(&chosen);
            let expect_bumped: Vec<(u32, u32)> =
                chosen.iter().filter(|&&t| !done_before[t as usize]).map(|&t| (t, 1)).collect();
            prop_assert_eq!(&bumped, &expect_bumped);

            // The rest of epoch 0, the re-run of bumped tiles, and duplicated stale results.
            let mut rest = first[cut..].to_vec();
            for &(tile, epoch) in &bumped {
                rest.extend(trace_tile(&g, tile, epoch, spp, seed));
                let stale = first[..cut].iter().filter(|m| m.tile == tile);
                rest.extend(stale.filter(|_| order.below(2) == 0).cloned());
            }
            order.shuffle(&mut rest);
            let mut pending = current_counts(&l, &rest);
            deliver(&mut l, &rest, &mut pending);

            prop_assert!(l.is_complete());
            prop_assert_eq!(l.image_sums(), clean);
        }

        #[test]
        fn split_credit_is_exact_and_positive(credit: u64, parts in 1usize..64) {
            match split_credit(credit, parts) {
                Ok(shares) => {
                    let shares: Vec<u64> = shares.collect();
                    prop_assert!(shares.iter().all(|&s| s >= 1));
                    prop_assert_eq!(shares.iter().map(|&s| u128::from(s)).sum::<u128>(), u128::from(credit));
                }
                Err(e) => prop_assert!(credit < parts as u64, "{}", e),
            }
        }

        #[test]
        fn overflow_attempt_leaves_state_unchanged(
            first in 1u64..1000, extra in 1u64..1000, pixel in 0u32..15,
        ) {
            let g = grid();
            let tile = g.tile_of(pixel).unwrap();
            let mut l = FrameLedger::new(g, 1000);
            let first = first.min(999);
            l.accept(tile, 0, first, &[(pixel, [1, 2, 3])]).unwrap();
            let before = l.clone();
            let too_much = 1000 - first + extra;
            let verdict = l.accept(tile, 0, too_much, &[(pixel, [9, 9, 9])]);
            let is_overflow = matches!(verdict, Err(Reject::Overflow { .. }));
            prop_assert!(is_overflow);
            prop_assert_eq!(l, before);
        }
    }
}

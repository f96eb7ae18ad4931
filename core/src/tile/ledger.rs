//! The tile ledger: which tiles are complete, per tile epoch, returned credit and pixel sums.

use std::error::Error;
use std::fmt;

use super::TileGrid;

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
    /// stands for (see [`TileLedger::with_samples`]).
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
pub struct TileLedger {
    grid: TileGrid,
    tile_credit: u64,
    tiles: Vec<TileState>,
    done: u32,
    /// Samples per pixel, when results must name the pixels their credit came from.
    spp: Option<u32>,
}

impl TileLedger {
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
    /// got [`primary_credit`](super::credit::primary_credit) in pixel-major order (index `local pixel * spp + sample`).
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

//! Camera rays as every renderer issues them: the same ray, with the same share of its tile's
//! credit, whichever process makes it and in whatever order.

use crate::camera::PinholeCamera;
use crate::progressive::Samples;
use crate::ray::RayRecord;
use crate::tile::TileGrid;
use crate::tile::credit::{TILE_CREDIT, primary_credit};

/// The camera ray of `sample` of `pixel`, tagged with its tile and its share of the tile's
/// credit. The tile's rays in a pass of `samples` (a progressive subframe, or the whole
/// frame) are its pixels in [`TileGrid::pixels`] order, `samples.count` each: the credit is
/// the pass's, the ray itself depends only on (pixel, sample).
pub fn primary_ray(
    camera: &PinholeCamera,
    grid: &TileGrid,
    samples: Samples,
    pixel: u32,
    sample: u32,
) -> RayRecord {
    let mut ray = camera.primary(pixel, sample);
    // Every pixel of the frame lies in the grid, so these lookups cannot fail; a sample
    // outside the pass gets no credit (callers issue only the pass's samples).
    let tile = grid.tile_of(pixel).unwrap_or(0);
    let local = grid.local_index(tile, pixel).unwrap_or(0) as u64;
    let count = u64::from(samples.count);
    let rays = grid.tile_pixel_count(tile) as u64 * count;
    let index = local * count + u64::from(samples.offset(sample).unwrap_or(samples.count));
    ray.tile = tile;
    ray.credit = primary_credit(TILE_CREDIT, rays, index).unwrap_or(0);
    ray
}

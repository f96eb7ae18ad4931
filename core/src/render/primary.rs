//! Camera rays as every renderer issues them: the same ray, with the same share of its tile's
//! credit, whichever process makes it and in whatever order.

use crate::camera::PinholeCamera;
use crate::frame::{TILE_CREDIT, TileGrid, primary_credit};
use crate::ray::RayRecord;

/// The camera ray of `sample` of `pixel`, tagged with its tile and its share of the tile's
/// credit (the tile's rays are its pixels in [`TileGrid::pixels`] order, `spp` each).
pub fn primary_ray(
    camera: &PinholeCamera,
    grid: &TileGrid,
    spp: u32,
    pixel: u32,
    sample: u32,
) -> RayRecord {
    let mut ray = camera.primary(pixel, sample);
    // Every pixel of the frame lies in the grid, so these lookups cannot fail.
    let tile = grid.tile_of(pixel).unwrap_or(0);
    let local = grid.local_index(tile, pixel).unwrap_or(0) as u64;
    let rays = grid.tile_pixel_count(tile) as u64 * spp as u64;
    ray.tile = tile;
    ray.credit = primary_credit(TILE_CREDIT, rays, local * spp as u64 + sample as u64).unwrap_or(0);
    ray
}

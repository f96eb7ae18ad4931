//! Tiles: how the image is cut ([`TileGrid`]), the credit a tile's rays carry ([`credit`])
//! and the ledger that commits a tile once all of its credit is back ([`ledger`]).

pub mod credit;
pub mod ledger;

/// Tile side in pixels: the unit of credit, epochs and results.
pub const TILE_SIZE: u32 = 32;

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

#[cfg(test)]
mod tests;

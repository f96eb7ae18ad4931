/// The deposit's fast conversion is the reference formula (fused multiply-add, then
/// floor) to the bit, for every kind of value, rounding ties and the clamp included.
#[test]
fn to_fixed_equals_the_fused_multiply_add_and_floor() {
    let reference = |v: f32| {
        if v.is_finite() && v > 0.0 {
            (v as f64)
                .min(MAX_CONTRIBUTION)
                .mul_add(FIXED_ONE, 0.5)
                .floor() as i64
        } else {
            0
        }
    };
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    let mut values = vec![
        0.0,
        -0.0,
        1.0,
        0.5,
        1e6,
        1e6 + 64.0,
        f32::MAX,
        f32::MIN_POSITIVE,
    ];
    values.extend([
        f32::INFINITY,
        f32::NAN,
        -1.0,
        1.0 / 16_777_216.0,
        1.5 / 16_777_216.0,
    ]);
    for _ in 0..1_000_000 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        values.push(f32::from_bits(x as u32));
        // Small values, where ties at half a fixed-point unit happen.
        values.push((x >> 40) as f32 / 16_777_216.0 / 2.0);
    }
    for v in values {
        assert_eq!(to_fixed(v), reference(v), "{v:e} ({:#x})", v.to_bits());
    }
}

use super::encode::srgb_byte;
use super::*;

fn grid(w: u32, h: u32) -> TileGrid {
    TileGrid::new(w, h, 4).unwrap()
}

/// The sums of every pixel, row-major, as the hash covers them.
fn film_with(dir: &Path, g: TileGrid, sums: impl Fn(u32) -> [i64; 3]) -> Film {
    let film = Film::temporary_in(dir, g, 1).unwrap();
    for tile in 0..g.count() {
        let s: Vec<[i64; 3]> = g.pixels(tile).map(&sums).collect();
        film.write_tile(tile, &s).unwrap();
    }
    film
}

#[test]
fn a_full_size_preview_of_a_whole_film_is_the_saved_png() {
    let dir = tempfile::tempdir().unwrap();
    let g = grid(10, 7);
    let film = film_with(dir.path(), g, |p| [p as i64 * 40_000, 1 << 22, 0]);
    let saved = dir.path().join("image.png");
    film.save(&saved).unwrap();
    let preview = film.preview_png(1024).unwrap();
    assert_eq!((preview.width, preview.height, preview.factor), (10, 7, 1));
    assert_eq!(preview.png, std::fs::read(&saved).unwrap());
    // A tile not written is drawn as the checkerboard, not its sums.
    let part = Film::temporary_in(dir.path(), g, 1).unwrap();
    for tile in 1..g.count() {
        let s: Vec<[i64; 3]> = g
            .pixels(tile)
            .map(|p| [p as i64 * 40_000, 1 << 22, 0])
            .collect();
        part.write_tile(tile, &s).unwrap();
    }
    assert_ne!(part.preview_png(1024).unwrap().png, preview.png);
}

#[test]
fn a_preview_longer_than_its_bound_is_shrunk_by_a_whole_factor() {
    let dir = tempfile::tempdir().unwrap();
    let g = grid(10, 7);
    let film = film_with(dir.path(), g, |_| [1 << 23, 1 << 23, 1 << 23]);
    let preview = film.preview_png(4).unwrap();
    // ceil(10 / 4) = 3; 10 / 3 and 7 / 3 rounded up.
    assert_eq!((preview.width, preview.height, preview.factor), (4, 3, 3));
    let mut decoder = png::Decoder::new(std::io::Cursor::new(preview.png))
        .read_info()
        .unwrap();
    let mut pixels = vec![0; decoder.output_buffer_size().unwrap()];
    decoder.next_frame(&mut pixels).unwrap();
    // Every film pixel is 0.5: so is every mean of them.
    assert!(pixels.iter().all(|&b| b == srgb_byte(0.5)));
}

#[test]
fn subframes_added_tile_by_tile_make_the_one_pass_film_and_previews_average_each_tile() {
    let dir = tempfile::tempdir().unwrap();
    let g = grid(10, 7);
    // Three subframes of 1, 1 and 2 samples; the one pass has all 4.
    let part = |p: u32, k: i64| [p as i64 * 1000 + k, (1 << 24) * k, -k];
    let one = Film::temporary_in(dir.path(), g, 4).unwrap();
    let progressive = Film::temporary_in(dir.path(), g, 4).unwrap();
    for tile in 0..g.count() {
        let sub = |k: i64| -> Vec<[i64; 3]> { g.pixels(tile).map(|p| part(p, k)).collect() };
        let total: Vec<[i64; 3]> = (0..sub(1).len())
            .map(|i| [0, 1, 2].map(|c| sub(1)[i][c] + sub(1)[i][c] + sub(2)[i][c]))
            .collect();
        one.write_tile(tile, &total).unwrap();
        for (k, n) in [(1, 1), (1, 1), (2, 2)] {
            progressive.add_tile(tile, &sub(k), n).unwrap();
        }
        assert_eq!(progressive.tile_samples(tile), 4);
    }
    assert_eq!(progressive.hash().unwrap(), one.hash().unwrap());
    assert_eq!(
        progressive.preview_png(1024).unwrap().png,
        one.preview_png(1024).unwrap().png
    );
    // One subframe of one sample of light 1.0 everywhere previews as 1.0, not 1/4.
    let first = Film::temporary_in(dir.path(), g, 4).unwrap();
    for tile in 0..g.count() {
        let n = g.tile_pixel_count(tile);
        first.add_tile(tile, &vec![[1 << 24; 3]; n], 1).unwrap();
    }
    let preview = first.preview_png(1024).unwrap();
    let mut decoder = png::Decoder::new(std::io::Cursor::new(preview.png))
        .read_info()
        .unwrap();
    let mut pixels = vec![0; decoder.output_buffer_size().unwrap()];
    decoder.next_frame(&mut pixels).unwrap();
    assert!(pixels.iter().all(|&b| b == srgb_byte(1.0)));
}

#[test]
fn the_hash_is_the_xxh3_of_the_sums_in_pixel_order() {
    let dir = tempfile::tempdir().unwrap();
    // Edge tiles smaller than the slot on both sides.
    let g = grid(10, 7);
    let value = |p: u32| [p as i64, -(p as i64) * 3, i64::MAX - p as i64];
    let film = film_with(dir.path(), g, value);
    let flat: Vec<i64> = (0..70).flat_map(value).collect();
    let expected = xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&flat));
    assert_eq!(film.hash().unwrap(), expected);
    let png = dir.path().join("a.png");
    let exr = dir.path().join("a.exr");
    assert_eq!(film.save_all(&[&png, &exr]).unwrap(), expected);
}

#[test]
fn images_decode_to_the_film_row_by_row() {
    let dir = tempfile::tempdir().unwrap();
    let g = grid(9, 6);
    let value = |p: u32| {
        let v = (p as f64 / 54.0 * FIXED_ONE) as i64;
        [v, v / 2, FIXED_ONE as i64 - v]
    };
    let film = film_with(dir.path(), g, value);
    let (png, exr) = (dir.path().join("a.png"), dir.path().join("a.exr"));
    film.save_all(&[&png, &exr]).unwrap();
    let decoded = image::open(&png).unwrap().to_rgb8();
    assert_eq!(decoded.dimensions(), (9, 6));
    let exr_img = image::open(&exr).unwrap().to_rgb32f();
    assert_eq!(exr_img.dimensions(), (9, 6));
    for p in 0..54u32 {
        let (x, y) = (p % 9, p / 9);
        let linear = value(p).map(|c| (c as f64 / FIXED_ONE) as f32);
        assert_eq!(exr_img.get_pixel(x, y).0, linear, "pixel {p}");
        assert_eq!(
            decoded.get_pixel(x, y).0,
            linear.map(srgb_byte),
            "pixel {p}"
        );
    }
}

#[test]
fn unwritten_tiles_are_black_and_bad_tiles_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let g = grid(8, 8);
    let path = dir.path().join("film.bin");
    let film = Film::create(&path, g, 1).unwrap();
    assert_eq!(
        std::fs::metadata(&path).unwrap().len(),
        Film::file_bytes(&g)
    );
    film.write_tile(3, &[[1, 2, 3]]).unwrap();
    let mut flat = vec![0i64; 64 * 3];
    // Tile 3 is the bottom-right one; its first pixel is (4, 4).
    flat[(4 * 8 + 4) * 3..(4 * 8 + 4) * 3 + 3].copy_from_slice(&[1, 2, 3]);
    assert_eq!(
        film.hash().unwrap(),
        xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&flat))
    );
    assert!(film.write_tile(4, &[]).is_err());
    assert!(film.write_tile(0, &[[0; 3]; 17]).is_err());
    drop(film);
    assert!(!path.exists(), "a named film is removed with it");
}

#[test]
fn open_tiles_commit_to_the_film_and_free_their_memory() {
    let dir = tempfile::tempdir().unwrap();
    let g = grid(8, 4);
    let film = Film::temporary_in(dir.path(), g, 1).unwrap();
    let mut open = OpenTiles::new(g);
    let vals = [[0.1, 0.2, 0.3], [1e-7, 5.0, 0.0], [0.333, 0.333, 0.334]];
    for v in vals {
        open.deposit(0, 1, v);
    }
    open.deposit(1, 4, [1.0; 3]);
    open.deposit(1, 0, [1.0; 3]); // pixel 0 is not in tile 1: ignored
    assert_eq!(open.in_memory(), 2);
    open.commit(0, &film).unwrap();
    open.commit(1, &film).unwrap();
    open.deposit(1, 4, [1.0; 3]); // committed: ignored
    assert_eq!(open.in_memory(), 0);
    let mut flat = vec![0i64; 32 * 3];
    for v in vals {
        for (c, x) in flat[3..6].iter_mut().zip(v) {
            *c += to_fixed(x);
        }
    }
    flat[12..15].copy_from_slice(&[1 << 24; 3]);
    assert_eq!(
        film.hash().unwrap(),
        xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&flat))
    );
}

#[test]
fn bad_values_are_ignored_not_propagated() {
    assert_eq!(to_fixed(f32::NAN), 0);
    assert_eq!(to_fixed(-1.0), 0);
    assert_eq!(to_fixed(1.0), 1 << 24);
}

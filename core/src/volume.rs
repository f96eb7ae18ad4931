//! Raw scalar volumes: headerless little-endian voxel files, x fastest, then
//! y, then z, as written by most CT/MRI and simulation tools.

use crate::isosurface::Lattice;
use memmap2::Mmap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// Storage type of one voxel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelType {
    /// Unsigned 8-bit integer.
    U8,
    /// Signed 16-bit integer, little-endian.
    I16,
    /// Unsigned 16-bit integer, little-endian.
    U16,
    /// IEEE 754 single precision, little-endian.
    F32,
}

impl VoxelType {
    /// Bytes per voxel.
    pub fn size(self) -> usize {
        match self {
            VoxelType::U8 => 1,
            VoxelType::I16 | VoxelType::U16 => 2,
            VoxelType::F32 => 4,
        }
    }

    /// Decodes the voxel starting at `bytes[0]`.
    fn decode(self, bytes: &[u8]) -> f32 {
        match self {
            VoxelType::U8 => f32::from(bytes[0]),
            VoxelType::I16 => f32::from(i16::from_le_bytes([bytes[0], bytes[1]])),
            VoxelType::U16 => f32::from(u16::from_le_bytes([bytes[0], bytes[1]])),
            VoxelType::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
        }
    }
}

/// A voxel type name that is none of `u8`, `i16`, `u16`, `f32`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown voxel type {0:?} (expected one of u8, i16, u16, f32)")]
pub struct ParseVoxelTypeError(pub String);

impl FromStr for VoxelType {
    type Err = ParseVoxelTypeError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "u8" => Ok(VoxelType::U8),
            "i16" => Ok(VoxelType::I16),
            "u16" => Ok(VoxelType::U16),
            "f32" => Ok(VoxelType::F32),
            other => Err(ParseVoxelTypeError(other.to_owned())),
        }
    }
}

/// Why a raw volume could not be opened; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    /// Opening, inspecting or mapping the file failed.
    #[error("cannot read volume {}: {source}", path.display())]
    Io {
        /// The volume file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A dimension is zero, so there is no lattice to sample.
    #[error("volume {}: dimensions {dims:?} contain a zero", path.display())]
    ZeroDims {
        /// The volume file.
        path: PathBuf,
        /// The requested dimensions.
        dims: [u32; 3],
    },
    /// X*Y*Z*voxel size does not fit in memory addresses.
    #[error("volume {}: dimensions {dims:?} of {ty:?} overflow the addressable size", path.display())]
    TooLarge {
        /// The volume file.
        path: PathBuf,
        /// The requested dimensions.
        dims: [u32; 3],
        /// The requested voxel type.
        ty: VoxelType,
    },
    /// The file is not exactly X*Y*Z*voxel-size bytes long.
    #[error(
        "volume {}: expected {expected} bytes ({dims:?} voxels of {ty:?}) but the file has {actual}",
        path.display()
    )]
    SizeMismatch {
        /// The volume file.
        path: PathBuf,
        /// The requested dimensions.
        dims: [u32; 3],
        /// The requested voxel type.
        ty: VoxelType,
        /// Bytes the dimensions and type call for.
        expected: u64,
        /// Bytes the file has.
        actual: u64,
    },
}

/// A memory-mapped raw volume, sampled as a [`Lattice`] with one lattice point
/// per voxel.
///
/// The mapping is read-only and shared: the file must not be truncated or
/// rewritten while the volume is open (see [`RawVolume::open`]).
#[derive(Debug)]
pub struct RawVolume {
    map: Mmap,
    dims: [u32; 3],
    ty: VoxelType,
}

impl RawVolume {
    /// Maps `path` as `dims` voxels of `ty`, checking that the file size is
    /// exactly `X*Y*Z*size_of(ty)`.
    ///
    /// The file must stay unchanged while the volume is open; changing it
    /// underneath a memory map is undefined behaviour.
    pub fn open(path: &Path, dims: [u32; 3], ty: VoxelType) -> Result<Self, VolumeError> {
        let expected = expected_len(path, dims, ty)?;
        let io_err = |source| VolumeError::Io {
            path: path.to_owned(),
            source,
        };
        let file = File::open(path).map_err(io_err)?;
        let actual = file.metadata().map_err(io_err)?.len();
        if actual != expected {
            return Err(VolumeError::SizeMismatch {
                path: path.to_owned(),
                dims,
                ty,
                expected,
                actual,
            });
        }
        // SAFETY: the mapping is read-only and the caller keeps the file
        // unchanged while it is open (documented above); its length was just
        // checked, and every access below is bounds-checked against it.
        let map = unsafe { Mmap::map(&file) }.map_err(io_err)?;
        if map.len() as u64 != expected {
            // The file changed between the size check and the mapping.
            return Err(VolumeError::SizeMismatch {
                path: path.to_owned(),
                dims,
                ty,
                expected,
                actual: map.len() as u64,
            });
        }
        Ok(RawVolume { map, dims, ty })
    }

    /// Voxels along x, y and z.
    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }

    /// Storage type of the voxels.
    pub fn voxel_type(&self) -> VoxelType {
        self.ty
    }
}

/// Bytes a volume of `dims` voxels of `ty` must have, rejecting zero and
/// overflowing dimensions.
fn expected_len(path: &Path, dims: [u32; 3], ty: VoxelType) -> Result<u64, VolumeError> {
    if dims.contains(&0) {
        return Err(VolumeError::ZeroDims {
            path: path.to_owned(),
            dims,
        });
    }
    let too_large = || VolumeError::TooLarge {
        path: path.to_owned(),
        dims,
        ty,
    };
    let bytes = dims
        .iter()
        .try_fold(ty.size() as u64, |acc, &d| acc.checked_mul(u64::from(d)))
        .ok_or_else(too_large)?;
    // Voxel offsets are computed in usize, so the whole file must be addressable.
    usize::try_from(bytes).map_err(|_| too_large())?;
    Ok(bytes)
}

impl Lattice for RawVolume {
    /// # Panics
    /// If `(i, j, k)` is outside the volume's dimensions.
    fn value(&self, i: u32, j: u32, k: u32) -> f32 {
        let [nx, ny, nz] = self.dims;
        assert!(
            i < nx && j < ny && k < nz,
            "voxel ({i}, {j}, {k}) outside volume {:?}",
            self.dims
        );
        // Fits: open() checked that X*Y*Z*size is addressable.
        let index = i as usize + nx as usize * (j as usize + ny as usize * k as usize);
        let size = self.ty.size();
        self.ty.decode(&self.map[index * size..][..size])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::isosurface::{Grid, march};
    use std::io::Write;

    fn write_file(bytes: &[u8]) -> tempfile::NamedTempFile {
        let mut file = tempfile::NamedTempFile::new().unwrap();
        file.write_all(bytes).unwrap();
        file.flush().unwrap();
        file
    }

    #[test]
    fn parses_voxel_types() {
        assert_eq!("u8".parse(), Ok(VoxelType::U8));
        assert_eq!("i16".parse(), Ok(VoxelType::I16));
        assert_eq!("u16".parse(), Ok(VoxelType::U16));
        assert_eq!("f32".parse(), Ok(VoxelType::F32));
        let err = "float".parse::<VoxelType>().unwrap_err();
        assert!(err.to_string().contains("\"float\""));
    }

    #[test]
    fn reads_each_type_little_endian_x_fastest() {
        let dims = [3u32, 2, 2];
        let n = 12;
        let u8s: Vec<u8> = (0..n).map(|v| v as u8 * 20).collect();
        let i16s: Vec<u8> = (0..n)
            .flat_map(|v| (v as i16 * -300).to_le_bytes())
            .collect();
        let u16s: Vec<u8> = (0..n)
            .flat_map(|v| (v as u16 * 5000).to_le_bytes())
            .collect();
        let f32s: Vec<u8> = (0..n)
            .flat_map(|v| (v as f32 * 0.25 - 1.0).to_le_bytes())
            .collect();
        // (type, file bytes, expected value of voxel number n)
        type Case<'a> = (VoxelType, &'a [u8], fn(u32) -> f32);
        let cases: [Case; 4] = [
            (VoxelType::U8, &u8s, |v| (v * 20) as f32),
            (VoxelType::I16, &i16s, |v| (v as i32 * -300) as f32),
            (VoxelType::U16, &u16s, |v| (v * 5000) as f32),
            (VoxelType::F32, &f32s, |v| v as f32 * 0.25 - 1.0),
        ];
        for (ty, bytes, expected) in cases {
            let file = write_file(bytes);
            let vol = RawVolume::open(file.path(), dims, ty).unwrap();
            for k in 0..2 {
                for j in 0..2 {
                    for i in 0..3 {
                        let linear = i + 3 * (j + 2 * k);
                        assert_eq!(
                            vol.value(i, j, k),
                            expected(linear),
                            "{ty:?} at {i},{j},{k}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn size_mismatch_names_file_and_both_sizes() {
        let file = write_file(&[0u8; 23]);
        let err = RawVolume::open(file.path(), [3, 2, 2], VoxelType::U16).unwrap_err();
        assert!(matches!(
            err,
            VolumeError::SizeMismatch {
                expected: 24,
                actual: 23,
                ..
            }
        ));
        let msg = err.to_string();
        assert!(msg.contains(&file.path().display().to_string()), "{msg}");
        assert!(msg.contains("24") && msg.contains("23"), "{msg}");
    }

    #[test]
    fn rejects_zero_and_overflowing_dims() {
        let file = write_file(&[0u8; 8]);
        let err = RawVolume::open(file.path(), [2, 0, 4], VoxelType::U8).unwrap_err();
        assert!(matches!(err, VolumeError::ZeroDims { .. }));
        let huge = [u32::MAX; 3];
        let err = RawVolume::open(file.path(), huge, VoxelType::F32).unwrap_err();
        assert!(matches!(err, VolumeError::TooLarge { .. }));
        assert!(err.to_string().contains(&file.path().display().to_string()));
    }

    #[test]
    fn missing_file_is_an_io_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("absent.raw");
        let err = RawVolume::open(&path, [1, 1, 1], VoxelType::U8).unwrap_err();
        assert!(matches!(err, VolumeError::Io { .. }));
        assert!(err.to_string().contains("absent.raw"));
    }

    #[test]
    #[should_panic(expected = "outside volume")]
    fn out_of_range_sample_panics() {
        let file = write_file(&[0u8; 8]);
        let vol = RawVolume::open(file.path(), [2, 2, 2], VoxelType::U8).unwrap();
        vol.value(2, 0, 0);
    }

    #[test]
    fn marches_a_volume() {
        // One bright voxel in the middle of a dark 3x3x3 block: a closed
        // octahedron of 8 triangles.
        let mut bytes = [0u8; 27];
        bytes[13] = 200;
        let file = write_file(&bytes);
        let vol = RawVolume::open(file.path(), [3, 3, 3], VoxelType::U8).unwrap();
        let grid = Grid {
            origin: glam::Vec3::ZERO,
            spacing: glam::Vec3::ONE,
            dims: vol.dims(),
        };
        let mut count = 0;
        march(&grid, &vol, 100.0, grid.all_cells(), |_| count += 1);
        assert_eq!(count, 8);
    }
}

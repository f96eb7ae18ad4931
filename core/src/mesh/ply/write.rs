//! PLY writers: ASCII and binary little-endian, vertices and triangles only.

use std::io::{self, BufWriter, Write};

use super::super::{TriangleMesh, check_writable};

/// Writes `mesh` as ASCII PLY, with coordinates in shortest round-trip form.
pub fn write_ply_ascii(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let mut w = BufWriter::new(w);
    write_header(&mut w, mesh, "ascii")?;
    for [x, y, z] in &mesh.positions {
        writeln!(w, "{x:?} {y:?} {z:?}")?;
    }
    for [a, b, c] in &mesh.triangles {
        writeln!(w, "3 {a} {b} {c}")?;
    }
    w.flush()
}

/// Writes `mesh` as binary little-endian PLY.
pub fn write_ply_binary(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let mut w = BufWriter::new(w);
    write_header(&mut w, mesh, "binary_little_endian")?;
    for position in &mesh.positions {
        for coordinate in position {
            w.write_all(&coordinate.to_le_bytes())?;
        }
    }
    for triangle in &mesh.triangles {
        w.write_all(&[3])?;
        for index in triangle {
            w.write_all(&index.to_le_bytes())?;
        }
    }
    w.flush()
}

/// The header both writers share: float x/y/z vertices, triangles as index lists.
fn write_header(w: &mut impl Write, mesh: &TriangleMesh, format: &str) -> io::Result<()> {
    writeln!(w, "ply\nformat {format} 1.0")?;
    writeln!(w, "element vertex {}", mesh.positions.len())?;
    writeln!(w, "property float x\nproperty float y\nproperty float z")?;
    writeln!(w, "element face {}", mesh.triangles.len())?;
    writeln!(w, "property list uchar uint vertex_indices\nend_header")
}

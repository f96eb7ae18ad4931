//! The worker's [`RaySpill`]: rays that do not fit the queues' memory cap wait in one file per
//! domain under a temporary directory, read back from the front and started over once empty.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::Path;

use bytemuck::Zeroable;
use rayfarm_core::ray::RayRecord;
use rayfarm_machine::worker::queues::{RAY_BYTES, RaySpill};

/// Bytes written to a new spill directory before a frame starts.
const PROBE_BYTES: usize = 64 << 10;

/// Writes and removes a small file in `dir`.
fn probe(dir: &Path) -> std::io::Result<()> {
    let path = dir.join("probe");
    let written = File::create(&path).and_then(|mut f| f.write_all(&[0; PROBE_BYTES]));
    let removed = std::fs::remove_file(&path);
    written.and(removed)
}

/// Rays of one domain in a file read from the front.
struct Spill {
    file: File,
    /// Rays written and not yet read back.
    rays: u64,
    /// Byte offset of the first unread ray.
    read_at: u64,
}

/// See the module documentation.
pub struct FileSpill {
    spills: Vec<Option<Spill>>,
    /// Removed with everything in it when the frame's queues are dropped.
    dir: tempfile::TempDir,
}

impl FileSpill {
    /// A spill store in a fresh directory under `root`, written to once so that a full or
    /// read-only directory is found before the frame starts (the worker then declines the
    /// frame) rather than halfway through it.
    pub fn new(root: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(root)?;
        let dir = tempfile::Builder::new()
            .prefix("rayfarm-spill-")
            .tempdir_in(root)?;
        probe(dir.path())?;
        Ok(FileSpill {
            spills: Vec::new(),
            dir,
        })
    }

    fn append_io(&mut self, domain: u32, rays: &[RayRecord]) -> std::io::Result<()> {
        let d = domain as usize;
        if self.spills.len() <= d {
            self.spills.resize_with(d + 1, || None);
        }
        let spill = match &mut self.spills[d] {
            Some(s) => s,
            none => none.insert(Spill {
                // Read back as well as appended to.
                file: std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create(true)
                    .truncate(true)
                    .open(self.dir.path().join(format!("domain-{d}.rays")))?,
                rays: 0,
                read_at: 0,
            }),
        };
        spill.file.seek(SeekFrom::End(0))?;
        spill.file.write_all(bytemuck::cast_slice(rays))?;
        spill.rays += rays.len() as u64;
        Ok(())
    }

    fn take_io(&mut self, domain: u32, n: usize) -> std::io::Result<Vec<RayRecord>> {
        let Some(spill) = self
            .spills
            .get_mut(domain as usize)
            .and_then(Option::as_mut)
            .filter(|s| s.rays >= n as u64)
        else {
            return Err(std::io::Error::other(format!(
                "domain {domain}: fewer than {n} rays spilled"
            )));
        };
        let mut back = vec![RayRecord::zeroed(); n];
        spill.file.seek(SeekFrom::Start(spill.read_at))?;
        spill.file.read_exact(bytemuck::cast_slice_mut(&mut back))?;
        spill.read_at += n as u64 * RAY_BYTES;
        spill.rays -= n as u64;
        if spill.rays == 0 {
            // Everything read back: start the file over.
            spill.file.set_len(0)?;
            spill.read_at = 0;
        }
        Ok(back)
    }
}

impl FileSpill {
    /// The error named by the directory the worker was given (`--spill-dir`).
    fn named(&self, e: std::io::Error) -> String {
        let root = self.dir.path().parent().unwrap_or(self.dir.path());
        format!("spill directory {}: {e}", root.display())
    }
}

impl RaySpill for FileSpill {
    fn append(&mut self, domain: u32, rays: &[RayRecord]) -> Result<(), String> {
        self.append_io(domain, rays).map_err(|e| self.named(e))
    }

    fn take_front(&mut self, domain: u32, n: usize) -> Result<Vec<RayRecord>, String> {
        self.take_io(domain, n).map_err(|e| self.named(e))
    }
}

#[cfg(test)]
mod tests {
    use rayfarm_machine::worker::queues::DomainQueues;

    use super::*;

    #[test]
    fn rays_spilled_to_files_all_come_back_in_order_of_arrival() {
        let root = tempfile::tempdir().unwrap();
        let spill = FileSpill::new(root.path()).unwrap();
        let mut q = DomainQueues::new(2, 4 * RAY_BYTES, 100 * RAY_BYTES, spill);
        let rays: Vec<RayRecord> = (0..10)
            .map(|pixel| RayRecord {
                pixel,
                ..RayRecord::zeroed()
            })
            .collect();
        q.push(1, &rays).unwrap();
        assert_eq!(q.spilled_total, 6, "only 4 fit in memory");
        let mut back: Vec<u32> = Vec::new();
        while q.len(1) > 0 {
            back.extend(q.take(1, 3).unwrap().iter().map(|r| r.pixel));
        }
        back.sort_unstable();
        assert_eq!(back, (0..10).collect::<Vec<_>>());
        // Emptied files start over: a second round trip reads the new rays, not the old.
        q.push(1, &rays).unwrap();
        assert_eq!(q.take(1, 100).unwrap().len(), 10);
    }
}

//! One ray queue per domain with a memory cap: past the cap, rays spill to files in a local
//! directory and come back when their domain is traced, so nothing is dropped and memory
//! stays bounded. Past the spill cap the frame cannot proceed within its budgets, and says so.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::Path;

use bytemuck::Zeroable;
use rayfarm_core::ray::RayRecord;

/// Bytes of one queued ray.
const RAY_BYTES: u64 = std::mem::size_of::<RayRecord>() as u64;

/// Why rays could not be queued.
#[derive(Debug, thiserror::Error)]
pub enum QueueError {
    /// Memory and spill caps are both full.
    #[error(
        "queued rays exceed the worker's budgets: {mem_cap} bytes in memory and {spill_cap} bytes \
         spilled to disk (raise --queue-bytes or --spill-bytes, or give the frame more workers)"
    )]
    Full { mem_cap: u64, spill_cap: u64 },
    /// The spill directory failed.
    #[error("spilling rays to disk: {0}")]
    Io(#[from] std::io::Error),
}

/// Bytes written to a new spill directory before a frame starts.
const PROBE_BYTES: usize = 64 << 10;

/// Writes and removes a small file in `dir`, so that a full or read-only spill directory is
/// found before the frame starts (the worker then declines it) rather than halfway through.
fn probe(dir: &Path) -> std::io::Result<()> {
    let path = dir.join("probe");
    let written = File::create(&path).and_then(|mut f| f.write_all(&[0; PROBE_BYTES]));
    let removed = std::fs::remove_file(&path);
    written.and(removed)
}

/// Rays of one domain that did not fit in memory, in a file read from the front.
#[derive(Default)]
struct Spill {
    file: Option<File>,
    /// Rays written and not yet read back.
    rays: u64,
    /// Byte offset of the first unread ray.
    read_at: u64,
}

/// See the module documentation.
pub struct DomainQueues {
    mem: Vec<Vec<RayRecord>>,
    spills: Vec<Spill>,
    mem_rays: u64,
    mem_cap_rays: u64,
    spill_rays: u64,
    spill_cap_rays: u64,
    dir: tempfile::TempDir,
    /// Rays ever spilled, for the statistics.
    pub spilled_total: u64,
}

impl DomainQueues {
    /// Queues for `domains` domains holding at most `mem_cap` bytes of rays in memory and
    /// `spill_cap` bytes in files under `spill_root`.
    pub fn new(
        domains: usize,
        mem_cap: u64,
        spill_cap: u64,
        spill_root: &Path,
    ) -> std::io::Result<Self> {
        std::fs::create_dir_all(spill_root)?;
        let dir = tempfile::Builder::new()
            .prefix("rayfarm-spill-")
            .tempdir_in(spill_root)?;
        if spill_cap > 0 {
            probe(dir.path())?;
        }
        Ok(DomainQueues {
            mem: vec![Vec::new(); domains],
            spills: (0..domains).map(|_| Spill::default()).collect(),
            mem_rays: 0,
            mem_cap_rays: (mem_cap / RAY_BYTES).max(1),
            spill_rays: 0,
            spill_cap_rays: spill_cap / RAY_BYTES,
            dir,
            spilled_total: 0,
        })
    }

    /// Queues `rays`, each for its `domain` (which must be below the domain count).
    pub fn push(&mut self, domain: u32, rays: &[RayRecord]) -> Result<(), QueueError> {
        let d = domain as usize;
        let room = self.mem_cap_rays.saturating_sub(self.mem_rays) as usize;
        // Rays already spilled for this domain keep their place in line.
        let in_memory = if self.spills[d].rays > 0 {
            0
        } else {
            room.min(rays.len())
        };
        self.mem[d].extend_from_slice(&rays[..in_memory]);
        self.mem_rays += in_memory as u64;
        let rest = &rays[in_memory..];
        if !rest.is_empty() {
            self.spill(d, rest)?;
        }
        Ok(())
    }

    fn spill(&mut self, d: usize, rays: &[RayRecord]) -> Result<(), QueueError> {
        if self.spill_rays + rays.len() as u64 > self.spill_cap_rays {
            return Err(QueueError::Full {
                mem_cap: self.mem_cap_rays * RAY_BYTES,
                spill_cap: self.spill_cap_rays * RAY_BYTES,
            });
        }
        let spill = &mut self.spills[d];
        let file = match &mut spill.file {
            Some(f) => f,
            // Read back as well as appended to.
            None => spill.file.insert(
                std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create(true)
                    .truncate(true)
                    .open(self.dir.path().join(format!("domain-{d}.rays")))?,
            ),
        };
        file.seek(SeekFrom::End(0))?;
        file.write_all(bytemuck::cast_slice(rays))?;
        spill.rays += rays.len() as u64;
        self.spill_rays += rays.len() as u64;
        self.spilled_total += rays.len() as u64;
        Ok(())
    }

    /// Takes up to `max` rays of `domain`: from memory first, then back from its spill file.
    pub fn take(&mut self, domain: u32, max: usize) -> Result<Vec<RayRecord>, QueueError> {
        let d = domain as usize;
        let q = &mut self.mem[d];
        let mut out = if q.len() > max {
            q.split_off(q.len() - max)
        } else {
            std::mem::take(q)
        };
        self.mem_rays -= out.len() as u64;
        let want = (max - out.len()) as u64;
        let spill = &mut self.spills[d];
        if want > 0
            && spill.rays > 0
            && let Some(file) = &mut spill.file
        {
            let n = want.min(spill.rays);
            let mut back = vec![RayRecord::zeroed(); n as usize];
            file.seek(SeekFrom::Start(spill.read_at))?;
            file.read_exact(bytemuck::cast_slice_mut(&mut back))?;
            spill.read_at += n * RAY_BYTES;
            spill.rays -= n;
            self.spill_rays -= n;
            if spill.rays == 0 {
                // Everything read back: start the file over.
                file.set_len(0)?;
                spill.read_at = 0;
            }
            out.extend(back);
        }
        Ok(out)
    }

    /// Rays queued for `domain`, in memory and spilled.
    pub fn len(&self, domain: u32) -> u64 {
        let d = domain as usize;
        self.mem[d].len() as u64 + self.spills[d].rays
    }

    /// Number of domains.
    pub fn domains(&self) -> u32 {
        self.mem.len() as u32
    }

    /// Rays queued over all domains.
    pub fn total(&self) -> u64 {
        self.mem_rays + self.spill_rays
    }

    /// Keeps only the rays `keep` accepts (in memory and in spill files).
    pub fn retain(&mut self, keep: impl Fn(&RayRecord) -> bool) -> Result<(), QueueError> {
        for d in 0..self.domains() {
            let len = self.len(d) as usize;
            let rays = self.take(d, len)?;
            let kept: Vec<RayRecord> = rays.into_iter().filter(|r| keep(r)).collect();
            self.push(d, &kept)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(pixel: u32) -> RayRecord {
        RayRecord {
            pixel,
            ..RayRecord::zeroed()
        }
    }

    #[test]
    fn rays_past_the_memory_cap_spill_and_all_come_back() {
        let root = tempfile::tempdir().unwrap();
        let mut q = DomainQueues::new(2, 4 * RAY_BYTES, 100 * RAY_BYTES, root.path()).unwrap();
        let rays: Vec<RayRecord> = (0..10).map(ray).collect();
        q.push(0, &rays).unwrap();
        q.push(1, &rays[..3]).unwrap();
        assert_eq!((q.len(0), q.len(1), q.total()), (10, 3, 13));
        assert_eq!(q.spilled_total, 9, "only 4 fit in memory");
        let mut back: Vec<u32> = Vec::new();
        while q.len(0) > 0 {
            back.extend(q.take(0, 3).unwrap().iter().map(|r| r.pixel));
        }
        back.sort_unstable();
        assert_eq!(back, (0..10).collect::<Vec<_>>());
        assert_eq!(q.take(1, 10).unwrap().len(), 3);
        assert_eq!(q.total(), 0);
    }

    #[test]
    fn past_both_caps_the_error_names_the_budgets() {
        let root = tempfile::tempdir().unwrap();
        let mut q = DomainQueues::new(1, 2 * RAY_BYTES, 3 * RAY_BYTES, root.path()).unwrap();
        let rays: Vec<RayRecord> = (0..5).map(ray).collect();
        q.push(0, &rays).unwrap();
        let err = q.push(0, &rays[..1]).unwrap_err().to_string();
        let memory = format!("{} bytes in memory", 2 * RAY_BYTES);
        assert!(
            err.contains("--queue-bytes") && err.contains(&memory),
            "{err}"
        );
    }

    #[test]
    fn retain_filters_spilled_rays_too() {
        let root = tempfile::tempdir().unwrap();
        let mut q = DomainQueues::new(1, 2 * RAY_BYTES, 100 * RAY_BYTES, root.path()).unwrap();
        q.push(0, &(0..8).map(ray).collect::<Vec<_>>()).unwrap();
        q.retain(|r| r.pixel % 2 == 0).unwrap();
        let mut left: Vec<u32> = q.take(0, 100).unwrap().iter().map(|r| r.pixel).collect();
        left.sort_unstable();
        assert_eq!(left, [0, 2, 4, 6]);
    }
}

//! Where a loaded domain file's bytes live ([`Residence`]): mapped from the file, or copied
//! into memory backed by 2 MiB pages; and a file's bytes arriving from a peer ([`Received`]),
//! held the same way. The file's layout and its checks are `domain_file`'s; this module only
//! says which memory holds the bytes, so both kinds of load trace the same.

use std::sync::Mutex;

use memmap2::{Mmap, MmapMut, MmapOptions};

/// Where a domain's bytes live while it is loaded.
///
/// Incoherent rays are bound by memory: each one touches a few dozen nodes and blocks spread
/// over the whole tree, and with 4 KiB pages most of those touches also miss the TLB (a
/// 61 MiB domain is 15,000 pages, far beyond the TLB's reach; 31 huge pages are within it).
/// A file mapping is made of the page cache's pages, which the program cannot ask to be huge,
/// so the default copies the file into anonymous memory that the kernel is asked
/// (`madvise(MADV_HUGEPAGE)`) to back with 2 MiB pages. The load reads every byte anyway (the
/// checksum, the tree's validation, the material check), so the copy adds one pass over
/// memory; the cache counts the same bytes as before (the file's size).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Residence {
    /// Mapped from the file (`mmap`), in the page cache's pages.
    Mapped,
    /// Copied into anonymous memory aligned to, and advised to use, 2 MiB pages.
    HugePages,
}

/// Files smaller than this stay mapped: they would not fill one huge page.
const HUGE_PAGE: usize = 2 << 20;

impl Residence {
    /// The process's choice for a file of `bytes`: `RAYFARM_HUGEPAGES=0` (or `off`) maps
    /// every domain file, `RAYFARM_HUGEPAGES=1` (or `on`) copies every one whatever its size;
    /// unset, files of at least one huge page (2 MiB) are copied and smaller ones mapped. The
    /// variable is read once.
    pub fn selected(bytes: u64) -> Residence {
        static CHOICE: std::sync::OnceLock<Option<Residence>> = std::sync::OnceLock::new();
        let forced = *CHOICE.get_or_init(|| match std::env::var("RAYFARM_HUGEPAGES") {
            Ok(v) if matches!(v.trim(), "0" | "off" | "false" | "no") => {
                tracing::info!("domain files mapped, not copied into huge pages");
                Some(Residence::Mapped)
            }
            Ok(v) if matches!(v.trim(), "1" | "on" | "true" | "yes") => {
                tracing::info!("every domain file copied into huge pages");
                Some(Residence::HugePages)
            }
            _ => None,
        });
        forced.unwrap_or(if bytes >= HUGE_PAGE as u64 {
            Residence::HugePages
        } else {
            Residence::Mapped
        })
    }
}

/// A domain file's bytes: a mapping of the file, or a copy at an offset in an anonymous
/// region (`start`), aligned to a huge page. A copy's region goes back to the spare when the
/// bytes are dropped ([`Spare`]).
pub(super) struct Held {
    /// Always present; taken out only when the bytes are dropped.
    map: Option<Mmap>,
    start: Option<usize>,
    len: usize,
}

/// The anonymous region of a copied domain whose bytes were dropped (evicted), kept for the
/// next load of about its size. Reading a file into a fresh region makes the kernel fault in
/// and zero every page first: in a local render of big48 with caches of two domains
/// (`render --local --cache-bytes 5.7MiB`) that zeroing (`clear_page_erms`) was 45% of the
/// process's time. A spare region's pages are already backed, so the next load only copies.
/// One region at most, taken by the next load it fits: the process holds at most one
/// domain's memory beyond what its caches count.
struct Spare {
    region: MmapMut,
    start: usize,
}

static SPARE: Mutex<Option<Spare>> = Mutex::new(None);

fn spare() -> std::sync::MutexGuard<'static, Option<Spare>> {
    // The spare is a whole region or none: a panic while holding the lock leaves it usable.
    SPARE.lock().unwrap_or_else(|p| p.into_inner())
}

/// Anonymous memory for `len` bytes advised `MADV_HUGEPAGE`, and the offset in it of a 2 MiB
/// boundary where they start: one huge page more than `len`, so that the bytes can start on
/// the boundary (pages of the slack that are never touched are never allocated). The spare
/// region when it holds `len` bytes and is no more than a huge page larger than a fresh
/// one would be (so a small domain never keeps a large one's pages), else a fresh region.
fn huge_page_region(len: usize) -> std::io::Result<(MmapMut, usize)> {
    let region = len
        .checked_add(HUGE_PAGE)
        .ok_or(std::io::ErrorKind::FileTooLarge)?;
    {
        let mut spare = spare();
        let fits = |s: &Spare| {
            s.region.len() - s.start >= len && s.region.len() <= region.saturating_add(HUGE_PAGE)
        };
        if let Some(s) = spare.take_if(|s| fits(s)) {
            return Ok((s.region, s.start));
        }
    }
    let map = MmapOptions::new().len(region).map_anon()?;
    // Best effort: without transparent huge pages (`never`) the bytes are still correct.
    #[cfg(target_os = "linux")]
    if let Err(e) = map.advise(memmap2::Advice::HugePage) {
        tracing::debug!("madvise(MADV_HUGEPAGE) refused: {e}");
    }
    let start = map.as_ptr().align_offset(HUGE_PAGE).min(HUGE_PAGE);
    Ok((map, start))
}

impl Held {
    /// A copy of `bytes` in anonymous memory, mapped read-only (tests and fuzzing read domain
    /// files from memory).
    pub(super) fn copy_of(bytes: &[u8]) -> std::io::Result<Held> {
        let mut map = MmapOptions::new().len(bytes.len().max(1)).map_anon()?;
        map[..bytes.len()].copy_from_slice(bytes);
        Ok(Held {
            map: Some(map.make_read_only()?),
            start: None,
            len: bytes.len(),
        })
    }

    /// How these bytes are held: copied into huge pages, or mapped (from the file, or, for a
    /// received file, anonymous memory of ordinary pages).
    pub(super) fn residence(&self) -> Residence {
        if self.start.is_some() {
            Residence::HugePages
        } else {
            Residence::Mapped
        }
    }

    /// Holds `file` (`len` bytes long) as `residence` says.
    pub(super) fn load(
        mut file: std::fs::File,
        len: u64,
        residence: Residence,
    ) -> std::io::Result<Held> {
        let len = usize::try_from(len).map_err(|_| std::io::ErrorKind::FileTooLarge)?;
        if residence == Residence::Mapped || len == 0 {
            // SAFETY: domain files are written once, then renamed into place and never
            // modified; a file changed under us is a broken deployment, and every value read
            // is bounds-checked.
            let map = unsafe { Mmap::map(&file) }?;
            let len = map.len();
            return Ok(Held {
                map: Some(map),
                start: None,
                len,
            });
        }
        let (mut anon, start) = huge_page_region(len)?;
        std::io::Read::read_exact(&mut file, &mut anon[start..start + len])?;
        // A file that grew since its size was read is a file changed under us: refused, as
        // its checksum would be.
        let mut probe = [0u8; 1];
        if std::io::Read::read(&mut file, &mut probe)? != 0 {
            return Err(std::io::Error::other("the file grew while it was read"));
        }
        Ok(Held {
            map: Some(anon.make_read_only()?),
            start: Some(start),
            len,
        })
    }
}

impl Drop for Held {
    /// A copy's region becomes the spare, unless one is kept already.
    fn drop(&mut self) {
        let (Some(start), Some(map)) = (self.start, self.map.take()) else {
            return;
        };
        let mut spare = spare();
        if spare.is_none()
            && let Ok(region) = map.make_mut()
        {
            *spare = Some(Spare { region, start });
        }
    }
}

/// A domain file's bytes arriving in order from elsewhere (a peer), written straight into
/// memory held as a load from storage would hold them ([`Residence`]: a file of a huge page
/// or more into 2 MiB-aligned memory advised `MADV_HUGEPAGE`), so a domain from a peer
/// traces exactly like one from storage. Never holds more than the length it was made for.
pub struct Received {
    map: memmap2::MmapMut,
    start: usize,
    len: usize,
    written: usize,
    huge: bool,
}

impl Received {
    /// Room for a file of `len` bytes, held as `residence` says (`None`: as the process
    /// chooses for that size, [`Residence::selected`]).
    pub fn new(len: u64, residence: Option<Residence>) -> std::io::Result<Received> {
        let residence = residence.unwrap_or_else(|| Residence::selected(len));
        let len = usize::try_from(len).map_err(|_| std::io::ErrorKind::FileTooLarge)?;
        let huge = residence == Residence::HugePages && len > 0;
        let (map, start) = if huge {
            huge_page_region(len)?
        } else {
            (MmapOptions::new().len(len.max(1)).map_anon()?, 0)
        };
        Ok(Received {
            map,
            start,
            len,
            written: 0,
            huge,
        })
    }

    /// Appends `chunk`; refused if it would run past the length.
    pub fn push(&mut self, chunk: &[u8]) -> Result<(), String> {
        let end = self
            .written
            .checked_add(chunk.len())
            .filter(|&e| e <= self.len)
            .ok_or_else(|| {
                format!(
                    "{} more bytes after {} of a {} byte file",
                    chunk.len(),
                    self.written,
                    self.len
                )
            })?;
        self.map[self.start + self.written..self.start + end].copy_from_slice(chunk);
        self.written = end;
        Ok(())
    }

    /// Bytes written so far.
    pub fn written(&self) -> u64 {
        self.written as u64
    }

    /// Bytes still missing.
    pub fn missing(&self) -> u64 {
        (self.len - self.written) as u64
    }

    pub(super) fn into_held(self) -> std::io::Result<Held> {
        if self.written != self.len {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                format!("{} of {} bytes arrived", self.written, self.len),
            ));
        }
        Ok(Held {
            map: Some(self.map.make_read_only()?),
            // Reported as huge-page resident only when it was copied into such memory.
            start: self.huge.then_some(self.start),
            len: self.len,
        })
    }
}

impl std::ops::Deref for Held {
    type Target = [u8];

    fn deref(&self) -> &[u8] {
        let start = self.start.unwrap_or(0);
        self.map
            .as_ref()
            .map_or(&[][..], |m| &m[start..start + self.len])
    }
}

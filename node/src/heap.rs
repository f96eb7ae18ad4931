//! Keeping a long-running server's heap what it uses: few allocator arenas, and free memory
//! given back to the system between frames.
//!
//! glibc's malloc keeps freed memory in its arenas (one per thread that allocated, up to eight
//! per core) for reuse, and returns little of it on its own. Once a frame's ray queues,
//! bundles and passes are gone, much of a worker's heap is such free memory: its resident
//! memory steps up to each arena's high-water mark and stays there (a worker's anonymous
//! memory went 13 -> 55 MiB over an hour's soak, and a trim by hand gave half of a busy
//! worker's back). Trimming at the end of each frame returns it, so what a process holds
//! between frames is what it uses, and memory that grows with the jobs is a leak.

/// Returns the allocator's free memory to the system (glibc's `malloc_trim`); elsewhere
/// nothing. It walks every arena, a few milliseconds: call it once per frame, off the async
/// runtime.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim has no preconditions: it takes each arena's lock and releases
    // free pages; any thread may call it at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// What the allocator holds for the program, bytes: what is allocated now, and what is freed
/// but kept for reuse. A heap whose `in_use` stays flat while the process's anonymous memory
/// grows is fragmenting, not leaking.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HeapUsage {
    /// Bytes in allocations not yet freed (from arenas and from their own mappings).
    pub in_use: u64,
    /// Bytes freed but kept in the arenas.
    pub free: u64,
}

/// The allocator's figures (glibc's `mallinfo2`, summed over every arena); `None` elsewhere.
/// It walks each arena's free lists under the arena's lock, microseconds with two arenas:
/// fine at each scrape, not per allocation.
pub fn usage() -> Option<HeapUsage> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallinfo2 has no preconditions; it only reads the allocator's state.
        let info = unsafe { libc::mallinfo2() };
        // uordblks: allocated from the arenas; hblkhd: allocated in mappings of their own.
        let in_use = info.uordblks as u64 + info.hblkhd as u64;
        Some(HeapUsage {
            in_use,
            free: info.fordblks as u64,
        })
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    None
}

/// Allocator arenas a server keeps (see [`limit_arenas`]).
pub const ARENAS: i32 = 2;

/// Caps glibc's malloc at [`ARENAS`] arenas (`mallopt(M_ARENA_MAX)`); elsewhere nothing. By
/// default glibc adds arenas as threads contend, up to eight per core, and each grows to its
/// own high-water mark: a server whose tokio blocking threads come and go (store reads,
/// trims, passes) reaches its steady heap only after thousands of jobs, in steps that look
/// like a leak. In CI's 150 s soak the heap floor grew over the second half by 33% on the
/// coordinator and 37% on a worker with the default arenas, and by 4% and 0% with two, at
/// half the memory; the hour-long run's coordinator took 2,000 jobs to level off. An
/// operator's own `MALLOC_ARENA_MAX` (which glibc reads at start) is left as it is. Call it
/// first thing in `main`, before any thread starts.
pub fn limit_arenas() {
    if std::env::var_os("MALLOC_ARENA_MAX").is_some() {
        return;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a tunable of the allocator; called before other threads
    // exist, nothing allocates concurrently.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, ARENAS);
    }
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    #[test]
    fn usage_counts_an_allocation_while_it_lives() {
        let before = usage().expect("glibc").in_use;
        // Larger than glibc's mmap threshold, so it is its own mapping, counted in hblkhd.
        let block = vec![1u8; 64 << 20];
        let during = usage().expect("glibc").in_use;
        assert!(during >= before + (64 << 20), "{before} -> {during}");
        drop(std::hint::black_box(block));
        let after = usage().expect("glibc").in_use;
        assert!(after + (64 << 20) <= during, "{during} -> {after}");
    }
}

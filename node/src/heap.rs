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

/// Allocator arenas a server keeps (see [`limit_arenas`]).
pub const ARENAS: i32 = 2;

/// Caps glibc's malloc at [`ARENAS`] arenas (`mallopt(M_ARENA_MAX)`); elsewhere nothing. By
/// default glibc adds arenas as threads contend, up to eight per core, and each grows to its
/// own high-water mark: a server whose tokio blocking threads come and go (store reads,
/// trims, passes) reaches its steady heap only after thousands of jobs, in steps that look
/// like a leak. In CI's 150 s soak the heap floor grew over the second half by 33% on the
/// coordinator and 37% on a worker with the default arenas, and by 4% and 0% with two, at
/// half the memory; the hour-long run's coordinator took 2,000 jobs to level off. Call it
/// first thing in `main`, before any thread starts.
pub fn limit_arenas() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a tunable of the allocator; called before other threads
    // exist, nothing allocates concurrently.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, ARENAS);
    }
}

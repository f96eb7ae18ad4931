//! Giving the allocator's free memory back to the system between frames.
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

//! The heap a manifest's parse takes at its peak: `Manifest::load` of `DIR/scene.toml` under
//! an allocator that counts live bytes (README "Scenes": the manifest cap).
//!
//! `cargo run --release -p rayfarm-core --example manifest_memory -- DIR`

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayfarm_core::scene::Manifest;

/// The system allocator, counting live bytes and their peak.
struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call goes to the system allocator unchanged; only counters are added.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

fn main() {
    let Some(dir) = std::env::args_os().nth(1) else {
        eprintln!("usage: manifest_memory SCENE_DIR");
        std::process::exit(2);
    };
    let before = LIVE.load(Ordering::Relaxed);
    PEAK.store(before, Ordering::Relaxed);
    let start = std::time::Instant::now();
    let manifest = match Manifest::load(std::path::Path::new(&dir)) {
        Ok(m) => m,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
    };
    let took = start.elapsed();
    let mib = |b: usize| b as f64 / (1 << 20) as f64;
    let file = std::fs::metadata(std::path::Path::new(&dir).join("scene.toml"))
        .map(|m| m.len())
        .unwrap_or(0);
    println!(
        "{} domains, manifest {:.1} MiB: parse peak {:.1} MiB of heap, {:.1} MiB kept, {:.2} s",
        manifest.domains.len(),
        mib(file as usize),
        mib(PEAK.load(Ordering::Relaxed) - before),
        mib(LIVE.load(Ordering::Relaxed) - before),
        took.as_secs_f64()
    );
}

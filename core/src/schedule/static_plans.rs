//! The two static baselines of Navrátil et al. (Section 4.2).
//!
//! Both decide once, before any ray is traced, and never look at queues:
//! - image-plane decomposition (Fig. 3): each worker traces a contiguous share
//!   of the image and loads whatever data its own rays need;
//! - domain decomposition (Fig. 4): domains are dealt to workers round robin
//!   and rays travel to the owner of the domain they enter.

use std::ops::Range;

use super::DomainId;

/// The contiguous range of pixel indices (row-major) that worker number
/// `worker_index` of `workers` traces under the image-plane schedule.
///
/// Shares differ in size by at most one pixel and together cover `0..pixels`
/// exactly once, in worker order, so per-worker framebuffers merge without
/// overlap (the paper's `MergeFramebuffers`).
///
/// # Panics
/// If `workers` is zero or `worker_index >= workers`: there is no share to
/// give, and silently returning an empty range would lose pixels.
pub fn image_plane_share(worker_index: u32, workers: u32, pixels: u32) -> Range<u32> {
    assert!(workers > 0, "image_plane_share needs at least one worker");
    assert!(
        worker_index < workers,
        "worker index {worker_index} out of range for {workers} workers"
    );
    share_start(worker_index, workers, pixels)..share_start(worker_index + 1, workers, pixels)
}

/// First pixel of share `index`; widened to u64 because `index * pixels`
/// overflows u32 for ordinary image sizes and worker counts.
fn share_start(index: u32, workers: u32, pixels: u32) -> u32 {
    let start = u64::from(index) * u64::from(pixels) / u64::from(workers);
    u32::try_from(start).expect("a share never starts past the last pixel")
}

/// Index of the worker that owns `domain` under the static domain schedule:
/// domains are dealt round robin (Section 4.2, "typically in round-robin
/// order"), so a worker may own several domains, or none when there are more
/// workers than domains.
///
/// # Panics
/// If `workers` is zero.
pub fn domain_owner(domain: DomainId, workers: u32) -> u32 {
    assert!(workers > 0, "domain_owner needs at least one worker");
    domain.0 % workers
}

/// The hybrid schedule's condition for demand-driven loads on one worker: its cache of
/// `cache_bytes` holds the domains it owns (`owned_bytes`) and still has room for the largest
/// other domain (`largest_bytes`), so a domain loaded on demand never pushes owned
/// (data-parallel) data out. The coordinator asks it of every worker before a frame
/// ([`owned_domains_fit`]), a worker of itself once it knows what it owns.
pub fn demand_loads_fit(cache_bytes: u64, owned_bytes: u64, largest_bytes: u64) -> bool {
    cache_bytes >= owned_bytes.saturating_add(largest_bytes)
}

/// Whether the domain schedule's owner map ([`domain_owner`]) leaves every cache (`caches`,
/// one a worker, in worker order) room for its owned domains plus the largest other
/// ([`demand_loads_fit`]); `domain_bytes` are the domains' sizes in domain order.
pub fn owned_domains_fit(domain_bytes: &[u64], caches: &[u64]) -> bool {
    let n = caches.len().max(1) as u32;
    let largest = domain_bytes.iter().copied().max().unwrap_or(0);
    let mut owned = vec![0u64; n as usize];
    for (d, &bytes) in domain_bytes.iter().enumerate() {
        owned[domain_owner(DomainId(d as u32), n) as usize] += bytes;
    }
    caches
        .iter()
        .zip(&owned)
        .all(|(&cache, &own)| demand_loads_fit(cache, own, largest))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn owned_domains_fit_when_each_cache_holds_its_share_and_the_largest_other() {
        // Four domains of 100 over two workers: each owns 200 and needs 100 more.
        assert!(owned_domains_fit(&[100; 4], &[300, 300]));
        assert!(!owned_domains_fit(&[100; 4], &[299, 300]));
        // Worker 0 owns domains 0 and 2 (500), worker 1 domains 1 and 3 (20); largest 400.
        assert!(owned_domains_fit(&[400, 10, 100, 10], &[900, 420]));
        assert!(!owned_domains_fit(&[400, 10, 100, 10], &[899, 420]));
        // One worker's own test is the same rule.
        assert!(demand_loads_fit(900, 500, 400) && !demand_loads_fit(899, 500, 400));
        assert!(!demand_loads_fit(u64::MAX - 1, u64::MAX, 1), "no overflow");
    }

    #[test]
    fn image_plane_shares_are_contiguous_and_balanced() {
        let shares: Vec<_> = (0..3).map(|i| image_plane_share(i, 3, 10)).collect();
        assert_eq!(shares, [0..3, 3..6, 6..10]);
    }

    #[test]
    fn image_plane_share_survives_large_images() {
        let last = image_plane_share(63, 64, u32::MAX);
        assert_eq!(last.end, u32::MAX);
    }

    #[test]
    fn more_workers_than_pixels_leaves_some_idle() {
        let sizes: Vec<_> = (0..4).map(|i| image_plane_share(i, 4, 2).len()).collect();
        assert_eq!(sizes.iter().sum::<usize>(), 2);
        assert!(sizes.iter().all(|&n| n <= 1));
    }

    #[test]
    #[should_panic(expected = "out of range")]
    fn image_plane_share_rejects_bad_index() {
        let _ = image_plane_share(3, 3, 10);
    }

    #[test]
    fn domains_are_dealt_round_robin() {
        let owners: Vec<_> = (0..7).map(|d| domain_owner(DomainId(d), 3)).collect();
        assert_eq!(owners, [0, 1, 2, 0, 1, 2, 0]);
    }

    proptest! {
        #[test]
        fn image_plane_shares_tile_the_image(workers in 1u32..200, pixels in any::<u32>()) {
            let mut next = 0;
            for i in 0..workers {
                let share = image_plane_share(i, workers, pixels);
                prop_assert_eq!(share.start, next);
                let len = u64::from(share.end - share.start);
                let even = u64::from(pixels) / u64::from(workers);
                prop_assert!(len == even || len == even + 1);
                next = share.end;
            }
            prop_assert_eq!(next, pixels);
        }
    }
}

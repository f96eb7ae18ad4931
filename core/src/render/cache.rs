//! The domain cache: mapped domain files under a byte budget, least recently used out first.
//! A domain larger than the whole budget is still loaded, alone. An evicted domain is really
//! gone: unmapped, and its pages dropped from the page cache, so loading it again reads
//! storage. Slower shared storage can be emulated ([`StorageModel`]) to study schedules in
//! the regime where loading dominates.
//!
//! A domain may also be loaded ahead of need (a prefetch): [`DomainCache::begin_prefetch`]
//! decides under the cache's lock whether it fits without evicting what must stay, the I/O
//! ([`PendingLoad::read`]) runs without the lock while passes go on tracing, and
//! [`DomainCache::finish_prefetch`] adds it. Prefetches count as loads, and separately as used
//! (a pass asked for the domain before it left) or wasted (it left unused).
//!
//! A load may take the domain's bytes from a peer that has it loaded instead of storage
//! ([`peers`]: when that is cheaper, checked like a file from storage, falling back to
//! storage); such loads count as loads like any other, and apart (`bytes_from_peers`). The
//! domains resident here are also on a [`Shelf`] that this worker's peer service reads
//! without the cache's lock (a pass may hold it through a slow load).
//!
//! Apart from the cache itself, a module each: its counters (`counters`), the emulated
//! storage (`storage`), where a load reads a domain from and a prefetch's read off the lock
//! (`load`), and the shelf the peer service reads (`shelf`).

mod counters;
mod load;
pub mod peers;
mod shared;
mod shelf;
mod storage;

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use tracing::{debug, info_span};

use crate::scene::{DomainData, Manifest, SceneError};
use load::Source;
use peers::{Origin, PeerLoads};
use storage::StorageLine;

pub use counters::CacheCounters;
pub use load::{LoadedDomain, PendingLoad};
pub use shared::SharedMappings;
pub use shelf::Shelf;
pub use storage::StorageModel;

/// `posix_fadvise(DONTNEED)` on a whole file: clean pages leave the page cache.
fn drop_page_cache(path: &std::path::Path) -> std::io::Result<()> {
    let file = std::fs::File::open(path)?;
    rustix::fs::fadvise(&file, 0, None, rustix::fs::Advice::DontNeed)?;
    Ok(())
}

/// A mapped domain and when it was last asked for.
struct Resident {
    data: Arc<DomainData>,
    last_use: u64,
    /// Loaded by a prefetch and not asked for since.
    prefetched: bool,
}

/// Domains of one scene, loaded on demand. It keeps state only for the domains it holds or
/// has verified, so many caches over one shared manifest (the simulator's workers) cost
/// memory for what they hold, not for the scene's domain count.
pub struct DomainCache {
    dir: PathBuf,
    manifest: Arc<Manifest>,
    /// Loading from peers, when on.
    peers: Option<Arc<PeerLoads>>,
    /// The resident domains again, for the peer service.
    shelf: Shelf,
    budget: u64,
    resident: BTreeMap<u32, Resident>,
    /// Domains whose checksum was verified (on their first load).
    verified: BTreeSet<u32>,
    clock: u64,
    resident_bytes: u64,
    counters: CacheCounters,
    storage: StorageLine,
    /// Domains the least-recently-used rule must not evict (a schedule's owned data).
    pinned: BTreeSet<u32>,
    /// Leave the operating system's page cache alone when a domain is evicted.
    keep_page_cache: bool,
    /// Where other caches of this process share their mappings, if they do.
    mappings: Option<Arc<SharedMappings>>,
}

impl DomainCache {
    /// A cache for the scene in `dir` holding at most `budget` bytes of domains.
    pub fn new(dir: impl Into<PathBuf>, manifest: &Manifest, budget: u64) -> Self {
        Self::shared(dir, Arc::new(manifest.clone()), budget)
    }

    /// A cache like [`DomainCache::new`]'s over a manifest shared with others.
    pub fn shared(dir: impl Into<PathBuf>, manifest: Arc<Manifest>, budget: u64) -> Self {
        DomainCache {
            dir: dir.into(),
            manifest,
            peers: None,
            shelf: Shelf::default(),
            budget,
            resident: BTreeMap::new(),
            verified: BTreeSet::new(),
            clock: 0,
            resident_bytes: 0,
            counters: CacheCounters::default(),
            storage: StorageLine::default(),
            pinned: Default::default(),
            keep_page_cache: false,
            mappings: None,
        }
    }

    /// The cache leaving the operating system's page cache alone on eviction. A worker drops
    /// an evicted domain's pages so that its next load pays for the read as it would on a
    /// cold node; many caches over one scene in one process (the simulator, whose loads are
    /// priced by its storage model, not by the disk) would only make every other cache's
    /// next load of that domain read the disk for real, and pay a system call an eviction
    /// (19% of a 1,024-worker image-plane simulation's time).
    pub fn keep_page_cache(mut self) -> Self {
        self.keep_page_cache = true;
        self
    }

    /// The cache mapping its domains through `mappings`, shared with other caches of this
    /// process over the same scene: one mapping of a domain for all of them (the simulator's
    /// workers). Its loads, evictions and counters are its own, as without it.
    pub fn with_shared_mappings(mut self, mappings: Arc<SharedMappings>) -> Self {
        self.mappings = Some(mappings);
        self
    }

    /// Protects `domains` from eviction by other loads (an explicit `evict` still drops
    /// them); replaces the previous set.
    pub fn pin(&mut self, domains: impl IntoIterator<Item = u32>) {
        self.pinned = domains.into_iter().collect();
    }

    /// The cache with loads charged as on `storage`.
    pub fn with_storage(mut self, storage: StorageModel) -> Self {
        self.storage = StorageLine {
            model: storage,
            ..StorageLine::default()
        };
        self
    }

    /// Loads take domains from peers through `peers` when that is cheaper (`None`: storage
    /// only). Set per frame: it is a job's option.
    pub fn set_peers(&mut self, peers: Option<Arc<PeerLoads>>) {
        self.peers = peers;
    }

    /// The resident domains, for the peer service to read without this cache's lock.
    pub fn shelf(&self) -> Shelf {
        self.shelf.clone()
    }

    fn source(&self) -> Source {
        Source {
            dir: self.dir.clone(),
            manifest: self.manifest.clone(),
            storage: self.storage.clone(),
            peers: self.peers.clone(),
            mappings: self.mappings.clone(),
        }
    }

    /// Adds one load's origin to the counters.
    fn count_origin(&mut self, origin: Origin, bytes: u64) {
        if origin.from_peer {
            self.counters.peer_loads += 1;
            self.counters.bytes_from_peers += bytes;
        }
        if origin.peer_failed {
            self.counters.peer_failures += 1;
        }
        if origin.peer_refused {
            self.counters.peer_refusals += 1;
        }
    }

    /// The domain, mapping it (and evicting others) if needed. Its checksum is verified the
    /// first time it is loaded (and always when its bytes come from a peer).
    pub fn get(&mut self, domain: u32) -> Result<Arc<DomainData>, SceneError> {
        let i = domain as usize;
        self.clock += 1;
        if let Some(d) = self.resident.get_mut(&domain) {
            d.last_use = self.clock;
            if std::mem::take(&mut d.prefetched) {
                self.counters.prefetches_used += 1;
            }
            return Ok(d.data.clone());
        }
        let _span =
            info_span!("load_domain", domain, file = %self.manifest.domains[i].file).entered();
        debug!("loading domain");
        let started = Instant::now();
        let (data, origin) = self
            .source()
            .read(domain, !self.verified.contains(&domain))?;
        // A peer's bytes were verified, the file on storage was not.
        if !origin.from_peer {
            self.verified.insert(domain);
        }
        let bytes = data.bytes();
        self.count_origin(origin, bytes);
        self.evict_for(bytes, |j| j == domain);
        self.counters.load_nanos += started.elapsed().as_nanos() as u64;
        Ok(self.insert(domain, data, false))
    }

    /// Maps `data` as `domain`, counted as a load.
    fn insert(&mut self, domain: u32, data: Arc<DomainData>, prefetched: bool) -> Arc<DomainData> {
        let bytes = data.bytes();
        self.resident_bytes += bytes;
        self.counters.loads += 1;
        self.counters.bytes_loaded += bytes;
        self.counters.peak_resident_bytes =
            self.counters.peak_resident_bytes.max(self.resident_bytes);
        debug!(
            bytes,
            resident = self.resident_bytes,
            prefetched,
            "domain loaded"
        );
        self.shelf.lock().insert(domain, data.clone());
        let last_use = self.clock;
        self.resident.insert(
            domain,
            Resident {
                data: data.clone(),
                last_use,
                prefetched,
            },
        );
        data
    }

    /// Starts loading `domain` ahead of need, if it is not mapped and fits in the budget
    /// once domains outside `keep` (and not pinned) are counted as free: a prefetch never
    /// pushes out what the current plan needs. The load itself is [`PendingLoad::read`], off
    /// this cache's lock; [`DomainCache::finish_prefetch`] adds it.
    pub fn begin_prefetch(&self, domain: u32, keep: &BTreeSet<u32>) -> Option<PendingLoad> {
        let entry = self.manifest.domains.get(domain as usize)?;
        if self.resident.contains_key(&domain) {
            return None;
        }
        let staying: u64 = self
            .resident
            .iter()
            .filter(|&(j, _)| keep.contains(j) || self.pinned.contains(j))
            .map(|(_, r)| r.data.bytes())
            .sum();
        if staying + entry.bytes > self.budget {
            return None;
        }
        Some(PendingLoad {
            domain,
            source: self.source(),
            verify: !self.verified.contains(&domain),
        })
    }

    /// Adds a prefetched domain, evicting least recently used domains outside `keep` (and
    /// not pinned) to make room. Returns false if it was not kept: a pass mapped it
    /// meanwhile, or what must stay leaves no room for it now (it counts as wasted).
    pub fn finish_prefetch(&mut self, loaded: LoadedDomain, keep: &BTreeSet<u32>) -> bool {
        let LoadedDomain {
            domain,
            data,
            nanos,
            origin,
        } = loaded;
        self.count_origin(origin, data.bytes());
        self.counters.prefetches += 1;
        self.counters.prefetch_nanos += nanos;
        if !origin.from_peer {
            self.verified.insert(domain);
        }
        let bytes = data.bytes();
        let fits = |c: &Self| c.resident_bytes + bytes <= c.budget;
        if self.resident.contains_key(&domain) {
            // Read twice: the prefetch's copy is the one wasted.
            self.counters.loads += 1;
            self.counters.bytes_loaded += bytes;
            self.counters.prefetches_wasted += 1;
            return false;
        }
        self.evict_for(bytes, |j| keep.contains(&j));
        if !fits(self) {
            self.counters.loads += 1;
            self.counters.bytes_loaded += bytes;
            self.counters.prefetches_wasted += 1;
            debug!(domain, "prefetched domain found no room");
            return false;
        }
        self.clock += 1;
        self.insert(domain, data, true);
        true
    }

    /// Evicts least recently used domains, other than pinned ones and those `stays` names,
    /// until `incoming` bytes fit (or nothing more may go).
    fn evict_for(&mut self, incoming: u64, stays: impl Fn(u32) -> bool) {
        while self.resident_bytes + incoming > self.budget {
            let victim = self
                .resident
                .iter()
                .filter(|&(&j, _)| !stays(j) && !self.pinned.contains(&j))
                .min_by_key(|(_, r)| r.last_use)
                .map(|(&j, _)| j);
            let Some(j) = victim else { break };
            self.drop_domain(j);
        }
    }

    /// Unmaps a resident domain and asks the kernel to drop its pages from the page cache,
    /// so that a later load costs a read from storage, as it would on a cluster.
    fn drop_domain(&mut self, domain: u32) {
        let Some(d) = self.resident.remove(&domain) else {
            return;
        };
        self.shelf.lock().remove(&domain);
        self.resident_bytes -= d.data.bytes();
        self.counters.evictions += 1;
        if d.prefetched {
            self.counters.prefetches_wasted += 1;
        }
        drop(d);
        let i = domain as usize;
        if !self.keep_page_cache {
            let path = self.dir.join(&self.manifest.domains[i].file);
            if let Err(e) = drop_page_cache(&path) {
                debug!(domain = i, error = %e, "page cache not dropped");
            }
        }
        debug!(domain = i, "domain evicted");
    }

    /// Unmaps every domain (a frame that must pay for all its loads).
    pub fn clear(&mut self) {
        let all: Vec<u32> = self.resident.keys().copied().collect();
        for d in all {
            self.drop_domain(d);
        }
    }

    /// Drops `domain` from the cache if it is resident (the schedule asked for its slot).
    pub fn evict(&mut self, domain: u32) {
        self.drop_domain(domain);
    }

    /// Size of every domain file of the scene, by domain id.
    pub fn domain_bytes(&self) -> Arc<[u64]> {
        self.manifest.domains.iter().map(|d| d.bytes).collect()
    }

    /// Domains mapped now, least recently used first: the order in which the coordinator
    /// evicts those no ray wants (the worker reports them so).
    pub fn resident(&self) -> Vec<u32> {
        let mut by_use: Vec<(u64, u32)> = self
            .resident
            .iter()
            .map(|(&d, r)| (r.last_use, d))
            .collect();
        by_use.sort_unstable();
        by_use.into_iter().map(|(_, d)| d).collect()
    }

    /// The counters so far.
    pub fn counters(&self) -> CacheCounters {
        self.counters
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prepare::generate::{NbodyOptions, prepare_nbody};
    use std::path::Path;

    /// A small generated scene of four domains, prepared in `dir`.
    pub(super) fn four_domains(dir: &Path) -> Manifest {
        let options = NbodyOptions {
            name: "nb".into(),
            triangles: 2000,
            seed: 1,
            domains: 4,
            max_memory: None,
            force: false,
        };
        prepare_nbody(dir, &options).unwrap()
    }

    #[test]
    fn resident_domains_are_listed_least_recently_used_first() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("nb");
        let manifest = four_domains(&dir);
        let mut cache = DomainCache::new(&dir, &manifest, u64::MAX);
        for d in [2, 0, 3, 0] {
            cache.get(d).unwrap();
        }
        // The coordinator evicts in this order: 0, used last, goes last.
        assert_eq!(cache.resident(), [2, 3, 0]);
    }
}

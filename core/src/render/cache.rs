//! The domain cache: mapped domain files under a byte budget, least recently used out first.
//! A domain larger than the whole budget is still loaded, alone. An evicted domain is really
//! gone: unmapped, and its pages dropped from the page cache, so loading it again reads
//! storage. Slower shared storage can be emulated ([`StorageModel`]) to study schedules in
//! the regime where loading dominates.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tracing::{debug, info_span};

use crate::scene::{DomainData, Manifest, SceneError};

/// Loads, evictions and bytes, for the statistics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CacheCounters {
    /// Domain files mapped.
    pub loads: u64,
    /// Bytes of the domain files mapped.
    pub bytes_loaded: u64,
    /// Domains dropped to stay under the budget.
    pub evictions: u64,
    /// Largest number of bytes resident at once.
    pub peak_resident_bytes: u64,
    /// Time spent loading (mapping, checking, emulated storage delay), nanoseconds.
    #[serde(default)]
    pub load_nanos: u64,
}

/// An emulation of slower shared storage, charged on every load: `latency` plus the file's
/// bytes at `bandwidth`. For benchmarks only; it makes a load cost what it would on a
/// cluster's network file system.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StorageModel {
    /// Bytes per second; `None` is unlimited.
    pub bandwidth: Option<u64>,
    /// Fixed cost of each load.
    pub latency: Duration,
}

impl StorageModel {
    /// The emulated time to load `bytes`.
    pub fn delay(&self, bytes: u64) -> Duration {
        let transfer = self
            .bandwidth
            .filter(|&b| b > 0)
            .map_or(Duration::ZERO, |b| {
                Duration::from_secs_f64(bytes as f64 / b as f64)
            });
        self.latency + transfer
    }

    /// Whether any delay is added.
    pub fn is_active(&self) -> bool {
        self.bandwidth.is_some() || !self.latency.is_zero()
    }
}

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
}

/// Domains of one scene, loaded on demand. It keeps state only for the domains it holds or
/// has verified, so many caches over one shared manifest (the simulator's workers) cost
/// memory for what they hold, not for the scene's domain count.
pub struct DomainCache {
    dir: PathBuf,
    manifest: Arc<Manifest>,
    budget: u64,
    resident: BTreeMap<u32, Resident>,
    /// Domains whose checksum was verified (on their first load).
    verified: BTreeSet<u32>,
    clock: u64,
    resident_bytes: u64,
    counters: CacheCounters,
    storage: StorageModel,
    /// Domains the least-recently-used rule must not evict (a schedule's owned data).
    pinned: BTreeSet<u32>,
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
            budget,
            resident: BTreeMap::new(),
            verified: BTreeSet::new(),
            clock: 0,
            resident_bytes: 0,
            counters: CacheCounters::default(),
            storage: StorageModel::default(),
            pinned: Default::default(),
        }
    }

    /// Protects `domains` from eviction by other loads (an explicit `evict` still drops
    /// them); replaces the previous set.
    pub fn pin(&mut self, domains: impl IntoIterator<Item = u32>) {
        self.pinned = domains.into_iter().collect();
    }

    /// The cache with loads charged as on `storage`.
    pub fn with_storage(mut self, storage: StorageModel) -> Self {
        self.storage = storage;
        self
    }

    /// The domain, mapping it (and evicting others) if needed. Its checksum is verified the
    /// first time it is loaded.
    pub fn get(&mut self, domain: u32) -> Result<Arc<DomainData>, SceneError> {
        let i = domain as usize;
        self.clock += 1;
        if let Some(d) = self.resident.get_mut(&domain) {
            d.last_use = self.clock;
            return Ok(d.data.clone());
        }
        let _span =
            info_span!("load_domain", domain, file = %self.manifest.domains[i].file).entered();
        debug!("loading domain");
        let started = Instant::now();
        let data =
            self.manifest
                .open_domain(&self.dir, domain, !self.verified.contains(&domain))?;
        if self.storage.is_active() {
            std::thread::sleep(self.storage.delay(data.bytes()));
        }
        self.verified.insert(domain);
        let bytes = data.bytes();
        self.evict_for(bytes, domain);
        self.resident_bytes += bytes;
        self.counters.loads += 1;
        self.counters.bytes_loaded += bytes;
        self.counters.peak_resident_bytes =
            self.counters.peak_resident_bytes.max(self.resident_bytes);
        self.counters.load_nanos += started.elapsed().as_nanos() as u64;
        debug!(bytes, resident = self.resident_bytes, "domain loaded");
        let data = Arc::new(data);
        let last_use = self.clock;
        self.resident.insert(
            domain,
            Resident {
                data: data.clone(),
                last_use,
            },
        );
        Ok(data)
    }

    fn evict_for(&mut self, incoming: u64, keep: u32) {
        while self.resident_bytes + incoming > self.budget {
            let victim = self
                .resident
                .iter()
                .filter(|&(&j, _)| j != keep && !self.pinned.contains(&j))
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
        self.resident_bytes -= d.data.bytes();
        self.counters.evictions += 1;
        drop(d);
        let i = domain as usize;
        let path = self.dir.join(&self.manifest.domains[i].file);
        if let Err(e) = drop_page_cache(&path) {
            debug!(domain = i, error = %e, "page cache not dropped");
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

    /// Domains mapped now, ascending.
    pub fn resident(&self) -> Vec<u32> {
        self.resident.keys().copied().collect()
    }

    /// The counters so far.
    pub fn counters(&self) -> CacheCounters {
        self.counters
    }
}

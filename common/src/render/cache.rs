//! The domain cache: mapped domain files under a byte budget, least recently used out first.
//! A domain larger than the whole budget is still loaded, alone.

use std::path::PathBuf;
use std::sync::Arc;

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
}

/// Domains of one scene, loaded on demand.
pub struct DomainCache {
    dir: PathBuf,
    manifest: Manifest,
    budget: u64,
    resident: Vec<Option<Arc<DomainData>>>,
    last_use: Vec<u64>,
    verified: Vec<bool>,
    clock: u64,
    resident_bytes: u64,
    counters: CacheCounters,
}

impl DomainCache {
    /// A cache for the scene in `dir` holding at most `budget` bytes of domains.
    pub fn new(dir: impl Into<PathBuf>, manifest: &Manifest, budget: u64) -> Self {
        let n = manifest.domains.len();
        DomainCache {
            dir: dir.into(),
            manifest: manifest.clone(),
            budget,
            resident: vec![None; n],
            last_use: vec![0; n],
            verified: vec![false; n],
            clock: 0,
            resident_bytes: 0,
            counters: CacheCounters::default(),
        }
    }

    /// The domain, mapping it (and evicting others) if needed. Its checksum is verified the
    /// first time it is loaded.
    pub fn get(&mut self, domain: u32) -> Result<Arc<DomainData>, SceneError> {
        let i = domain as usize;
        self.clock += 1;
        self.last_use[i] = self.clock;
        if let Some(d) = &self.resident[i] {
            return Ok(d.clone());
        }
        let _span =
            info_span!("load_domain", domain, file = %self.manifest.domains[i].file).entered();
        let data = self
            .manifest
            .open_domain(&self.dir, domain, !self.verified[i])?;
        self.verified[i] = true;
        let bytes = data.bytes();
        self.evict_for(bytes, domain);
        self.resident_bytes += bytes;
        self.counters.loads += 1;
        self.counters.bytes_loaded += bytes;
        self.counters.peak_resident_bytes =
            self.counters.peak_resident_bytes.max(self.resident_bytes);
        debug!(bytes, resident = self.resident_bytes, "domain loaded");
        let data = Arc::new(data);
        self.resident[i] = Some(data.clone());
        Ok(data)
    }

    fn evict_for(&mut self, incoming: u64, keep: u32) {
        while self.resident_bytes + incoming > self.budget {
            let victim = (0..self.resident.len())
                .filter(|&j| j != keep as usize && self.resident[j].is_some())
                .min_by_key(|&j| self.last_use[j]);
            let Some(j) = victim else { break };
            if let Some(d) = self.resident[j].take() {
                self.resident_bytes -= d.bytes();
                self.counters.evictions += 1;
                debug!(domain = j, "domain evicted");
            }
        }
    }

    /// Drops `domain` from the cache if it is resident (the schedule asked for its slot).
    pub fn evict(&mut self, domain: u32) {
        if let Some(d) = self
            .resident
            .get_mut(domain as usize)
            .and_then(Option::take)
        {
            self.resident_bytes -= d.bytes();
            self.counters.evictions += 1;
            debug!(domain, "domain evicted by plan");
        }
    }

    /// Domains mapped now, ascending.
    pub fn resident(&self) -> Vec<u32> {
        (0..)
            .zip(&self.resident)
            .filter(|(_, d)| d.is_some())
            .map(|(i, _)| i)
            .collect()
    }

    /// The counters so far.
    pub fn counters(&self) -> CacheCounters {
        self.counters
    }
}

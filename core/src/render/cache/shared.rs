//! One mapping of a domain for every cache of a process that asks for it: the simulator runs
//! a thousand workers' caches over one scene in one process, and if each mapped its own copy
//! of a domain the process would hold workers x domains mappings (over Linux's 65,530 a
//! process at 1,024 workers with about a hundred domains each) and pay a map, a structure
//! check and a checksum on every load. Each cache still decides, counts and evicts its own
//! loads exactly as before (it holds its own reference to the shared data); only the bytes
//! behind them are shared, so a cache's figures do not change.
//!
//! A domain stays mapped while any cache holds it (the map keeps a weak reference), so the
//! mappings follow the domains resident somewhere, never workers x domains. Its checksum is
//! verified the first time the process maps it; mapping it again after every holder let go
//! checks its structure again but not every byte (the file was hashed once by this process).

use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::sync::{Arc, Mutex, Weak};

use crate::scene::{DomainData, Manifest, SceneError};

/// Domains mapped once for many caches of one scene (see the module documentation). Give
/// every cache the same one with [`super::DomainCache::with_shared_mappings`].
#[derive(Default)]
pub struct SharedMappings {
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    /// Domains mapped by some cache, and maybe still held: an entry whose data was dropped
    /// is mapped again on the next open. At most one entry a domain of the scene.
    mapped: HashMap<u32, Weak<DomainData>>,
    /// Domains whose every byte this process has hashed.
    verified: BTreeSet<u32>,
    /// Times a domain file was mapped (not found held), for tests and statistics.
    maps: u64,
}

impl SharedMappings {
    /// No domain mapped yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The data of `domain` of the scene in `dir`: the mapping some cache holds, or a new one
    /// (`Manifest::open_domain`, its checksum verified if this process never verified it and
    /// `verify` asks for it).
    pub fn open(
        &self,
        manifest: &Manifest,
        dir: &Path,
        domain: u32,
        verify: bool,
    ) -> Result<Arc<DomainData>, SceneError> {
        // Mapping under the lock: two caches asking for the same domain at once must not
        // map it twice (passes of simulated workers run one at a time, so nobody waits).
        let mut s = self.state.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(data) = s.mapped.get(&domain).and_then(Weak::upgrade) {
            return Ok(data);
        }
        let verify = verify && !s.verified.contains(&domain);
        let data = Arc::new(manifest.open_domain(dir, domain, verify)?);
        if verify {
            s.verified.insert(domain);
        }
        s.maps += 1;
        s.mapped.insert(domain, Arc::downgrade(&data));
        Ok(data)
    }

    /// Domains mapped now (held by at least one cache or pass).
    pub fn mapped(&self) -> usize {
        let s = self.state.lock().unwrap_or_else(|p| p.into_inner());
        s.mapped.values().filter(|w| w.strong_count() > 0).count()
    }

    /// Times a domain file was mapped so far.
    pub fn maps(&self) -> u64 {
        self.state.lock().unwrap_or_else(|p| p.into_inner()).maps
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::cache::DomainCache;
    use crate::render::cache::tests::four_domains;

    #[test]
    fn caches_share_one_mapping_a_domain_and_count_their_own_loads() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("nb");
        let manifest = Arc::new(four_domains(&dir));
        let shared = Arc::new(SharedMappings::new());
        let cache = |budget| {
            DomainCache::shared(&dir, manifest.clone(), budget).with_shared_mappings(shared.clone())
        };
        // Room for no domain: each load is alone (a domain over the budget still loads) and
        // evicts the one before.
        let (mut a, mut b) = (cache(1), cache(1));
        let mut own = DomainCache::shared(&dir, manifest.clone(), 1);
        let da = a.get(0).unwrap();
        let db = b.get(0).unwrap();
        assert!(Arc::ptr_eq(&da, &db), "one mapping for both caches");
        assert_eq!((shared.maps(), shared.mapped()), (1, 1));
        drop((da, db));
        a.get(1).unwrap();
        assert_eq!(shared.mapped(), 2, "b still holds domain 0");
        b.get(1).unwrap();
        assert_eq!(
            (shared.maps(), shared.mapped()),
            (2, 1),
            "0 is gone from both"
        );
        a.get(0).unwrap();
        assert_eq!(shared.maps(), 3, "mapped again once nobody held it");
        for d in [0, 1, 0] {
            own.get(d).unwrap();
        }
        let (ca, cb, co) = (a.counters(), b.counters(), own.counters());
        assert_eq!((ca.loads, ca.evictions), (3, 2));
        assert_eq!((cb.loads, cb.evictions), (2, 1));
        assert_eq!(
            (
                ca.loads,
                ca.bytes_loaded,
                ca.evictions,
                ca.peak_resident_bytes
            ),
            (
                co.loads,
                co.bytes_loaded,
                co.evictions,
                co.peak_resident_bytes
            ),
            "the same loads as a cache of its own"
        );
    }
}

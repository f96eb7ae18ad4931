//! The domains resident in a cache, for this worker's peer service to serve without the
//! cache's lock.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::scene::DomainData;

/// The domains resident in a cache, readable without the cache's lock: what this worker's
/// peer service serves. A transfer holds its domain until it ends, even if the cache evicts
/// it meanwhile (the server bounds how many run at once).
#[derive(Clone, Default)]
pub struct Shelf(Arc<std::sync::Mutex<BTreeMap<u32, Arc<DomainData>>>>);

impl Shelf {
    /// The domain if it is resident now.
    pub fn get(&self, domain: u32) -> Option<Arc<DomainData>> {
        self.lock().get(&domain).cloned()
    }

    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u32, Arc<DomainData>>> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }
}

//! Where a cache reads a domain from (a peer that has it loaded, else storage) and a
//! prefetch's read, which runs off the cache's lock and is handed back to
//! [`super::DomainCache::finish_prefetch`].

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use tracing::info_span;

use super::SharedMappings;
use super::peers::{Origin, PeerError, PeerLoads};
use super::storage::StorageLine;
use crate::scene::{DomainData, Manifest, SceneError};

/// A prefetch under way: what [`PendingLoad::read`] needs to load the domain without the
/// cache.
pub struct PendingLoad {
    pub(super) domain: u32,
    pub(super) source: Source,
    pub(super) verify: bool,
}

/// A prefetched domain read from storage or a peer, for
/// [`super::DomainCache::finish_prefetch`].
pub struct LoadedDomain {
    pub(super) domain: u32,
    pub(super) data: Arc<DomainData>,
    pub(super) nanos: u64,
    pub(super) origin: Origin,
}

/// Where a cache reads domains from: the scene's directory on storage and, when loading
/// from peers is on, its peers. Cloned into prefetches, which read off the cache's lock.
#[derive(Clone)]
pub(super) struct Source {
    pub(super) dir: PathBuf,
    pub(super) manifest: Arc<Manifest>,
    pub(super) storage: StorageLine,
    pub(super) peers: Option<Arc<PeerLoads>>,
    /// Where other caches of this process share their mappings, if they do.
    pub(super) mappings: Option<Arc<SharedMappings>>,
}

impl Source {
    /// Reads `domain`: from a peer when [`peers`] decides so and the peer delivers (its
    /// checksum always verified), else from storage (verified if `verify`).
    pub(super) fn read(
        &self,
        domain: u32,
        verify: bool,
    ) -> Result<(Arc<DomainData>, Origin), SceneError> {
        let mut origin = Origin::default();
        if let Some(peers) = &self.peers {
            let bytes = self
                .manifest
                .domains
                .get(domain as usize)
                .map_or(0, |d| d.bytes);
            match peers.fetch(&self.manifest, domain, self.storage.estimate(bytes)) {
                Ok(Some(data)) => {
                    origin.from_peer = true;
                    return Ok((Arc::new(data), origin));
                }
                Ok(None) => {}
                Err(PeerError::Refused(_)) => origin.peer_refused = true,
                Err(PeerError::Failed(_)) => origin.peer_failed = true,
            }
        }
        let started = Instant::now();
        let data = open(
            &self.manifest,
            &self.dir,
            domain,
            verify,
            self.mappings.as_deref(),
        )?;
        self.storage.deliver(data.bytes());
        if let Some(peers) = &self.peers {
            peers.note_storage(data.bytes(), started.elapsed());
        }
        Ok((data, origin))
    }
}

/// Maps `domain` for a cache: its own mapping, or the one `mappings` shares.
fn open(
    manifest: &Manifest,
    dir: &std::path::Path,
    domain: u32,
    verify: bool,
    mappings: Option<&SharedMappings>,
) -> Result<Arc<DomainData>, SceneError> {
    match mappings {
        Some(m) => m.open(manifest, dir, domain, verify),
        None => manifest.open_domain(dir, domain, verify).map(Arc::new),
    }
}

impl PendingLoad {
    /// The domain being loaded.
    pub fn domain(&self) -> u32 {
        self.domain
    }

    /// Maps and checks the domain and waits for the emulated storage: the prefetch's I/O,
    /// run off the cache's lock.
    pub fn read(self) -> Result<LoadedDomain, SceneError> {
        let _span = info_span!("prefetch_domain", domain = self.domain).entered();
        let started = Instant::now();
        let (data, origin) = self.source.read(self.domain, self.verify)?;
        Ok(LoadedDomain {
            domain: self.domain,
            data,
            nanos: started.elapsed().as_nanos() as u64,
            origin,
        })
    }
}

impl LoadedDomain {
    /// The domain loaded.
    pub fn domain(&self) -> u32 {
        self.domain
    }
}

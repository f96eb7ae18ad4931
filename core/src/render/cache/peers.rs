//! Domains from peers: a load may take a domain's bytes from another worker that has it
//! loaded, when that is cheaper than shared storage (the paper's data requests in the control
//! tier). The cache decides here, per load, where the bytes come from; the transfer itself is
//! the worker shell's ([`PeerSource`], a gRPC stream), and the bytes are checked exactly as a
//! file from storage is (`Manifest::received_domain`: sizes from the manifest, the file's own
//! checksum always, the header and tree checks), so a domain from a peer is byte-identical to
//! the file or refused. A peer that fails, stalls past its deadline or sends bad bytes costs
//! that time and the load falls back to storage; the peer is then passed over for a while.
//!
//! The decision ([`choose`]) compares two estimates of the same load: storage's (measured
//! from this cache's completed storage loads, else the emulated storage model's) and the
//! link's (a known bandwidth, else measured from completed peer transfers). With no storage
//! estimate yet the load goes to storage (it measures it); with no link estimate the peer is
//! tried once under a deadline no later than storage would have finished.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use tracing::{debug, info_span, warn};

use crate::scene::{DomainData, Manifest, Received, SceneError};

/// Where a worker can fetch a domain's bytes from other than storage: implemented by the
/// worker shell over its peers' `FetchDomain` streams. Called from a loading thread (a pass
/// or a prefetch), never from an async runtime; it may block up to the deadline it is given.
pub trait PeerSource: Send + Sync {
    /// Other workers holding `domain` now, as this worker's latest plan names them.
    fn holders(&self, domain: u32) -> Vec<String>;

    /// The peer link's bandwidth in bytes per second when it is known (configured); `None`:
    /// the cache measures it from completed transfers.
    fn link_bandwidth(&self) -> Option<u64>;

    /// Fetches `domain` from `peer` by the deadline: its file's bytes and, when the manifest
    /// names one (`surfaces`), its surfaces file's, together exactly `bytes` long (the
    /// manifest's size: a peer announcing other sizes is refused before anything is held).
    fn fetch(
        &self,
        peer: &str,
        domain: u32,
        bytes: u64,
        surfaces: bool,
        deadline: Instant,
    ) -> Result<(Received, Option<Received>), PeerError>;
}

/// Why a peer gave no domain.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PeerError {
    /// It answered at once that it cannot serve it now (not loaded there, another frame,
    /// busy): no fault of the peer's, and cheap.
    Refused(String),
    /// It failed: unreachable, broken off, stalled past the deadline, or bytes the checks
    /// refuse. The peer is passed over for [`SHUN_FOR`].
    Failed(String),
}

impl std::fmt::Display for PeerError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PeerError::Refused(r) => write!(f, "refused: {r}"),
            PeerError::Failed(r) => write!(f, "failed: {r}"),
        }
    }
}

/// Where one load's bytes should come from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Choice {
    /// Shared storage.
    Storage,
    /// A peer, given up on after `deadline` (then storage).
    Peer { deadline: Duration },
}

/// A peer must be at least this much faster than storage to be asked: serving costs the peer
/// CPU and its link, which its own ray bundles share, so a near tie stays with storage.
pub const PEER_MARGIN: f64 = 1.25;

/// Added to every peer deadline: connecting, the request's round trip, the checks.
pub const PEER_SLACK: Duration = Duration::from_millis(200);

/// Most peers one load asks (those that refuse at once; a failure ends the asking).
pub const ASKED: usize = 3;

/// How long a peer that failed a transfer is passed over.
pub const SHUN_FOR: Duration = Duration::from_secs(10);

/// The decision for one load, from the estimated time of the load from storage and over the
/// peer link (`None`: not known yet). Pure: the rule the module documentation states.
pub fn choose(storage: Option<Duration>, link: Option<Duration>) -> Choice {
    let Some(storage) = storage else {
        return Choice::Storage;
    };
    match link {
        // Tried once to learn the link, no longer than storage would take.
        None => Choice::Peer {
            deadline: storage + PEER_SLACK,
        },
        Some(link) if link.as_secs_f64() * PEER_MARGIN < storage.as_secs_f64() => Choice::Peer {
            // Twice the estimate absorbs a busy peer; never later than storage would be done.
            deadline: (link * 2).min(storage) + PEER_SLACK,
        },
        Some(_) => Choice::Storage,
    }
}

/// A bandwidth measured from completed transfers: bytes over seconds, older transfers
/// weighing less (each new one keeps 3/4 of what was there), so it follows a changing load.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rate {
    bytes: f64,
    seconds: f64,
}

impl Rate {
    /// Adds a transfer of `bytes` that took `took`.
    pub fn note(&mut self, bytes: u64, took: Duration) {
        self.bytes = self.bytes * 0.75 + bytes as f64;
        self.seconds = self.seconds * 0.75 + took.as_secs_f64();
    }

    /// Bytes per second, once something was measured.
    pub fn per_second(&self) -> Option<f64> {
        (self.seconds > 0.0 && self.bytes > 0.0).then(|| self.bytes / self.seconds)
    }

    /// The time `bytes` would take at this rate.
    pub fn time(&self, bytes: u64) -> Option<Duration> {
        self.per_second()
            .and_then(|r| Duration::try_from_secs_f64(bytes as f64 / r).ok())
    }
}

/// What happened to one load, for the counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Origin {
    /// The bytes came from a peer.
    pub from_peer: bool,
    /// A peer was asked and failed (the bytes then came from storage).
    pub peer_failed: bool,
    /// A peer was asked and refused at once (the bytes then came from storage).
    pub peer_refused: bool,
}

/// Measured rates and the peers passed over: one worker's state for loading from peers,
/// shared by its cache and its prefetches.
pub struct PeerLoads {
    source: Box<dyn PeerSource>,
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    storage: Rate,
    link: Rate,
    /// Peers that failed a transfer, and until when they are passed over.
    shunned: BTreeMap<String, Instant>,
}

impl PeerLoads {
    /// Loads from the peers `source` reaches.
    pub fn new(source: Box<dyn PeerSource>) -> Self {
        PeerLoads {
            source,
            state: Mutex::new(State::default()),
        }
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records a completed load from storage of `bytes` that took `took` (the storage rate).
    pub fn note_storage(&self, bytes: u64, took: Duration) {
        self.state().storage.note(bytes, took);
    }

    /// The domain from a peer, if one holds it and the decision says so and the transfer
    /// succeeds with bytes the manifest accepts; `Err` with the reason if a peer was asked
    /// and refused or failed (the caller loads from storage), `Ok(None)` if no peer was
    /// asked. `model` estimates storage until a load from it has been measured.
    pub fn fetch(
        &self,
        manifest: &Manifest,
        domain: u32,
        model: Option<Duration>,
    ) -> Result<Option<DomainData>, PeerError> {
        let Some(entry) = manifest.domains.get(domain as usize) else {
            return Ok(None);
        };
        let bytes = entry.bytes;
        let now = Instant::now();
        let (peers, choice) = {
            let mut st = self.state();
            st.shunned.retain(|_, until| *until > now);
            let peers: Vec<String> = self
                .source
                .holders(domain)
                .into_iter()
                .filter(|p| !st.shunned.contains_key(p))
                .take(ASKED)
                .collect();
            if peers.is_empty() {
                return Ok(None);
            }
            let storage = st.storage.time(bytes).or(model);
            let link = match self.source.link_bandwidth() {
                Some(b) if b > 0 => Duration::try_from_secs_f64(bytes as f64 / b as f64).ok(),
                _ => st.link.time(bytes),
            };
            (peers, choose(storage, link))
        };
        let Choice::Peer { deadline } = choice else {
            return Ok(None);
        };
        // The whole deadline is the load's, however many peers refuse first.
        let deadline = Instant::now() + deadline;
        let mut refused = None;
        for peer in peers {
            match self.fetch_from(manifest, domain, &peer, deadline) {
                Ok(data) => return Ok(Some(data)),
                Err(e @ PeerError::Refused(_)) => refused = Some(e),
                Err(e @ PeerError::Failed(_)) => {
                    self.state().shunned.insert(peer, Instant::now() + SHUN_FOR);
                    return Err(e);
                }
            }
        }
        Err(refused.unwrap_or_else(|| PeerError::Refused("no peer asked".into())))
    }

    /// One peer's transfer of `domain`, checked against the manifest.
    fn fetch_from(
        &self,
        manifest: &Manifest,
        domain: u32,
        peer: &str,
        deadline: Instant,
    ) -> Result<DomainData, PeerError> {
        let entry = &manifest.domains[domain as usize];
        let bytes = entry.bytes;
        let _span = info_span!("peer_domain", domain, %peer, bytes).entered();
        let started = Instant::now();
        let fetched = self
            .source
            .fetch(peer, domain, bytes, entry.surfaces.is_some(), deadline)
            .and_then(|(file, surfaces)| {
                let origin = std::path::PathBuf::from(format!("peer {peer}: {}", entry.file));
                manifest
                    .received_domain(&origin, domain, file, surfaces)
                    .map_err(|e: SceneError| PeerError::Failed(e.to_string()))
            });
        let took = started.elapsed();
        match &fetched {
            Ok(_) => {
                self.state().link.note(bytes, took);
                debug!(ms = took.as_millis() as u64, "domain fetched from a peer");
            }
            Err(e @ PeerError::Refused(_)) => debug!(error = %e, "a peer refused a domain"),
            Err(e @ PeerError::Failed(_)) => {
                warn!(error = %e, "loading a domain from a peer failed: from storage instead")
            }
        }
        fetched
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn storage_first_then_a_peer_tried_then_the_cheaper_one() {
        // Nothing known of storage: storage (its load measures it).
        assert_eq!(choose(None, None), Choice::Storage);
        assert_eq!(choose(None, Some(MS)), Choice::Storage);
        // Storage known, the link not: the peer, no later than storage would be done.
        assert_eq!(
            choose(Some(400 * MS), None),
            Choice::Peer {
                deadline: 400 * MS + PEER_SLACK
            }
        );
        // A link 10x faster: the peer, with twice its estimate.
        assert_eq!(
            choose(Some(400 * MS), Some(40 * MS)),
            Choice::Peer {
                deadline: 80 * MS + PEER_SLACK
            }
        );
        // Faster, but not by the margin, or slower: storage.
        assert_eq!(choose(Some(400 * MS), Some(330 * MS)), Choice::Storage);
        assert_eq!(choose(Some(400 * MS), Some(900 * MS)), Choice::Storage);
        // Just past the margin: the peer, the deadline capped at storage's time.
        assert_eq!(
            choose(Some(400 * MS), Some(300 * MS)),
            Choice::Peer {
                deadline: 400 * MS + PEER_SLACK
            }
        );
    }

    #[test]
    fn rates_follow_recent_transfers() {
        let mut r = Rate::default();
        assert_eq!(r.per_second(), None);
        assert_eq!(r.time(100), None);
        r.note(100 << 20, Duration::from_secs(1));
        assert_eq!(r.time(50 << 20), Some(Duration::from_millis(500)));
        // A much slower link now: the estimate moves most of the way at once.
        for _ in 0..8 {
            r.note(10 << 20, Duration::from_secs(1));
        }
        let rate = r.per_second().unwrap() / (1 << 20) as f64;
        assert!(rate > 10.0 && rate < 25.0, "{rate}");
    }

    /// A small generated scene of four domains.
    pub(crate) fn tiny_scene(dir: &std::path::Path) -> Manifest {
        crate::prepare::generate::prepare_nbody(
            &dir.join("s"),
            &crate::prepare::generate::NbodyOptions {
                name: "s".into(),
                triangles: 4000,
                seed: 3,
                domains: 4,
                max_memory: None,
                force: false,
            },
        )
        .unwrap()
    }

    /// A source whose peer hands out what it is told to, counting calls.
    struct Fake {
        holders: Vec<String>,
        bandwidth: Option<u64>,
        calls: std::sync::atomic::AtomicUsize,
        fail: bool,
    }

    impl PeerSource for Fake {
        fn holders(&self, _: u32) -> Vec<String> {
            self.holders.clone()
        }
        fn link_bandwidth(&self) -> Option<u64> {
            self.bandwidth
        }
        fn fetch(
            &self,
            _: &str,
            _: u32,
            bytes: u64,
            _: bool,
            _: Instant,
        ) -> Result<(Received, Option<Received>), PeerError> {
            self.calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            if self.fail {
                return Err(PeerError::Failed("peer gone".into()));
            }
            // Zeroes: never a valid domain file.
            let mut r = Received::new(bytes, None).unwrap();
            r.push(&vec![0; bytes as usize]).unwrap();
            Ok((r, None))
        }
    }

    #[test]
    fn a_failing_or_lying_peer_is_passed_over_and_no_holder_asks_no_one() {
        let dir = tempfile::tempdir().unwrap();
        let manifest = tiny_scene(dir.path());
        for fail in [true, false] {
            let loads = PeerLoads::new(Box::new(Fake {
                holders: vec!["a:1".into()],
                bandwidth: Some(1 << 30),
                calls: Default::default(),
                fail,
            }));
            // No storage estimate: not asked.
            assert!(matches!(loads.fetch(&manifest, 0, None), Ok(None)));
            // A storage estimate, a fast link: asked, refused (gone, or zero bytes).
            let slow = Some(Duration::from_secs(1));
            assert!(loads.fetch(&manifest, 0, slow).is_err());
            // Passed over now.
            assert!(matches!(loads.fetch(&manifest, 0, slow), Ok(None)));
        }
        let none = PeerLoads::new(Box::new(Fake {
            holders: vec![],
            bandwidth: None,
            calls: Default::default(),
            fail: false,
        }));
        assert!(matches!(
            none.fetch(&manifest, 0, Some(Duration::from_secs(1))),
            Ok(None)
        ));
    }

    /// A peer that serves the scene's own files, or flips one byte of them.
    struct Files {
        dir: std::path::PathBuf,
        manifest: Manifest,
        flip: bool,
    }

    impl PeerSource for Files {
        fn holders(&self, _: u32) -> Vec<String> {
            vec!["peer:1".into()]
        }
        fn link_bandwidth(&self) -> Option<u64> {
            Some(u64::MAX)
        }
        fn fetch(
            &self,
            _: &str,
            domain: u32,
            bytes: u64,
            _: bool,
            _: Instant,
        ) -> Result<(Received, Option<Received>), PeerError> {
            let entry = &self.manifest.domains[domain as usize];
            let mut file = std::fs::read(self.dir.join(&entry.file)).unwrap();
            assert_eq!(file.len() as u64, bytes);
            if self.flip {
                let last = file.len() - 1;
                file[last] ^= 1;
            }
            let mut r = Received::new(bytes, None).unwrap();
            // In two pieces, as chunks arrive.
            r.push(&file[..file.len() / 2]).unwrap();
            r.push(&file[file.len() / 2..]).unwrap();
            Ok((r, None))
        }
    }

    #[test]
    fn a_cache_loads_from_a_peer_the_same_bytes_and_falls_back_on_bad_ones() {
        use crate::render::cache::{DomainCache, StorageModel};
        let tmp = tempfile::tempdir().unwrap();
        let manifest = tiny_scene(tmp.path());
        let dir = tmp.path().join("s");
        let slow = StorageModel {
            bandwidth: Some(1 << 30),
            latency: Duration::from_millis(5),
        };
        for flip in [false, true] {
            let mut cache = DomainCache::new(&dir, &manifest, u64::MAX).with_storage(slow);
            cache.set_peers(Some(std::sync::Arc::new(PeerLoads::new(Box::new(Files {
                dir: dir.clone(),
                manifest: manifest.clone(),
                flip,
            })))));
            let data = cache.get(1).unwrap();
            let file = std::fs::read(dir.join(&manifest.domains[1].file)).unwrap();
            assert_eq!(data.file_bytes(), &file[..], "byte-identical to the file");
            assert!(
                cache.shelf().get(1).is_some(),
                "resident domains are shelved"
            );
            let c = cache.counters();
            assert_eq!((c.loads, c.bytes_loaded), (1, file.len() as u64));
            if flip {
                assert_eq!(
                    (c.peer_loads, c.bytes_from_peers, c.peer_failures),
                    (0, 0, 1)
                );
            } else {
                assert_eq!(
                    (c.peer_loads, c.bytes_from_peers, c.peer_failures),
                    (1, file.len() as u64, 0)
                );
                assert_eq!(c.bytes_from_storage(), 0);
            }
            cache.evict(1);
            assert!(
                cache.shelf().get(1).is_none(),
                "evicted domains leave the shelf"
            );
        }
    }
}

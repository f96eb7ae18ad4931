//! What a domain cache counts: loads, evictions, bytes, prefetches and loads from peers, for
//! a frame's statistics.

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
    /// Time passes spent loading (mapping, checking, emulated storage delay), nanoseconds;
    /// prefetches' time is apart (`prefetch_nanos`): it overlaps tracing.
    #[serde(default)]
    pub load_nanos: u64,
    /// Of `loads`, those made ahead of need (prefetches), kept or not.
    #[serde(default)]
    pub prefetches: u64,
    /// Prefetched domains a pass then asked for while they were mapped.
    #[serde(default)]
    pub prefetches_used: u64,
    /// Prefetched domains that left the cache unused, or found no room when they arrived.
    #[serde(default)]
    pub prefetches_wasted: u64,
    /// Time prefetches spent loading, nanoseconds (beside tracing, not in a pass's time).
    #[serde(default)]
    pub prefetch_nanos: u64,
    /// Of `loads`, those whose bytes came from a peer.
    #[serde(default)]
    pub peer_loads: u64,
    /// Of `bytes_loaded`, the bytes that came from peers (the rest came from storage).
    #[serde(default)]
    pub bytes_from_peers: u64,
    /// Loads that asked a peer, which failed (unreachable, stalled, bad bytes): then storage.
    #[serde(default)]
    pub peer_failures: u64,
    /// Loads that asked a peer, which refused at once (not loaded there, busy): then storage.
    #[serde(default)]
    pub peer_refusals: u64,
}

impl CacheCounters {
    /// Adds `other`'s counts to these; the peak is the larger of the two.
    pub fn add(&mut self, other: &CacheCounters) {
        self.loads += other.loads;
        self.bytes_loaded += other.bytes_loaded;
        self.evictions += other.evictions;
        self.peak_resident_bytes = self.peak_resident_bytes.max(other.peak_resident_bytes);
        self.load_nanos += other.load_nanos;
        self.prefetches += other.prefetches;
        self.prefetches_used += other.prefetches_used;
        self.prefetches_wasted += other.prefetches_wasted;
        self.prefetch_nanos += other.prefetch_nanos;
        self.peer_loads += other.peer_loads;
        self.bytes_from_peers += other.bytes_from_peers;
        self.peer_failures += other.peer_failures;
        self.peer_refusals += other.peer_refusals;
    }

    /// Bytes loaded from storage (the rest came from peers).
    pub fn bytes_from_storage(&self) -> u64 {
        self.bytes_loaded.saturating_sub(self.bytes_from_peers)
    }

    /// What changed from `start` to these (a frame's share of a process's counters); the
    /// peak is these counters' own.
    pub fn since(&self, start: &CacheCounters) -> CacheCounters {
        CacheCounters {
            loads: self.loads - start.loads,
            bytes_loaded: self.bytes_loaded - start.bytes_loaded,
            evictions: self.evictions - start.evictions,
            peak_resident_bytes: self.peak_resident_bytes,
            load_nanos: self.load_nanos - start.load_nanos,
            prefetches: self.prefetches - start.prefetches,
            prefetches_used: self.prefetches_used - start.prefetches_used,
            prefetches_wasted: self.prefetches_wasted - start.prefetches_wasted,
            prefetch_nanos: self.prefetch_nanos - start.prefetch_nanos,
            peer_loads: self.peer_loads - start.peer_loads,
            bytes_from_peers: self.bytes_from_peers - start.bytes_from_peers,
            peer_failures: self.peer_failures - start.peer_failures,
            peer_refusals: self.peer_refusals - start.peer_refusals,
        }
    }
}

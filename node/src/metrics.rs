//! Prometheus metrics of a coordinator ([`CoordinatorMetrics`]) and of a worker
//! ([`WorkerMetrics`]), kept in `prometheus-client` registries and served as text at
//! `/metrics` by [`crate::http`].
//!
//! Each process has one set, reached through [`coordinator`] or [`worker`] (a binary touches
//! only its own, so a worker's `/metrics` shows no coordinator families). Counting is atomic
//! adds on handles taken once; labelled children of the hot counters (rays by kind, traffic by
//! tier) are looked up once and kept, so counting never takes the families' locks.
//! README.md's table documents every metric.

use std::sync::LazyLock;

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::metrics::info::Info;
use prometheus_client::registry::{Registry, Unit};
use rayfarm_core::bundler::Tier;
use rayfarm_core::cluster::stats::tier_name;

/// The content type of the text [`encode`] writes (OpenMetrics 1.0, which Prometheus reads).
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// A label set of one label.
type Label = [(&'static str, &'static str); 1];

/// A counter in seconds (fractional).
pub type SecondsCounter = Counter<f64, std::sync::atomic::AtomicU64>;

/// Job states as the `state` label of `rayfarm_jobs` spells them.
pub const JOB_STATES: [&str; 5] = ["queued", "running", "succeeded", "failed", "cancelled"];

/// The gRPC status codes as the `code` label of `rayfarm_rpc_errors_total` spells them,
/// indexed by code number (0, OK, is never counted).
pub const RPC_CODES: [&str; 17] = [
    "ok",
    "cancelled",
    "unknown",
    "invalid_argument",
    "deadline_exceeded",
    "not_found",
    "already_exists",
    "permission_denied",
    "resource_exhausted",
    "failed_precondition",
    "aborted",
    "out_of_range",
    "unimplemented",
    "internal",
    "unavailable",
    "data_loss",
    "unauthenticated",
];

/// The gRPC errors this process answered, by status code (shared by both registries: a
/// process has one gRPC server stack).
static RPC_ERROR_FAMILY: LazyLock<Family<Label, Counter>> = LazyLock::new(Family::default);

/// [`RPC_ERROR_FAMILY`]'s children, by code number.
static RPC_ERRORS: LazyLock<[Counter; 17]> = LazyLock::new(|| {
    std::array::from_fn(|i| {
        RPC_ERROR_FAMILY
            .get_or_create(&[("code", RPC_CODES[i])])
            .clone()
    })
});

/// The allocator's bytes in use and held free (set at each scrape, shared by both registries:
/// a process has one heap).
static HEAP_IN_USE: LazyLock<Gauge> = LazyLock::new(Gauge::default);
static HEAP_FREE: LazyLock<Gauge> = LazyLock::new(Gauge::default);

/// Registers what both kinds of process export: build information, the gRPC errors they
/// answered and the allocator's heap.
fn register_common(registry: &mut Registry, role: &'static str) {
    let info = Info::new(vec![("version", env!("CARGO_PKG_VERSION")), ("role", role)]);
    registry.register("build", "The build of this process (value 1)", info);
    registry.register(
        "rpc_errors",
        "gRPC calls this process answered with an error, by status code (errors at the start \
         of a call, refusals of the interceptors included)",
        RPC_ERROR_FAMILY.clone(),
    );
    LazyLock::force(&RPC_ERRORS);
    registry.register_with_unit(
        "heap_in_use",
        "Heap allocated by this process now (glibc's mallinfo2: arenas and large mappings)",
        Unit::Bytes,
        HEAP_IN_USE.clone(),
    );
    registry.register_with_unit(
        "heap_free",
        "Heap freed by this process but kept by the allocator for reuse",
        Unit::Bytes,
        HEAP_FREE.clone(),
    );
}

/// Counts a call answered with gRPC status `code` (0, OK, and unknown codes are not).
pub fn rpc_error(code: i32) {
    if let Some(c) = usize::try_from(code)
        .ok()
        .filter(|&c| c > 0)
        .and_then(|c| RPC_ERRORS.get(c))
    {
        c.inc();
    }
}

/// The response of a tonic server stack.
type GrpcResponse = http::Response<tonic::body::Body>;

/// Counts the `grpc-status` of a trailers-only response (how tonic answers an error at the
/// start of a call).
fn count_rpc_error(response: GrpcResponse) -> GrpcResponse {
    if let Some(code) = response
        .headers()
        .get("grpc-status")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<i32>().ok())
    {
        rpc_error(code);
    }
    response
}

/// A tower layer for a tonic server that counts the errors it answers at the start of a call
/// (refusals, bad requests) into `rayfarm_rpc_errors_total`.
pub fn rpc_error_layer() -> tower::util::MapResponseLayer<fn(GrpcResponse) -> GrpcResponse> {
    tower::util::MapResponseLayer::new(count_rpc_error)
}

/// The coordinator's metrics.
pub struct CoordinatorMetrics {
    registry: Registry,
    /// Jobs in each state, by [`JOB_STATES`] index (set at each scrape from the job table).
    pub jobs: [Gauge; 5],
    /// Workers registered now (set at each scrape).
    pub workers: Gauge,
    /// Frames completed (every tile's credit back, results written or not).
    pub frames_committed: Counter,
    /// Frames that failed.
    pub frames_failed: Counter,
    /// Subframes committed (a one-pass frame is one subframe).
    pub subframes_committed: Counter,
    /// Scheduling rounds planned.
    pub rounds: Counter,
    /// Time planning a round took (the frame machine's report handling that planned one).
    pub planning_seconds: Histogram,
    /// Tiles whose credit came back complete.
    pub tiles_committed: Counter,
    /// Workers lost (stream ended, silent, dropped).
    pub workers_lost: Counter,
}

impl CoordinatorMetrics {
    fn new() -> Self {
        let mut registry = Registry::with_prefix("rayfarm");
        register_common(&mut registry, "coordinator");
        let jobs_family = Family::<Label, Gauge>::default();
        registry.register(
            "jobs",
            "Jobs known to the coordinator, by state",
            jobs_family.clone(),
        );
        let jobs = std::array::from_fn(|i| {
            jobs_family
                .get_or_create(&[("state", JOB_STATES[i])])
                .clone()
        });
        let m = CoordinatorMetrics {
            jobs,
            workers: Gauge::default(),
            frames_committed: Counter::default(),
            frames_failed: Counter::default(),
            subframes_committed: Counter::default(),
            rounds: Counter::default(),
            // 10 µs to about 2.6 s.
            planning_seconds: Histogram::new(exponential_buckets(1e-5, 4.0, 10)),
            tiles_committed: Counter::default(),
            workers_lost: Counter::default(),
            registry: Registry::default(),
        };
        registry.register("workers", "Workers registered now", m.workers.clone());
        registry.register(
            "frames_committed",
            "Frames whose every tile came back (their images then written)",
            m.frames_committed.clone(),
        );
        registry.register(
            "frames_failed",
            "Frames that failed",
            m.frames_failed.clone(),
        );
        registry.register(
            "subframes_committed",
            "Subframes whose every tile came back (a one-pass frame is one subframe)",
            m.subframes_committed.clone(),
        );
        registry.register("rounds", "Scheduling rounds planned", m.rounds.clone());
        registry.register_with_unit(
            "planning",
            "Time taken to plan a round of the schedule",
            Unit::Seconds,
            m.planning_seconds.clone(),
        );
        registry.register(
            "tiles_committed",
            "Tiles whose credit came back complete and were added to the film",
            m.tiles_committed.clone(),
        );
        registry.register(
            "workers_lost",
            "Workers lost: stream ended, heartbeats stopped, or dropped for bad results",
            m.workers_lost.clone(),
        );
        CoordinatorMetrics { registry, ..m }
    }

    /// The metrics in the text format.
    pub fn encode(&self) -> String {
        encode_registry(&self.registry)
    }
}

/// Counters of one bundler tier on a worker.
#[derive(Clone, Default)]
pub struct TierCounters {
    /// Rays sent in this tier's bundles.
    pub rays: Counter,
    /// Bytes of batches sent.
    pub bytes: Counter,
    /// Bundles sent.
    pub bundles: Counter,
}

/// A worker's metrics.
pub struct WorkerMetrics {
    registry: Registry,
    /// Domains loaded (mapped and checked) into the cache.
    pub domain_loads: Counter,
    /// Bytes of domains loaded.
    pub domain_load_bytes: Counter,
    /// Time spent loading domains.
    pub domain_load_seconds: SecondsCounter,
    /// Domains evicted from the cache.
    pub domain_evictions: Counter,
    /// Of the bytes of domains loaded, those that came from peers (the rest from storage).
    pub domain_load_bytes_from_peers: Counter,
    /// Domain loads that asked a peer, which failed (then storage).
    pub domain_peer_failures: Counter,
    /// Bytes of domains this worker served to its peers.
    pub domain_bytes_served: Counter,
    /// Radiance-ray segments traced.
    pub radiance_segments: Counter,
    /// Shadow-ray segments traced.
    pub shadow_segments: Counter,
    /// Rays created, by kind: primary, shadow, bounce, reflection.
    pub rays_created: [Counter; 4],
    /// Passes run.
    pub passes: Counter,
    /// Time spent in passes.
    pub busy_seconds: SecondsCounter,
    /// Traffic to peers, by [`Tier::index`]; the `tier` label is the tier's name
    /// ([`tier_name`]).
    pub tiers: [TierCounters; Tier::COUNT],
    /// Rays received from peers.
    pub rays_received: Counter,
    /// Bytes of rays queued in memory now.
    pub queue_bytes: Gauge,
    /// Bytes of rays spilled to disk now.
    pub spill_bytes: Gauge,
    /// Peers that stopped acknowledging and were dropped.
    pub peers_lost: Counter,
}

impl WorkerMetrics {
    fn new() -> Self {
        let mut r = Registry::with_prefix("rayfarm");
        register_common(&mut r, "worker");
        let domain_loads = Counter::default();
        r.register(
            "domain_loads",
            "Domains loaded into the cache",
            domain_loads.clone(),
        );
        let domain_load_bytes = Counter::default();
        r.register_with_unit(
            "domain_load",
            "Bytes of domains loaded into the cache",
            Unit::Bytes,
            domain_load_bytes.clone(),
        );
        let domain_load_seconds = SecondsCounter::default();
        r.register_with_unit(
            "domain_load",
            "Time spent mapping and checking domains",
            Unit::Seconds,
            domain_load_seconds.clone(),
        );
        let domain_evictions = Counter::default();
        r.register(
            "domain_evictions",
            "Domains evicted from the cache",
            domain_evictions.clone(),
        );
        let domain_load_bytes_from_peers = Counter::default();
        r.register_with_unit(
            "domain_load_from_peers",
            "Bytes of domains loaded into the cache from peers rather than storage",
            Unit::Bytes,
            domain_load_bytes_from_peers.clone(),
        );
        let domain_peer_failures = Counter::default();
        r.register(
            "domain_peer_failures",
            "Domain loads from a peer that failed (unreachable, stalled, bad bytes) and went \
             to storage",
            domain_peer_failures.clone(),
        );
        let domain_bytes_served = Counter::default();
        r.register_with_unit(
            "domain_served",
            "Bytes of loaded domains served to peers",
            Unit::Bytes,
            domain_bytes_served.clone(),
        );
        let traced = Family::<Label, Counter>::default();
        r.register(
            "ray_segments_traced",
            "Ray segments traced against a domain, by kind (radiance, shadow)",
            traced.clone(),
        );
        let created = Family::<Label, Counter>::default();
        r.register(
            "rays_created",
            "Rays created, by kind (primary, shadow, bounce, reflection)",
            created.clone(),
        );
        let passes = Counter::default();
        r.register("passes", "Tracing passes run", passes.clone());
        let busy_seconds = SecondsCounter::default();
        r.register_with_unit(
            "busy",
            "Time spent in passes (tracing, camera rays, domain loads)",
            Unit::Seconds,
            busy_seconds.clone(),
        );
        let rays_sent = Family::<Label, Counter>::default();
        r.register(
            "rays_sent",
            "Rays sent to peers, by bundler tier",
            rays_sent.clone(),
        );
        let bytes_sent = Family::<Label, Counter>::default();
        r.register_with_unit(
            "sent",
            "Bytes of batches sent to peers, by bundler tier",
            Unit::Bytes,
            bytes_sent.clone(),
        );
        let bundles = Family::<Label, Counter>::default();
        r.register(
            "bundles_sent",
            "Bundles sent to peers, by bundler tier",
            bundles.clone(),
        );
        let rays_received = Counter::default();
        r.register(
            "rays_received",
            "Rays received from peers",
            rays_received.clone(),
        );
        let queue_bytes = Gauge::default();
        r.register_with_unit(
            "queue",
            "Bytes of rays queued in memory now",
            Unit::Bytes,
            queue_bytes.clone(),
        );
        let spill_bytes = Gauge::default();
        r.register_with_unit(
            "spill",
            "Bytes of rays spilled to disk now",
            Unit::Bytes,
            spill_bytes.clone(),
        );
        let peers_lost = Counter::default();
        r.register(
            "peers_lost",
            "Peers that stopped acknowledging and were dropped",
            peers_lost.clone(),
        );
        let child =
            |f: &Family<Label, Counter>, key, value| f.get_or_create(&[(key, value)]).clone();
        WorkerMetrics {
            domain_loads,
            domain_load_bytes,
            domain_load_seconds,
            domain_evictions,
            domain_load_bytes_from_peers,
            domain_peer_failures,
            domain_bytes_served,
            radiance_segments: child(&traced, "kind", "radiance"),
            shadow_segments: child(&traced, "kind", "shadow"),
            rays_created: ["primary", "shadow", "bounce", "reflection"]
                .map(|kind| child(&created, "kind", kind)),
            passes,
            busy_seconds,
            tiers: Tier::MOST_URGENT_FIRST.map(|tier| TierCounters {
                rays: child(&rays_sent, "tier", tier_name(tier)),
                bytes: child(&bytes_sent, "tier", tier_name(tier)),
                bundles: child(&bundles, "tier", tier_name(tier)),
            }),
            rays_received,
            queue_bytes,
            spill_bytes,
            peers_lost,
            registry: r,
        }
    }

    /// The metrics in the text format.
    pub fn encode(&self) -> String {
        encode_registry(&self.registry)
    }
}

fn encode_registry(registry: &Registry) -> String {
    if let Some(heap) = crate::heap::usage() {
        HEAP_IN_USE.set(i64::try_from(heap.in_use).unwrap_or(i64::MAX));
        HEAP_FREE.set(i64::try_from(heap.free).unwrap_or(i64::MAX));
    }
    let mut text = String::new();
    // Writing into a String cannot fail.
    let _ = encode(&mut text, registry);
    text
}

static COORDINATOR: LazyLock<CoordinatorMetrics> = LazyLock::new(CoordinatorMetrics::new);
static WORKER: LazyLock<WorkerMetrics> = LazyLock::new(WorkerMetrics::new);

/// This process's coordinator metrics.
pub fn coordinator() -> &'static CoordinatorMetrics {
    &COORDINATOR
}

/// This process's worker metrics.
pub fn worker() -> &'static WorkerMetrics {
    &WORKER
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn families_encode_with_conventional_names() {
        let m = WorkerMetrics::new();
        m.domain_loads.inc_by(3);
        m.tiers[Tier::Migrated.index()].bytes.inc_by(100);
        m.domain_load_seconds.inc_by(0.5);
        rpc_error(16);
        rpc_error(0);
        let text = m.encode();
        for line in [
            "rayfarm_domain_loads_total 3",
            "rayfarm_sent_bytes_total{tier=\"migrated\"} 100",
            "rayfarm_domain_load_seconds_total 0.5",
            "rayfarm_rpc_errors_total{code=\"unauthenticated\"} 1",
            "rayfarm_rpc_errors_total{code=\"ok\"} 0",
        ] {
            assert!(text.lines().any(|l| l == line), "no {line:?} in\n{text}");
        }
        assert!(text.contains("rayfarm_build_info{"), "{text}");
        // Every tier's series is there from the start, and only the tiers there are.
        for tier in ["results", "tasks"] {
            let line = format!("rayfarm_bundles_sent_total{{tier=\"{tier}\"}} 0");
            assert!(text.lines().any(|l| l == line), "no {line:?} in\n{text}");
        }
        assert!(!text.contains("tier=\"control\""), "{text}");
        let heap = text
            .lines()
            .find_map(|l| l.strip_prefix("rayfarm_heap_in_use_bytes "))
            .and_then(|v| v.parse::<i64>().ok());
        assert!(heap.is_some_and(|b| b > 0), "{text}");
        assert!(text.ends_with("# EOF\n"), "{text}");
        let c = CoordinatorMetrics::new();
        c.planning_seconds.observe(0.001);
        let text = c.encode();
        assert!(text.contains("rayfarm_planning_seconds_count 1"), "{text}");
        assert!(text.contains("rayfarm_jobs{state=\"queued\"} 0"), "{text}");
    }
}

//! A node with the cluster credentials (none configured here: loopback) that answers every
//! tile it is dealt with a whole tile's credit and no pixel sums. Without the ledger's pixel
//! bound that would end the frame at once with black tiles; it must be refused, the forger
//! dropped, and the image be the one `render --local` makes. Also a node that sends a
//! plausible result for a tile it was never given a ray of (which, taken, would spend credit
//! the honest worker's results then overflow), and one that accuses a healthy worker.

use std::time::Duration;

use rayfarm_core::cluster::tile_sums;
use rayfarm_core::tile::credit::TILE_CREDIT;
use rayfarm_core::tile::{TILE_SIZE, TileGrid};
use rayfarm_node::proto;
use rayfarm_node::proto::coordinator_message::Body as ToWorker;
use rayfarm_node::proto::worker_message::Body as FromWorker;
use rayfarm_tests::{
    Cluster, WorkerOpts, hash_of, local_hash, prepare_nbody, stats_field, submit_wait,
};

const FRAME: [&str; 8] = [
    "--width", "96", "--height", "64", "--spp", "2", "--depth", "2",
];

/// What the forger was told and did.
#[derive(Debug, Default)]
struct Forgery {
    /// Tiles it answered with forged results.
    forged: usize,
    /// How its control stream ended.
    ended: Option<tonic::Status>,
}

/// Registers as worker `id` on the coordinator's control service and attaches: the sender of
/// its messages and the stream of the coordinator's.
async fn attach(
    url: String,
    id: &str,
) -> (
    tokio::sync::mpsc::Sender<proto::WorkerMessage>,
    tonic::Streaming<proto::CoordinatorMessage>,
) {
    let mut client = proto::worker_control_client::WorkerControlClient::connect(url)
        .await
        .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    tx.send(proto::WorkerMessage {
        body: Some(FromWorker::Register(proto::Register {
            protocol_version: proto::PROTOCOL_VERSION,
            worker_id: id.into(),
            peer_address: "127.0.0.1:9".into(),
            cache_bytes: 1 << 30,
            threads: 1,
        })),
    })
    .await
    .unwrap();
    let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
    (tx, client.attach(stream).await.unwrap().into_inner())
}

/// Attaches as worker `id` and answers every tile dealt to it (at frame start or handed out
/// later) with `TileResult(credit = TILE_CREDIT, no sums)`, until the coordinator closes
/// the stream.
async fn forger(url: String, id: &str) -> Forgery {
    let (tx, mut answers) = attach(url, id).await;
    let mut out = Forgery::default();
    let mut epochs = std::collections::HashMap::new();
    loop {
        let msg = match answers.message().await {
            Ok(Some(m)) => m,
            Ok(None) => break,
            Err(e) => {
                out.ended = Some(e);
                break;
            }
        };
        let (job_id, tiles) = match msg.body {
            Some(ToWorker::StartFrame(f)) => {
                epochs = f.epochs.clone();
                (f.job_id, f.primary_tiles)
            }
            Some(ToWorker::HandOutTiles(h)) => (h.job_id, h.tiles),
            Some(ToWorker::EpochBump(b)) => {
                epochs.extend(b.epochs);
                continue;
            }
            _ => continue,
        };
        if tiles.is_empty() {
            continue;
        }
        out.forged += tiles.len();
        let results = tiles
            .iter()
            .map(|&tile| proto::TileResult {
                tile,
                epoch: epochs.get(&tile).copied().unwrap_or(0),
                credit: TILE_CREDIT,
                sums: Vec::new(),
            })
            .collect();
        let forged = proto::WorkerMessage {
            body: Some(FromWorker::TileResults(proto::TileResults {
                job_id,
                results,
                segments_traced: 0,
            })),
        };
        if tx.send(forged).await.is_err() {
            break;
        }
    }
    out
}

#[test]
fn a_worker_forging_credit_is_dropped_and_the_image_stays_right() {
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 2000, 2);
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::default()]);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let forgery = rt.spawn(forger(cluster.coordinator_url().to_string(), "forger"));
    cluster.wait_for_workers(2, Duration::from_secs(30));

    let stats = submit_wait(&cluster, &FRAME, "forged");
    let forgery = rt
        .block_on(async { tokio::time::timeout(Duration::from_secs(30), forgery).await })
        .expect("the forger's stream was not closed")
        .unwrap();
    // It was dealt tiles and forged them: the frame did not end on them.
    assert!(forgery.forged > 0, "the forger was dealt no tiles");
    assert_eq!(hash_of(&stats), local_hash(&scene, &FRAME));
    let ended = forgery.ended.expect("closed with a status");
    assert_eq!(ended.code(), tonic::Code::PermissionDenied, "{ended}");
    assert!(
        ended.message().contains("credit without the sums"),
        "{ended}"
    );
    let log = cluster.coordinator_log();
    assert!(
        log.contains("worker sent impossible tile results") && log.contains("forger"),
        "{log}"
    );
    // The honest worker stays; the forger is gone.
    let status = cluster.status();
    let workers = status["workers"].as_array().unwrap();
    assert_eq!(workers.len(), 1, "{status}");
}

/// Attaches as worker `id` and, when a frame starts, sends one plausible result (one unit of
/// credit and one pixel's sum) for the first tile of the `width` x `height` frame that was
/// not dealt to it; traces nothing. Returns how its control stream ended.
async fn poacher(url: String, id: &str, width: u32, height: u32) -> Option<tonic::Status> {
    let (tx, mut answers) = attach(url, id).await;
    let grid = TileGrid::new(width, height, TILE_SIZE).unwrap();
    loop {
        let msg = match answers.message().await {
            Ok(Some(m)) => m,
            Ok(None) => return None,
            Err(e) => return Some(e),
        };
        let Some(ToWorker::StartFrame(f)) = msg.body else {
            continue;
        };
        let tile = (0..grid.count())
            .find(|t| !f.primary_tiles.contains(t))
            .expect("another worker was dealt a tile");
        let pixel = grid.pixels(tile).next().unwrap();
        let result = proto::TileResult {
            tile,
            epoch: 0,
            credit: 1,
            sums: tile_sums::encode(&[(pixel, [1 << 40, 0, 0])]),
        };
        let poached = proto::WorkerMessage {
            body: Some(FromWorker::TileResults(proto::TileResults {
                job_id: f.job_id,
                results: vec![result],
                segments_traced: 0,
            })),
        };
        if tx.send(poached).await.is_err() {
            return None;
        }
    }
}

#[test]
fn a_worker_sending_results_of_a_tile_it_was_never_given_is_dropped() {
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 2000, 2);
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::default()]);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let url = cluster.coordinator_url().to_string();
    let poacher = rt.spawn(async move { poacher(url, "poacher", 96, 64).await });
    cluster.wait_for_workers(2, Duration::from_secs(30));

    // Image-plane routes no rays between workers, so only the worker dealt a tile may send
    // its results.
    let mut frame = FRAME.to_vec();
    frame.extend(["--schedule", "image-plane"]);
    let stats = submit_wait(&cluster, &frame, "poached");
    assert_eq!(hash_of(&stats), local_hash(&scene, &FRAME));
    assert_eq!(stats_field(&stats, "/refused_results"), 1);
    let ended = rt
        .block_on(async { tokio::time::timeout(Duration::from_secs(30), poacher).await })
        .expect("the poacher's stream was not closed")
        .unwrap()
        .expect("closed with a status");
    assert_eq!(ended.code(), tonic::Code::PermissionDenied, "{ended}");
    assert!(ended.message().contains("given no ray"), "{ended}");
    let log = cluster.coordinator_log();
    assert!(
        log.lines()
            .any(|l| l.contains("worker sent impossible tile results") && l.contains("poacher")),
        "{log}"
    );
    let status = cluster.status();
    let workers = status["workers"].as_array().unwrap();
    assert_eq!(workers.len(), 1, "{status}");
    assert_ne!(workers[0]["worker_id"], "poacher", "{status}");
}

/// Attaches as worker `id` and, once a frame starts, reports `victim` unreachable; answers
/// nothing else, until its control stream ends.
async fn accuser(url: String, id: &str, victim: String) {
    let (tx, mut answers) = attach(url, id).await;
    loop {
        match answers.message().await {
            Ok(Some(m)) => {
                if let Some(ToWorker::StartFrame(_)) = m.body {
                    let report = proto::WorkerMessage {
                        body: Some(FromWorker::PeerUnresponsive(proto::PeerUnresponsive {
                            peer_address: victim.clone(),
                            reason: "forged".into(),
                        })),
                    };
                    let _ = tx.send(report).await;
                }
            }
            Ok(None) | Err(_) => return,
        }
    }
}

#[test]
fn one_peer_reporting_a_worker_the_coordinator_hears_drops_the_accuser() {
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 2000, 2);
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::default()]);
    let victim = cluster.status()["workers"][0]["peer_address"]
        .as_str()
        .unwrap()
        .to_string();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let accused = rt.spawn(accuser(
        cluster.coordinator_url().to_string(),
        "liar",
        victim,
    ));
    cluster.wait_for_workers(2, Duration::from_secs(30));
    // The liar traces nothing: the frame ends only once it is dropped and its tiles go to the
    // worker it accused.
    let stats = submit_wait(&cluster, &FRAME, "accused");
    assert_eq!(hash_of(&stats), local_hash(&scene, &FRAME));
    // Dropping it ends its control stream.
    rt.block_on(async { tokio::time::timeout(Duration::from_secs(30), accused).await })
        .expect("the liar's stream was not closed")
        .unwrap();
    let status = cluster.status();
    let workers = status["workers"].as_array().unwrap();
    assert_eq!(workers.len(), 1, "{status}");
    assert_ne!(workers[0]["worker_id"], "liar", "{status}");
    // The first worker lost is the liar, and the accused never was.
    let log = cluster.coordinator_log();
    let lost: Vec<&str> = log.lines().filter(|l| l.contains("worker lost")).collect();
    assert!(
        lost.first().is_some_and(|l| l.contains("worker=liar ")),
        "{log}"
    );
    let honest = workers[0]["worker_id"].as_str().unwrap();
    let named = format!("worker={honest} ");
    assert!(!lost.iter().any(|l| l.contains(&named)), "{log}");
}

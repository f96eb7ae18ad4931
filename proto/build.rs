//! Compiles `rayfarm/v1` into message types only (no client or server code), with the pure-Rust
//! `protox` (no `protoc` needed on the build machine). `rayfarm-node` generates the gRPC
//! services over these same types.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = [
        "rayfarm/v1/jobs.proto",
        "rayfarm/v1/worker.proto",
        "rayfarm/v1/peer.proto",
    ];
    for f in files {
        println!("cargo:rerun-if-changed={f}");
    }
    let fds = protox::compile(files, ["."])?;
    // Ray batches and images as `Bytes`: handed on without copying.
    tonic_prost_build::configure()
        .build_client(false)
        .build_server(false)
        .bytes(".rayfarm.v1.PeerBundle.batches")
        .bytes(".rayfarm.v1.FetchResultResponse.image")
        .bytes(".rayfarm.v1.DomainChunk.data")
        // A report's queues as ordered maps: the coordinator keeps them so (`rounds::Queues`)
        // and takes a report's in without sorting them again; the worker counts them so.
        .btree_map(".rayfarm.v1.QueueReport")
        .compile_fds(fds)?;
    Ok(())
}

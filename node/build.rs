//! Compiles `proto/` once for the whole workspace, with the pure-Rust `protox` (no `protoc`
//! needed on the build machine).

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = [
        "../proto/rayfarm/v1/jobs.proto",
        "../proto/rayfarm/v1/worker.proto",
        "../proto/rayfarm/v1/peer.proto",
    ];
    for f in files {
        println!("cargo:rerun-if-changed={f}");
    }
    let fds = protox::compile(files, ["../proto"])?;
    // Ray batches and images as `Bytes`: handed on without copying.
    tonic_prost_build::configure()
        .bytes(".rayfarm.v1.PeerBundle.batches")
        .bytes(".rayfarm.v1.FetchResultResponse.image")
        .compile_fds(fds)?;
    Ok(())
}

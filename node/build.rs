//! Generates the gRPC services of `proto/rayfarm/v1` over the message types of `rayfarm-proto`
//! (one definition of every message for the whole workspace), with the pure-Rust `protox`.

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
    tonic_prost_build::configure()
        .extern_path(".rayfarm.v1", "::rayfarm_proto")
        .compile_fds(fds)?;
    Ok(())
}

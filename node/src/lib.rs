//! What every rayfarm process on the network shares, over the pure core (`rayfarm-core`): the
//! generated gRPC types and services, TLS and credentials, logging, test fault injection, a job's
//! frame as the user API carries it, and the checksum of a fetched result file.

pub mod bounds;
pub mod cpu;
pub mod fault;
pub mod heap;
pub mod http;
pub mod identity;
pub mod idle;
pub mod job;
pub mod listen;
pub mod metrics;
pub mod proto;
pub mod requests;
pub mod result_file;
pub mod security;
pub mod telemetry;

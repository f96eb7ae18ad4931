//! One module per subcommand.

pub mod bench;
pub mod bench_api;
pub mod cancel;
pub mod certs;
pub mod demo;
pub mod fetch;
pub mod health;
pub mod jobs;
pub mod prepare;
pub mod render;
pub mod sim;
pub mod status;
pub mod submit;
pub mod watch;

//! One module per subcommand.

pub mod demo;
pub mod prepare;
pub mod render;

//! marea: a MAREA-like middleware (work in progress).
#![warn(missing_docs)]

pub mod api;
pub mod codec;
pub mod config;
pub mod link;
pub mod name;
pub(crate) mod node;
pub mod protocol;
pub mod transport;
pub mod typeinfo;

pub use api::*;
pub use config::NetworkConfig;

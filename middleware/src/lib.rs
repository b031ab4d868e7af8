//! marea: a MAREA-like middleware (work in progress).
#![warn(missing_docs)]

pub mod codec;
pub mod name;
pub mod protocol;
pub mod transport;
pub mod typeinfo;

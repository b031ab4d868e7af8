//! FPMa: the USAL Flight Plan Manager library.
pub mod exec;
pub mod expand;
pub mod expr;
pub mod geo;
pub mod model;
pub mod parse;
pub mod polygon;
pub mod qgc;
pub mod vehicle;
pub mod xml;

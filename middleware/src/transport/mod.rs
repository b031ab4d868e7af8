//! Per-peer transport machinery shared by the links: the reliability layer (ARQ) for the safe
//! class, as pure state machines driven by `now` and input.

pub mod arq;
pub mod coalesce;

//! FPMa: the USAL Flight Plan Manager, the networked service that loads plans (checked by the
//! `flightplan` library), flies them through the VAS and takes changes in flight
//! ([`service::run`]). See `README.md` for its items and options.

pub mod service;

pub use service::run;

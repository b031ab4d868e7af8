//! Shared state: locking that stays valid when a holder panics, and the hasher of tables keyed
//! by what peers choose.

use std::sync::{Mutex, MutexGuard};

/// Locks a std mutex, ignoring poisoning.
///
/// Poisoning only says that another thread panicked while holding the lock. Everything this
/// project guards with a std mutex (queues, maps, counters, caches, plain values) is updated in
/// steps that each leave it structurally valid, so one panic must not cascade into every task
/// that touches the same state.
pub fn lock<T: ?Sized>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The hasher of the tables looked up per message or keyed by what a peer chooses (peers by
/// id, addresses, routes by offer id, UDP sessions by address): foldhash, several times cheaper
/// than std's SipHash on these small keys, and seeded per process so a peer cannot choose
/// colliding keys in advance.
pub(crate) type SeededHash = foldhash::fast::RandomState;

//! Locking shared state that stays valid when a holder panics.

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

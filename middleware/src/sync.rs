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

/// A task the node owns, boxed before it reaches tokio.
pub(crate) type BoxedTask = std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>;

/// Spawns `task` on `tasks` behind one boxed future type: tokio instantiates its task machinery
/// (harness, stages, join handle, drop glue; ~4 KB of code) once per spawned future type, and
/// the node spawns a dozen kinds of long-lived loops and per-request tasks. The one allocation
/// more per spawn is small beside the task's own.
pub(crate) fn spawn_tracked<F>(
    tasks: &tokio_util::task::TaskTracker,
    task: F,
) -> tokio::task::JoinHandle<()>
where
    F: std::future::Future<Output = ()> + Send + 'static,
{
    spawn_boxed(tasks, Box::pin(task))
}

fn spawn_boxed(
    tasks: &tokio_util::task::TaskTracker,
    task: BoxedTask,
) -> tokio::task::JoinHandle<()> {
    tasks.spawn(task)
}

//! What a station's middleware tasks and its pages share to follow changes and to stop: the
//! wake-up of the live channels, the cancellation, the tasks owned, and the loop that feeds the
//! station from a subscription.

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

/// A station's change notification, cancellation and tasks.
#[derive(Debug, Default)]
pub struct Live {
    /// Woken on every change the page should see at once.
    pub changed: Notify,
    /// Cancelled when the station stops.
    pub cancel: CancellationToken,
    /// Every task the station spawns (waited for when it stops).
    pub tasks: TaskTracker,
}

impl Live {
    /// Nothing changed yet, no task, stopping at `cancel`.
    pub fn new(cancel: CancellationToken) -> Self {
        Self {
            changed: Notify::new(),
            cancel,
            tasks: TaskTracker::new(),
        }
    }

    /// Spawns a task handing every sample of `sub` to `on_sample` until the station stops or
    /// the subscription closes; a sample that does not decode is logged as `what` and skipped.
    pub fn follow<T: marea::Payload>(
        &self,
        sub: marea::Subscription<T>,
        what: &'static str,
        mut on_sample: impl FnMut(marea::Sample<T>) + Send + 'static,
    ) {
        let cancel = self.cancel.clone();
        self.tasks.spawn(async move {
            loop {
                let got = tokio::select! {
                    r = sub.recv() => r,
                    _ = cancel.cancelled() => return,
                };
                match got {
                    Ok(s) => on_sample(s),
                    Err(marea::RecvError::Closed) => return,
                    Err(e) => tracing::warn!("{what}: {e}"),
                }
            }
        });
    }
}

//! The life of a process hosting a node: services stop cleanly (and the node says Bye to its
//! peers) when the process is asked to end with Ctrl-C or SIGTERM.

use tokio_util::sync::CancellationToken;

/// Resolves when the process receives Ctrl-C (SIGINT) or SIGTERM.
pub async fn terminated() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        if let Ok(mut term) = signal(SignalKind::terminate()) {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            return;
        }
    }
    let _ = tokio::signal::ctrl_c().await;
}

/// A token cancelled when the process receives Ctrl-C or SIGTERM (see [`terminated`]). Call it
/// inside a tokio runtime.
pub fn cancelled_on_signal() -> CancellationToken {
    let token = CancellationToken::new();
    let stop = token.clone();
    tokio::spawn(async move {
        terminated().await;
        stop.cancel();
    });
    token
}

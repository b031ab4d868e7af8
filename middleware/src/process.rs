//! The life of a process hosting a node: services stop cleanly (and the node says Bye to its
//! peers) when the process is asked to end with Ctrl-C or SIGTERM; where its user's state is
//! ([`state_dir`]).

use std::path::PathBuf;

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

/// The user's state directory for USAL: `$XDG_STATE_HOME/usal` when that is an absolute path,
/// else `$HOME/.local/state/usal`; `None` when neither is set.
pub fn state_dir() -> Option<PathBuf> {
    state_dir_from(std::env::var_os("XDG_STATE_HOME"), std::env::var_os("HOME"))
}

fn state_dir_from(
    xdg_state_home: Option<std::ffi::OsString>,
    home: Option<std::ffi::OsString>,
) -> Option<PathBuf> {
    // The XDG spec: a relative path in the variable is invalid and ignored.
    let absolute = |v: std::ffi::OsString| {
        let p = PathBuf::from(v);
        p.is_absolute().then_some(p)
    };
    if let Some(p) = xdg_state_home.and_then(absolute) {
        return Some(p.join("usal"));
    }
    home.and_then(absolute).map(|h| h.join(".local/state/usal"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_dir_is_xdg_state_home_else_under_home_never_tmp() {
        let d =
            |x: Option<&str>, h: Option<&str>| state_dir_from(x.map(Into::into), h.map(Into::into));
        assert_eq!(d(Some("/s"), Some("/h")), Some(PathBuf::from("/s/usal")));
        assert_eq!(
            d(None, Some("/home/op")),
            Some(PathBuf::from("/home/op/.local/state/usal"))
        );
        // A relative XDG_STATE_HOME is ignored, as the spec says.
        assert_eq!(
            d(Some("rel"), Some("/home/op")),
            Some(PathBuf::from("/home/op/.local/state/usal"))
        );
        assert_eq!(d(None, None), None);
    }
}

//! Every mission `usal run` starts is sealed, with no configuration: its domain key is made
//! once per mission in the user's state directory (`missions/<name>/domain.key`, mode 0600)
//! and reused by later runs, and for as long as the run lasts it is where every node of the
//! run's domain finds it by the domain's name ([`marea::config::domain_key`]): the mission's
//! services, its gateways and routers, the flight log, and this user's `usal list/echo/call/
//! send` with `--domain`. Another user, with another state directory, finds nothing, and
//! nothing without the key is heard.

use std::path::{Path, PathBuf};

use anyhow::Context;

/// A run's sealing: the mission's key, and the entry naming it for the run's domain, removed
/// when the run ends.
pub(crate) struct Sealed {
    /// The mission's domain key.
    pub key: PathBuf,
    /// The domain's entry (a link to `key`).
    entry: PathBuf,
}

impl Drop for Sealed {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.entry);
    }
}

/// A directory only this user may enter, made if missing.
fn private_dir(dir: &Path) -> anyhow::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700))
        .with_context(|| format!("making {} private", dir.display()))
}

/// Seals the run of mission `name` in `domain` (see the module docs).
pub(crate) fn seal(name: &str, domain: &str) -> anyhow::Result<Sealed> {
    let state = marea::state_dir().context(
        "no state directory for the mission's domain key: set HOME or XDG_STATE_HOME (or run the mission with security=\"off\")",
    )?;
    let dir = state.join("missions").join(name);
    private_dir(&dir)?;
    let key = dir.join("domain.key");
    if key.exists() {
        // Reused, once checked: a key others may read is refused here, not in every child.
        marea::link::auth::DomainKey::load(&key)?;
    } else {
        marea::link::auth::DomainKey::create_file(&key)?;
    }
    let entry = marea::config::domain_key::domain_key_path(domain)
        .context("no state directory for the domain's key")?;
    if let Some(parent) = entry.parent() {
        private_dir(parent)?;
    }
    // A run killed outright leaves its entry: a later run of the same domain replaces it.
    let _ = std::fs::remove_file(&entry);
    std::os::unix::fs::symlink(&key, &entry)
        .with_context(|| format!("linking {} to {}", entry.display(), key.display()))?;
    Ok(Sealed { key, entry })
}

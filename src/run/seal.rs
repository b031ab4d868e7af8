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
        let _ = std::fs::remove_file(owner_file(&self.entry));
    }
}

/// The file naming the launcher that made `entry` (its pid), so that the entry of a run
/// killed outright (SIGKILL: nothing removes it) is removed by a later run.
fn owner_file(entry: &Path) -> PathBuf {
    entry.with_extension("pid")
}

/// Removes the entries in `dir` whose launcher is gone, or that name none (the owner file
/// is written before the entry, so a live run's entry always has one).
fn prune(dir: &Path) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    for e in rd.filter_map(Result::ok) {
        let entry = e.path();
        if entry.extension().is_none_or(|x| x != "key") {
            continue;
        }
        let owner = owner_file(&entry);
        let alive = std::fs::read_to_string(&owner)
            .ok()
            .and_then(|s| s.trim().parse::<libc::pid_t>().ok())
            .is_some_and(process_exists);
        if !alive {
            let _ = std::fs::remove_file(&entry);
            let _ = std::fs::remove_file(&owner);
        }
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
        prune(parent);
    }
    // The owner first: another run's prune never finds this entry without it.
    std::fs::write(owner_file(&entry), format!("{}\n", std::process::id()))
        .with_context(|| format!("writing {}", owner_file(&entry).display()))?;
    // A run of the same domain killed outright may have left its entry: replaced.
    let _ = std::fs::remove_file(&entry);
    std::os::unix::fs::symlink(&key, &entry)
        .with_context(|| format!("linking {} to {}", entry.display(), key.display()))?;
    Ok(Sealed { key, entry })
}

/// Whether process `pid` exists (signal 0 checks without signalling; EPERM: it does, as
/// another user's).
#[allow(unsafe_code)]
fn process_exists(pid: libc::pid_t) -> bool {
    if pid <= 0 {
        return false;
    }
    // SAFETY: kill with signal 0 sends nothing; it only reads the process table.
    let r = unsafe { libc::kill(pid, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dead_launchers_entry_is_pruned_and_a_live_ones_kept() {
        let dir = tempfile::tempdir().unwrap();
        let entry = |n: &str, pid: String| {
            let key = dir.path().join(format!("{n}.key"));
            std::fs::write(&key, "k").unwrap();
            std::fs::write(owner_file(&key), pid).unwrap();
            key
        };
        let mine = entry("mine", std::process::id().to_string());
        // A child that has ended and been reaped: its pid names no process (for now).
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let gone = child.id();
        child.wait().unwrap();
        let dead = entry("dead", gone.to_string());
        let junk = entry("junk", "not a pid".into());
        let orphan = dir.path().join("orphan.key");
        std::fs::write(&orphan, "k").unwrap();
        prune(dir.path());
        assert!(mine.exists() && owner_file(&mine).exists());
        assert!(!dead.exists() && !owner_file(&dead).exists());
        assert!(!junk.exists() && !owner_file(&junk).exists());
        assert!(!orphan.exists(), "an entry naming no launcher");
    }
}

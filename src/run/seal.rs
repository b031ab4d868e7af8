//! Every mission `usal run` starts is sealed, with no configuration. The mission's seal is
//! made once in the user's state directory (`missions/<name>/`, 0700) and reused by later
//! runs: its domain key, an identity key per namespace of its nodes, one for its gateways and
//! one for this user's tools, the roster binding each namespace to its key (and the gateway
//! role to the gateways' key only), the `<access>` rules of its nodes,
//! and the key that signs MAVLink 2 between each VAS and its simulator (each key mode 0600).
//! For as long as the run lasts the directory is where every node of the run's domain finds
//! it by the domain's name ([`marea::config::domain_seal`]): the mission's services, its
//! gateways and routers, the flight log, and this user's `usal list/echo/call/send` with
//! `--domain`. Another user, with another state directory, finds nothing, and nothing without
//! the key is heard.

use std::path::{Path, PathBuf};

use anyhow::Context;
use marea::config::domain_seal::{
    access_path, domain_seal_dir, gateway_identity_path, identity_path,
};
use marea::identity::{IdentityKey, Listing, Roster};
use marea::link::auth::DomainKey;

use super::mission::Mission;

/// A run's seal: the mission's directory, and the entry naming it for the run's domain,
/// removed when the run ends.
pub(crate) struct Sealed {
    /// The mission's seal directory.
    pub dir: PathBuf,
    /// The domain's entry (a link to `dir`).
    entry: PathBuf,
}

impl Sealed {
    /// The domain key.
    pub fn key(&self) -> PathBuf {
        self.dir.join("domain.key")
    }

    /// The MAVLink 2 signing key of the mission's VAS-simulator links.
    pub fn mavlink_key(&self) -> PathBuf {
        self.dir.join("mavlink.key")
    }
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
        if entry.extension().is_some_and(|x| x == "pid") {
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

/// A 32-byte secret key file (64 hex digits, 0600) at `path`: made if missing, else checked
/// (a key others may read is refused here, not in every child).
fn secret_key(path: &Path) -> anyhow::Result<()> {
    if path.exists() {
        DomainKey::load(path)?;
    } else {
        DomainKey::create_file(path)?;
    }
    Ok(())
}

/// The public half of the identity key at `path`: made if missing, else read.
fn identity(path: &Path) -> anyhow::Result<[u8; 32]> {
    let key = if path.exists() {
        IdentityKey::load(path)?
    } else {
        // A public file left without its secret is stale: made afresh with the key.
        let _ = std::fs::remove_file(IdentityKey::public_path(path));
        IdentityKey::create_files(path)?
    };
    Ok(key.public())
}

/// Writes `text` to `path` through a temporary file renamed over it: a run of the same
/// mission starting meanwhile reads the old file or the new, never half of one.
/// Mode 0644 whatever the umask would add: nodes refuse a roster group or others may write.
fn replace_file(path: &Path, text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    // A leftover of a crashed run of this pid would keep its mode: start afresh.
    let _ = std::fs::remove_file(&tmp);
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o644)
        .open(&tmp)
        .and_then(|mut f| f.write_all(text.as_bytes()))
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}

/// An exclusive lock on `path` (made if missing), held until the file is dropped: runs of
/// the same mission starting at once make its keys one after the other, never both.
#[allow(unsafe_code)]
fn lock(path: &Path) -> anyhow::Result<std::fs::File> {
    use std::os::fd::AsRawFd;
    let file = std::fs::File::options()
        .create(true)
        .truncate(false)
        .write(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    // SAFETY: flock on a descriptor this function owns (open for as long as `file`).
    let r = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX) };
    if r != 0 {
        return Err(std::io::Error::last_os_error())
            .with_context(|| format!("locking {}", path.display()));
    }
    Ok(file)
}

/// Makes (or brings up to date) the seal of `mission` in `dir`: see the module docs.
fn make_seal(mission: &Mission, dir: &Path) -> anyhow::Result<()> {
    private_dir(dir)?;
    let _lock = lock(&dir.join(".lock"))?;
    secret_key(&dir.join("domain.key"))?;
    secret_key(&dir.join("mavlink.key"))?;
    private_dir(&dir.join("identities"))?;
    let mut roster = Roster::default();
    let mut namespaces: Vec<&str> = mission
        .nodes
        .iter()
        .filter_map(|n| n.namespace.as_deref())
        .collect();
    namespaces.sort_unstable();
    namespaces.dedup();
    for ns in namespaces {
        roster.allow(identity(&identity_path(dir, ns))?, vec![ns.to_owned()]);
    }
    // The run's gateways and bridges: the only key that may speak for other nodes.
    roster.list(Listing {
        key: identity(&gateway_identity_path(dir))?,
        namespaces: vec!["*".to_owned()],
        nodes: Vec::new(),
        gateway: true,
    });
    // Anything else of this user: usal's tools, nodes of no namespace.
    roster.allow(identity(&dir.join("tools.id"))?, vec!["*".to_owned()]);
    replace_file(&dir.join("identities.xml"), &roster.to_xml())?;
    // Access rules as this run's mission file says, none left from an earlier version of it
    // (each file replaced whole: a node of a run already going reads the old or the new).
    private_dir(&dir.join("access"))?;
    let mut written = Vec::new();
    for node in &mission.nodes {
        if let (Some(ns), Some(rules)) = (&node.namespace, &node.access) {
            let path = access_path(dir, ns);
            replace_file(&path, &rules.to_xml())?;
            written.push(path);
        }
    }
    if let Ok(rd) = std::fs::read_dir(dir.join("access")) {
        for e in rd.filter_map(Result::ok) {
            if !written.contains(&e.path()) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    Ok(())
}

/// Seals the run of `mission` in `domain` (see the module docs).
pub(crate) fn seal(mission: &Mission, domain: &str) -> anyhow::Result<Sealed> {
    let state = marea::state_dir().context(
        "no state directory for the mission's keys: set HOME or XDG_STATE_HOME (or run the mission with security=\"off\")",
    )?;
    let dir = state.join("missions").join(&mission.name);
    make_seal(mission, &dir)?;
    let entry = domain_seal_dir(domain).context("no state directory for the domain's seal")?;
    if let Some(parent) = entry.parent() {
        private_dir(parent)?;
        prune(parent);
    }
    // The owner first: another run's prune never finds this entry without it.
    std::fs::write(owner_file(&entry), format!("{}\n", std::process::id()))
        .with_context(|| format!("writing {}", owner_file(&entry).display()))?;
    // A run of the same domain killed outright may have left its entry: replaced.
    let _ = std::fs::remove_file(&entry);
    std::os::unix::fs::symlink(&dir, &entry)
        .with_context(|| format!("linking {} to {}", entry.display(), dir.display()))?;
    Ok(Sealed { dir, entry })
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

    fn mission(access_for_rover1: bool) -> Mission {
        let access = if access_for_rover1 {
            r#"<access><allow kind="call" item="rover1/**" from="gcs/*"/></access>"#
        } else {
            ""
        };
        let src = format!(
            r#"<mission name="m">
  <node name="air1" namespace="rover1"><mavsim/><vas/>{access}</node>
  <node name="air2" namespace="rover2"><mavsim/><vas/></node>
  <node name="ground" namespace="gcs"><station plan="../flightplans/rover-demo.xml" fpma="rover1/fpma"/></node>
</mission>"#
        );
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/missions");
        Mission::parse(&src, &base).ok().expect("a valid mission")
    }

    #[test]
    fn a_mission_s_seal_binds_each_namespace_to_its_own_key_and_is_reused() {
        use std::os::unix::fs::PermissionsExt;
        let state = tempfile::tempdir().unwrap();
        let dir = state.path().join("m");
        make_seal(&mission(true), &dir).unwrap();
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&dir), 0o700);
        for secret in [
            dir.join("domain.key"),
            dir.join("mavlink.key"),
            dir.join("tools.id"),
            gateway_identity_path(&dir),
            identity_path(&dir, "rover1"),
            identity_path(&dir, "rover2"),
            identity_path(&dir, "gcs"),
        ] {
            assert_eq!(mode(&secret), 0o600, "{}", secret.display());
        }
        let public = |p: PathBuf| IdentityKey::load(&p).unwrap().public();
        let roster = marea::identity::Roster::load(&dir.join("identities.xml")).unwrap();
        for ns in ["rover1", "rover2", "gcs"] {
            assert_eq!(
                roster.namespaces(&public(identity_path(&dir, ns))),
                [ns],
                "{ns}'s key owns {ns} and nothing else"
            );
        }
        assert_eq!(roster.namespaces(&public(dir.join("tools.id"))), ["*"]);
        // Only the gateways' key makes a gateway: not the tools', not a namespace's.
        assert!(roster
            .grant(&public(gateway_identity_path(&dir)))
            .gateway_for("", "gateway"));
        for other in [dir.join("tools.id"), identity_path(&dir, "rover1")] {
            assert!(!roster
                .grant(&public(other))
                .gateway_for("rover1", "gateway"));
        }
        let rules = marea::config::AccessConfig::load(&access_path(&dir, "rover1")).unwrap();
        assert_eq!(rules, mission(true).nodes[0].access.clone().unwrap());
        assert!(!access_path(&dir, "rover2").exists(), "no rules, no file");

        // The next run reuses every key, and drops rules its mission file no longer has.
        let before = std::fs::read(identity_path(&dir, "rover1")).unwrap();
        let domain = std::fs::read(dir.join("domain.key")).unwrap();
        make_seal(&mission(false), &dir).unwrap();
        assert_eq!(
            std::fs::read(identity_path(&dir, "rover1")).unwrap(),
            before
        );
        assert_eq!(std::fs::read(dir.join("domain.key")).unwrap(), domain);
        assert!(!access_path(&dir, "rover1").exists());
    }

    #[test]
    fn runs_of_one_mission_sealing_at_once_share_one_set_of_keys() {
        let state = tempfile::tempdir().unwrap();
        let dir = state.path().join("m");
        let m = mission(true);
        std::thread::scope(|s| {
            let runs: Vec<_> = (0..4).map(|_| s.spawn(|| make_seal(&m, &dir))).collect();
            for r in runs {
                r.join().unwrap().unwrap();
            }
        });
        let roster = marea::identity::Roster::load(&dir.join("identities.xml")).unwrap();
        let rover1 = IdentityKey::load(&identity_path(&dir, "rover1")).unwrap();
        assert_eq!(roster.namespaces(&rover1.public()), ["rover1"]);
    }

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

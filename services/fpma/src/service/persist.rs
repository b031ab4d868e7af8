//! The FPMa's plan and progress on disk, so a restarted FPMa resumes where it was.
//!
//! One JSON file, `<stateDir>/fpma-state.json`, replaced atomically on every change: written
//! to a temporary file beside it, synced, renamed over the old one, and the directory synced,
//! so after a crash the file holds either the previous state or the new one, never a mix. The
//! directory is created private (0700) and files are opened without following links.

use std::io::Write;
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::core::Persisted;

/// Layout version of the file: a file of another version is not resumed.
const FORMAT: u32 = 1;

#[derive(Serialize, Deserialize)]
struct OnDisk {
    format: u32,
    state: Persisted,
}

/// The state file of one FPMa.
#[derive(Clone, Debug)]
pub struct StateFile {
    dir: PathBuf,
    path: PathBuf,
}

impl StateFile {
    /// The state file in `dir` (created when first saved).
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_owned(),
            path: dir.join("fpma-state.json"),
        }
    }

    /// Where the state is kept.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The persisted state; `Ok(None)` when there is none.
    ///
    /// # Errors
    /// An unreadable, corrupt or other-version file (the caller logs it and starts clean).
    pub fn load(&self) -> anyhow::Result<Option<Persisted>> {
        let bytes = match std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&self.path)
        {
            Ok(mut f) => {
                let mut b = Vec::new();
                std::io::Read::read_to_end(&mut f, &mut b)
                    .with_context(|| format!("reading {}", self.path.display()))?;
                b
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e).with_context(|| format!("opening {}", self.path.display())),
        };
        let d: OnDisk = serde_json::from_slice(&bytes)
            .with_context(|| format!("{} is corrupt", self.path.display()))?;
        anyhow::ensure!(
            d.format == FORMAT,
            "{} has format {}, this fpma reads {FORMAT}",
            self.path.display(),
            d.format
        );
        Ok(Some(d.state))
    }

    /// Replaces the persisted state atomically (see the module docs).
    ///
    /// # Errors
    /// The directory or file cannot be created, written, synced or renamed.
    pub fn save(&self, state: &Persisted) -> anyhow::Result<()> {
        let json = serde_json::to_vec(&OnDisk {
            format: FORMAT,
            state: state.clone(),
        })
        .context("encoding the state")?;
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(0o700)
            .create(&self.dir)
            .with_context(|| format!("creating {}", self.dir.display()))?;
        let tmp = self.dir.join("fpma-state.json.tmp");
        // Whatever is there (a leftover of a crash, a planted link) goes; the new one is
        // created exclusively, never written through a link.
        match std::fs::remove_file(&tmp) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(e).with_context(|| format!("removing {}", tmp.display())),
        }
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&tmp)
            .with_context(|| format!("opening {}", tmp.display()))?;
        f.write_all(&json)
            .and_then(|()| f.sync_all())
            .with_context(|| format!("writing {}", tmp.display()))?;
        drop(f);
        std::fs::rename(&tmp, &self.path)
            .with_context(|| format!("renaming into {}", self.path.display()))?;
        std::fs::File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .with_context(|| format!("syncing {}", self.dir.display()))?;
        Ok(())
    }

    /// Moves an unusable state file aside (`….corrupt`), so it is kept for a look and not
    /// read again.
    pub fn set_aside(&self) {
        let aside = self.path.with_extension("json.corrupt");
        if let Err(e) = std::fs::rename(&self.path, &aside) {
            tracing::warn!("cannot move {} aside: {e}", self.path.display());
        }
    }
}

#[cfg(test)]
mod tests {
    use std::os::unix::fs::PermissionsExt;

    use super::*;
    use flightplan::exec::Executive;
    use flightplan::vehicle::VehicleParams;

    fn state() -> Persisted {
        let plan = flightplan::check::load(
            include_str!("../../../../config/flightplans/rover-demo.xml"),
            &VehicleParams::rover(),
        )
        .unwrap();
        let mut exec = Executive::from_checked(plan);
        exec.waypoint_reached(1, 0).unwrap();
        Persisted {
            source: "rover-demo.xml".into(),
            exec,
            pending: Vec::new(),
            max_pushed: Some(7),
            last_reached: Some(0),
            taken_over: None,
        }
    }

    #[test]
    fn saved_state_loads_back_and_the_directory_is_private() {
        let t = tempfile::tempdir().unwrap();
        let f = StateFile::new(&t.path().join("rover1").join("fpma"));
        assert!(f.load().unwrap().is_none(), "no file: nothing to resume");
        f.save(&state()).unwrap();
        // Saved again over the first: the rename replaces it.
        f.save(&state()).unwrap();
        let back = f.load().unwrap().expect("a state");
        assert_eq!(back.exec.state(), state().exec.state());
        assert_eq!(
            back.exec.next_waypoints(100),
            state().exec.next_waypoints(100)
        );
        assert_eq!((back.max_pushed, back.last_reached), (Some(7), Some(0)));
        let dir = f.path().parent().unwrap();
        let names: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(names, ["fpma-state.json"], "temporary file left");
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(dir), 0o700);
        assert_eq!(mode(f.path()), 0o600);
    }

    #[test]
    fn a_link_at_the_temporary_path_is_not_written_through() {
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("fpma");
        std::fs::create_dir(&dir).unwrap();
        let target = t.path().join("victim");
        std::fs::write(&target, b"keep").unwrap();
        std::os::unix::fs::symlink(&target, dir.join("fpma-state.json.tmp")).unwrap();
        let f = StateFile::new(&dir);
        f.save(&state()).unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"keep");
        assert!(f.load().unwrap().is_some());
    }

    #[test]
    fn corrupt_or_foreign_files_are_errors_not_panics() {
        let t = tempfile::tempdir().unwrap();
        let f = StateFile::new(t.path());
        for bad in [
            &b""[..],
            b"{",
            b"\xff\xfe",
            b"{\"format\":1}",
            b"{\"format\":99,\"state\":null}",
        ] {
            std::fs::write(f.path(), bad).unwrap();
            let e = f.load().unwrap_err();
            assert!(format!("{e:#}").contains("fpma-state.json"), "{e:#}");
        }
        f.set_aside();
        assert!(!f.path().exists());
        assert!(t.path().join("fpma-state.json.corrupt").exists());
    }
}

//! The binaries `usal` starts, found next to its own executable and, in a source checkout,
//! built with cargo when missing or older than their sources.
//!
//! A binary's sources are what cargo says they are: the dep-info file it writes beside each
//! binary (`<target>/<profile>/<name>.d`) lists every source file the binary was built from,
//! its path dependencies' included. A binary is out of date when one of them is newer than it
//! (or gone): a service built before the sources changed would run old code beside a new
//! launcher (a VAS built before the domain key lookup joined unsealed, and the sealed station
//! never heard it). A change elsewhere in the checkout (a test, another service) leaves it be.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context};
use serde_json::json;

use super::ui::Ui;

/// The service binaries a mission needs, found next to the running `usal`.
pub(crate) struct Bins {
    dir: PathBuf,
}

impl Bins {
    pub(crate) fn path(&self, name: &str) -> PathBuf {
        self.dir
            .join(format!("{name}{}", std::env::consts::EXE_SUFFIX))
    }

    /// Cargo's dep-info file of binary `name`.
    fn dep_info(&self, name: &str) -> PathBuf {
        self.dir.join(format!("{name}.d"))
    }

    /// Whether binary `name` is older than one of its sources per its dep-info file; a binary
    /// without one (installed, not built here) is taken as it is.
    fn is_stale(&self, name: &str) -> bool {
        let Ok(built) = std::fs::metadata(self.path(name)).and_then(|m| m.modified()) else {
            return false;
        };
        let Ok(dep_info) = std::fs::read_to_string(self.dep_info(name)) else {
            return false;
        };
        sources_of(&dep_info).iter().any(|source| {
            std::fs::metadata(source)
                .and_then(|m| m.modified())
                .map_or(true, |t| t > built)
        })
    }
}

/// The source files a dep-info file lists (Makefile syntax: `target: dep dep ...`, a space
/// inside a path escaped as `\ `; comment lines start with `#`). Only the first rule's
/// prerequisites: the binary's.
fn sources_of(dep_info: &str) -> Vec<PathBuf> {
    let Some(rule) = dep_info
        .lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
    else {
        return Vec::new();
    };
    // The target itself ends at the first unescaped ": ".
    let mut prerequisites = None;
    let bytes = rule.as_bytes();
    for i in 0..bytes.len() {
        if bytes[i] == b':'
            && bytes.get(i + 1).is_none_or(|c| *c == b' ')
            && (i == 0 || bytes[i - 1] != b'\\')
        {
            prerequisites = Some(&rule[i + 1..]);
            break;
        }
    }
    let Some(prerequisites) = prerequisites else {
        return Vec::new();
    };
    let mut sources = Vec::new();
    let mut current = String::new();
    let mut chars = prerequisites.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\\' if chars.peek() == Some(&' ') => {
                current.push(' ');
                chars.next();
            }
            ' ' => {
                if !current.is_empty() {
                    sources.push(PathBuf::from(std::mem::take(&mut current)));
                }
            }
            c => current.push(c),
        }
    }
    if !current.is_empty() {
        sources.push(PathBuf::from(current));
    }
    sources
}

/// The directory of `usal`'s own executable, where the binaries it starts are: packages'
/// binaries named as their package (`packages`) and this package's own (`own`), built with
/// cargo (saying so on `ui`) when missing or out of date and this is a source checkout.
pub(crate) fn find_or_build(packages: &[&str], own: &[&str], ui: &Ui) -> anyhow::Result<Bins> {
    let exe = std::env::current_exe().context("locating the usal executable")?;
    let dir = exe
        .parent()
        .ok_or_else(|| anyhow!("usal has no parent directory"))?
        .to_owned();
    let bins = Bins { dir };
    let all = || packages.iter().chain(own).copied();
    let missing: Vec<&str> = all().filter(|b| !bins.path(b).is_file()).collect();
    let stale: Vec<&str> = all()
        .filter(|b| !missing.contains(b) && bins.is_stale(b))
        .collect();
    if missing.is_empty() && stale.is_empty() {
        return Ok(bins);
    }
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"));
    let target = bins.dir.parent().map(Path::to_path_buf);
    let is_checkout = workspace.join("Cargo.toml").is_file() && target.is_some();
    if missing.is_empty() && !is_checkout {
        // Out of date against sources that are no longer here to build: run them as they are.
        return Ok(bins);
    }
    if !is_checkout {
        bail!(
            "{} not found next to {} (build them with `cargo build --release {}`)",
            missing.join(", "),
            exe.display(),
            missing
                .iter()
                .map(|b| if own.contains(b) {
                    format!("--bin {b}")
                } else {
                    format!("-p {b}")
                })
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    // <target>/<profile>/usal: build into the same target directory and profile.
    let profile = bins
        .dir
        .file_name()
        .and_then(|p| p.to_str())
        .unwrap_or("debug")
        .to_owned();
    if !missing.is_empty() {
        ui.note(
            &format!(
                "{} not built yet: building them once with cargo ({profile} profile)",
                missing.join(", ")
            ),
            json!({"event": "building", "bins": missing, "profile": profile}),
        );
    }
    if !stale.is_empty() {
        ui.note(
            &format!(
                "{} out of date (a source changed since the build): rebuilding with cargo ({profile} profile)",
                stale.join(", ")
            ),
            json!({"event": "building", "bins": stale, "profile": profile, "stale": true}),
        );
    }
    let to_build = |b: &&str| missing.contains(b) || stale.contains(b);
    // Other packages by name; this package's own binaries by name.
    let mut selections: Vec<Vec<String>> = Vec::new();
    let other: Vec<&str> = packages.iter().copied().filter(to_build).collect();
    if !other.is_empty() {
        selections.push(
            other
                .iter()
                .flat_map(|b| ["-p".into(), b.to_string()])
                .collect(),
        );
    }
    let ours: Vec<&str> = own.iter().copied().filter(to_build).collect();
    if !ours.is_empty() {
        let mut v = vec!["-p".to_owned(), "usal".to_owned()];
        v.extend(ours.iter().flat_map(|b| ["--bin".into(), b.to_string()]));
        selections.push(v);
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    for selection in selections {
        let mut cmd = std::process::Command::new(&cargo);
        cmd.arg("build").current_dir(workspace);
        match profile.as_str() {
            "debug" => {}
            "release" => {
                cmd.arg("--release");
            }
            other => {
                cmd.args(["--profile", other]);
            }
        }
        cmd.args(&selection);
        if let Some(t) = &target {
            cmd.env("CARGO_TARGET_DIR", t);
        }
        // Cargo's own progress goes to our stderr: it is the user's build.
        let status = cmd
            .status()
            .context("running cargo (is it installed?) to build them")?;
        if !status.success() {
            bail!(
                "building {} failed ({status})",
                all().filter(to_build).collect::<Vec<_>>().join(", ")
            );
        }
    }
    let still: Vec<&str> = all().filter(|b| !bins.path(b).is_file()).collect();
    if !still.is_empty() {
        bail!(
            "cargo built, but {} are not in {}",
            still.join(", "),
            bins.dir.display()
        );
    }
    Ok(bins)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, SystemTime};

    fn write_at(path: &Path, secs: u64) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, "x").unwrap();
        std::fs::File::options()
            .write(true)
            .open(path)
            .unwrap()
            .set_modified(SystemTime::UNIX_EPOCH + Duration::from_secs(secs))
            .unwrap();
    }

    #[test]
    fn a_dep_info_file_lists_the_binary_s_sources_with_escaped_spaces() {
        let d = "/t/release/vas: /w/services/vas/src/main.rs /w/my\\ dir/lib.rs /w/middleware/src/lib.rs\n\n\
                 /w/services/vas/src/main.rs:\n";
        assert_eq!(
            sources_of(d),
            [
                "/w/services/vas/src/main.rs",
                "/w/my dir/lib.rs",
                "/w/middleware/src/lib.rs"
            ]
            .map(PathBuf::from)
        );
        assert!(sources_of("").is_empty());
        assert!(sources_of("# only a comment\n").is_empty());
        assert!(sources_of("no rule here").is_empty());
    }

    #[test]
    fn a_binary_is_stale_when_a_source_of_its_own_is_newer_or_gone_and_only_then() {
        let ws = tempfile::tempdir().unwrap();
        let bins = Bins {
            dir: ws.path().join("target/release"),
        };
        let main = ws.path().join("services/vas/src/main.rs");
        let lib = ws.path().join("middleware/src/lib.rs");
        let other = ws.path().join("services/fmo/src/main.rs");
        write_at(&main, 100);
        write_at(&lib, 100);
        write_at(&other, 900);
        write_at(&bins.path("vas"), 200);
        assert!(
            !bins.is_stale("vas"),
            "no dep-info: an installed binary is taken as it is"
        );
        std::fs::write(
            bins.dep_info("vas"),
            format!(
                "{}: {} {}\n",
                bins.path("vas").display(),
                main.display(),
                lib.display()
            ),
        )
        .unwrap();
        assert!(
            !bins.is_stale("vas"),
            "sources older, another package's newer"
        );
        write_at(&lib, 300);
        assert!(
            bins.is_stale("vas"),
            "a dependency's source changed after the build"
        );
        write_at(&lib, 100);
        std::fs::remove_file(&main).unwrap();
        assert!(bins.is_stale("vas"), "a source it was built from is gone");
        assert!(!bins.is_stale("fmo"), "not built: missing, not stale");
    }
}

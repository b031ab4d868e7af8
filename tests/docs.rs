//! The README and the book under `docs/` stay true: every relative link resolves (file and
//! heading), every `usal` command of a shell snippet names a subcommand `usal` has, every
//! repository path a snippet names exists, the README stays a guide (at most 300 lines), and the
//! architecture page's table of crates says exactly what `cargo metadata` says each uses.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

const USAL: &str = env!("CARGO_BIN_EXE_usal");

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The pages checked: the README, the book, and every package's README.
fn pages() -> Vec<PathBuf> {
    let mut pages = vec![root().join("README.md")];
    for dir in ["docs", "services", "crates"] {
        let Ok(entries) = std::fs::read_dir(root().join(dir)) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.extension().is_some_and(|x| x == "md") {
                pages.push(p);
            } else if p.join("README.md").is_file() {
                pages.push(p.join("README.md"));
            }
        }
    }
    for dir in ["sim", "middleware", "router", "gateway"] {
        let p = root().join(dir).join("README.md");
        if p.is_file() {
            pages.push(p);
        }
    }
    pages.sort();
    pages
}

fn read(p: &Path) -> String {
    std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn shown(p: &Path) -> String {
    p.strip_prefix(root()).unwrap_or(p).display().to_string()
}

/// The page's text outside fenced code blocks, and its fenced blocks with their info string.
fn split_fences(text: &str) -> (String, Vec<(String, String)>) {
    let mut prose = String::new();
    let mut blocks = Vec::new();
    let mut fence: Option<(String, String)> = None;
    for line in text.lines() {
        let t = line.trim_start();
        match &mut fence {
            None if t.starts_with("```") => fence = Some((t[3..].trim().to_owned(), String::new())),
            None => {
                prose.push_str(line);
                prose.push('\n');
            }
            Some(_) if t.starts_with("```") => blocks.extend(fence.take()),
            Some((_, body)) => {
                body.push_str(line);
                body.push('\n');
            }
        }
    }
    (prose, blocks)
}

/// Markdown links `[text](target)` in `prose` (inline code spans removed first).
fn links(prose: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in prose.lines() {
        let mut clean = String::new();
        let mut in_code = false;
        for c in line.chars() {
            if c == '`' {
                in_code = !in_code;
            } else if !in_code {
                clean.push(c);
            }
        }
        let mut rest = clean.as_str();
        while let Some(i) = rest.find("](") {
            let after = &rest[i + 2..];
            let Some(j) = after.find(')') else { break };
            out.push(after[..j].trim().to_owned());
            rest = &after[j..];
        }
    }
    out
}

/// GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

fn anchors(page: &str) -> BTreeSet<String> {
    let (prose, _) = split_fences(page);
    prose
        .lines()
        .filter_map(|l| l.strip_prefix('#'))
        .map(|l| slug(l.trim_start_matches('#').replace('`', "").as_str()))
        .collect()
}

#[test]
fn every_relative_link_of_the_readme_and_the_book_resolves() {
    let mut broken = Vec::new();
    let mut checked = 0;
    for page in pages() {
        let text = read(&page);
        let (prose, _) = split_fences(&text);
        for link in links(&prose) {
            if link.contains("://") || link.starts_with("mailto:") {
                continue;
            }
            checked += 1;
            let (path, anchor) = match link.split_once('#') {
                Some((p, a)) => (p, Some(a)),
                None => (link.as_str(), None),
            };
            let target = if path.is_empty() {
                page.clone()
            } else {
                page.parent().unwrap_or(root()).join(path)
            };
            if !target.exists() {
                broken.push(format!("{}: ({link}) does not exist", shown(&page)));
                continue;
            }
            if let Some(a) = anchor {
                if target.is_file() && !anchors(&read(&target)).contains(a) {
                    broken.push(format!(
                        "{}: ({link}) has no heading #{a} in {}",
                        shown(&page),
                        shown(&target)
                    ));
                }
            }
        }
    }
    assert!(
        checked > 30,
        "only {checked} links found: is the scan broken?"
    );
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

/// The `usal` subcommand a snippet line runs, if it runs `usal`: the word after `--` in
/// `cargo run ... --bin usal -- SUB`, else the word after `usal` or `path/usal`.
fn usal_subcommand(line: &str) -> Option<String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    let at = if line.contains("--bin usal") {
        words.iter().position(|w| *w == "--")?
    } else {
        words
            .iter()
            .position(|w| *w == "usal" || w.ends_with("/usal"))?
    };
    words
        .get(at + 1)
        .filter(|w| !w.starts_with('-'))
        .map(|w| w.to_string())
}

#[test]
fn every_usal_command_and_repository_path_of_a_snippet_exists() {
    let mut wrong = Vec::new();
    let mut subcommands = BTreeSet::new();
    for page in pages() {
        let (_, blocks) = split_fences(&read(&page));
        for (info, body) in blocks {
            if !matches!(info.as_str(), "sh" | "bash" | "console") {
                continue;
            }
            for line in body.lines() {
                if let Some(sub) = usal_subcommand(line) {
                    subcommands.insert((sub, shown(&page)));
                }
                for word in line.split_whitespace() {
                    let w = word.trim_matches(|c| "'\"`,;()".contains(c));
                    let repo_path = ["config/", "docs/", "tests/python/"]
                        .iter()
                        .any(|p| w.starts_with(p));
                    if repo_path && !w.contains('*') && !root().join(w).exists() {
                        wrong.push(format!("{}: `{w}` does not exist", shown(&page)));
                    }
                }
            }
        }
    }
    assert!(
        subcommands.iter().any(|(s, _)| s == "run"),
        "no `usal run` snippet found: is the scan broken? {subcommands:?}"
    );
    for (sub, page) in &subcommands {
        let ok = Command::new(USAL)
            .args([sub.as_str(), "--help"])
            .output()
            .is_ok_and(|o| o.status.success());
        if !ok {
            wrong.push(format!("{page}: `usal {sub}` is no subcommand of usal"));
        }
    }
    assert!(wrong.is_empty(), "snippets:\n{}", wrong.join("\n"));
}

#[test]
fn the_readme_is_a_guide_of_at_most_300_lines() {
    let lines = read(&root().join("README.md")).lines().count();
    assert!(
        lines <= 300,
        "README.md has {lines} lines: move detail to docs/"
    );
}

/// What each workspace crate uses among the workspace's crates (normal dependencies).
fn workspace_uses() -> BTreeMap<String, BTreeSet<String>> {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--no-deps",
            "--format-version",
            "1",
            "--offline",
        ])
        .current_dir(root())
        .output()
        .expect("running cargo metadata");
    assert!(out.status.success(), "cargo metadata failed");
    let m: serde_json::Value = serde_json::from_slice(&out.stdout).expect("cargo metadata JSON");
    let packages = m["packages"].as_array().expect("packages");
    let names: BTreeSet<String> = packages
        .iter()
        .filter_map(|p| p["name"].as_str().map(str::to_owned))
        .collect();
    packages
        .iter()
        .map(|p| {
            let uses = p["dependencies"]
                .as_array()
                .into_iter()
                .flatten()
                .filter(|d| d["kind"].is_null())
                .filter_map(|d| d["name"].as_str())
                .filter(|n| names.contains(*n))
                .map(str::to_owned)
                .collect();
            (p["name"].as_str().unwrap_or_default().to_owned(), uses)
        })
        .collect()
}

#[test]
fn the_architecture_page_says_what_each_crate_uses() {
    let page = read(&root().join("docs/architecture.md"));
    let mut documented = BTreeMap::new();
    for line in page.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        // | `crate` | `path` | uses | what |
        if cells.len() < 6 || !cells[1].starts_with('`') {
            continue;
        }
        let name = cells[1].trim_matches('`').to_owned();
        let uses: BTreeSet<String> = cells[3]
            .split(',')
            .map(|u| u.trim().trim_matches('`').to_owned())
            .filter(|u| !u.is_empty() && u != "—")
            .collect();
        documented.insert(name, uses);
    }
    assert_eq!(
        documented,
        workspace_uses(),
        "docs/architecture.md's table of crates (left) differs from cargo metadata (right)"
    );
}

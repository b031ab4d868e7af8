//! Keeps a crate's layering true: a top-level module names (with `crate::` paths, in `use`
//! lines or in code, or with `super::` chains climbing to the crate root) only modules of its
//! own layer or of a layer below. Each crate states its table (`lib.rs`) and keeps it with a
//! test calling [`Layers::check_crate`]. Unit-test modules (`#[cfg(test)] mod ... { }`) are
//! exempt: a test may drive its module through the layers above it.

use std::path::{Path, PathBuf};

/// A crate's layer table: rows bottom to top; a module may use the modules of its own row and
/// of the rows before it.
pub struct Layers<'a> {
    /// The rows, bottom to top.
    pub rows: &'a [&'a [&'a str]],
    /// Where the table is kept, for the messages (e.g. "LAYERS in tests/layering.rs, the
    /// table in src/lib.rs").
    pub table: &'a str,
}

/// Pseudo-module for items of the crate root itself (`crate::Node`, the re-exports of
/// `lib.rs`): above every layer, as `lib.rs` re-exports from the top.
const ROOT: &str = "the crate root";

impl Layers<'_> {
    fn layer_of(&self, module: &str) -> Option<usize> {
        if module == ROOT {
            return Some(self.rows.len());
        }
        self.rows.iter().position(|row| row.contains(&module))
    }

    fn unknown(&self, module: &str) -> String {
        format!(
            "module `{module}` is not in the layer table: add it to {}, in the row of the \
             layer it belongs to",
            self.table
        )
    }
}

/// The source text with comments blanked out and string and char literals emptied; newlines
/// stay, so line numbers are unchanged.
fn code_only(source: &str) -> String {
    let c: Vec<char> = source.chars().collect();
    let mut out = String::with_capacity(source.len());
    let mut i = 0;
    // Keeps the newlines of a skipped range.
    let blank = |out: &mut String, from: &[char]| {
        out.extend(from.iter().filter(|&&ch| ch == '\n'));
    };
    while i < c.len() {
        let rest = &c[i..];
        if rest.starts_with(&['/', '/']) {
            let end = rest.iter().position(|&ch| ch == '\n').unwrap_or(rest.len());
            i += end;
        } else if rest.starts_with(&['/', '*']) {
            let (mut depth, mut j) = (0usize, 0);
            while j < rest.len() {
                if rest[j..].starts_with(&['/', '*']) {
                    depth += 1;
                    j += 2;
                } else if rest[j..].starts_with(&['*', '/']) {
                    depth -= 1;
                    j += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    j += 1;
                }
            }
            blank(&mut out, &rest[..j]);
            i += j;
        } else if rest[0] == 'r' && matches!(rest.get(1), Some('"' | '#')) && raw_prefix(&c, i) {
            // Raw string: r"..." or r#"..."#.
            let hashes = rest[1..].iter().take_while(|&&ch| ch == '#').count();
            if rest.get(1 + hashes) != Some(&'"') {
                out.push(rest[0]);
                i += 1;
                continue;
            }
            let close: Vec<char> = std::iter::once('"')
                .chain(std::iter::repeat_n('#', hashes))
                .collect();
            let body = 2 + hashes;
            let end = (body..rest.len())
                .find(|&j| rest[j..].starts_with(&close))
                .map_or(rest.len(), |j| j + close.len());
            out.push_str("\"\"");
            blank(&mut out, &rest[..end]);
            i += end;
        } else if rest[0] == '"' {
            let mut j = 1;
            while j < rest.len() && rest[j] != '"' {
                j += if rest[j] == '\\' { 2 } else { 1 };
            }
            out.push_str("\"\"");
            blank(&mut out, &rest[..j.min(rest.len())]);
            i += j + 1;
        } else if rest[0] == '\'' {
            // A char literal ('x', '\n', '\u{..}'), else a lifetime or a label.
            let len = if rest.get(1) == Some(&'\\') {
                // The escaped char may itself be a quote: '\''.
                rest.iter()
                    .skip(3)
                    .position(|&ch| ch == '\'')
                    .map(|p| p + 4)
            } else if rest.get(2) == Some(&'\'') {
                Some(3)
            } else {
                None
            };
            match len {
                Some(len) => {
                    out.push_str("' '");
                    i += len;
                }
                None => {
                    out.push('\'');
                    i += 1;
                }
            }
        } else {
            out.push(rest[0]);
            i += 1;
        }
    }
    out
}

fn is_ident(ch: char) -> bool {
    ch.is_alphanumeric() || ch == '_'
}

/// Whether the `r` at `c[i]` can open a raw string: it starts a word, or follows the `b` of a
/// raw byte string.
fn raw_prefix(c: &[char], i: usize) -> bool {
    !ident_before(c, i) || (c[i - 1] == 'b' && !ident_before(c, i - 1))
}

/// Whether an identifier (or `$`, as in `$crate`) ends right before `c[i]`.
fn ident_before(c: &[char], i: usize) -> bool {
    i > 0 && (is_ident(c[i - 1]) || c[i - 1] == '$')
}

/// One path of a file that leaves its own top-level module's reach: the crate-root name it
/// starts with (a module, or an item of the root) and its line.
#[derive(Debug, PartialEq)]
struct Reference {
    line: usize,
    target: String,
}

/// Every path in `source` (the text of a file `depth` modules below the crate root: 1 for
/// `src/node.rs` or `src/node/mod.rs`, 2 for `src/node/files.rs`) that starts at the crate root:
/// `crate::x`, each branch of `crate::{x::A, y}` (over several lines too), and `super::`
/// chains that climb to the root. Comments and literals are ignored.
fn references(source: &str, depth: usize) -> Vec<Reference> {
    let code: Vec<char> = code_only(source).chars().collect();
    let line_at = |i: usize| 1 + code[..i].iter().filter(|&&ch| ch == '\n').count();
    let mut found = Vec::new();
    // Brace depths at which inline `mod x {` blocks were opened, innermost last.
    let mut inline_mods: Vec<usize> = Vec::new();
    // The brace depth at which a `#[cfg(test)]` module was opened: nothing inside is read.
    let mut test_mod: Option<usize> = None;
    let mut braces = 0usize;
    let mut i = 0;
    while i < code.len() {
        let ch = code[i];
        if ch == '{' {
            braces += 1;
        } else if ch == '}' {
            braces = braces.saturating_sub(1);
            if inline_mods.last() == Some(&braces) {
                inline_mods.pop();
            }
            if test_mod == Some(braces) {
                test_mod = None;
            }
        }
        if ident_before(&code, i) || !is_ident(ch) {
            i += 1;
            continue;
        }
        let word = read_ident(&code, i);
        let after = i + word.len();
        if word == "mod" {
            let name_at = skip_space(&code, after);
            let name = read_ident(&code, name_at);
            let open = skip_space(&code, name_at + name.len());
            if !name.is_empty() && code.get(open) == Some(&'{') {
                inline_mods.push(braces);
                if test_mod.is_none() && under_cfg_test(&code, i) {
                    test_mod = Some(braces);
                }
            }
        }
        if test_mod.is_some() {
            i = after;
            continue;
        }
        let root_at = match word.as_str() {
            "crate" => path_sep(&code, after),
            "super" => {
                // Count the chain: `super::super::x`.
                let mut climbs = 1;
                let mut at = after;
                while let Some(next) = path_sep(&code, at) {
                    if read_ident(&code, next) != "super" {
                        break;
                    }
                    climbs += 1;
                    at = next + "super".len();
                }
                let here = depth + inline_mods.len();
                if climbs >= here {
                    path_sep(&code, at)
                } else {
                    None
                }
            }
            _ => None,
        };
        if let Some(at) = root_at {
            first_segments(&code, at, &mut |pos, target| {
                found.push(Reference {
                    line: line_at(pos),
                    target,
                })
            });
        }
        i = after;
    }
    found
}

/// Whether the `mod` at `code[at]` carries `#[cfg(test)]` (with a visibility between them or
/// not).
fn under_cfg_test(code: &[char], at: usize) -> bool {
    let before: String = code[..at].iter().collect();
    let before = before.trim_end();
    let before = ["pub(crate)", "pub(super)", "pub"]
        .iter()
        .find_map(|v| before.strip_suffix(v))
        .unwrap_or(before)
        .trim_end();
    before.ends_with("#[cfg(test)]")
}

fn read_ident(code: &[char], at: usize) -> String {
    code[at.min(code.len())..]
        .iter()
        .take_while(|&&ch| is_ident(ch))
        .collect()
}

fn skip_space(code: &[char], mut at: usize) -> usize {
    while code.get(at).is_some_and(|ch| ch.is_whitespace()) {
        at += 1;
    }
    at
}

/// Where the path goes on after `::` at `at` (spaces allowed around it), if it does.
fn path_sep(code: &[char], at: usize) -> Option<usize> {
    let at = skip_space(code, at);
    (code.get(at) == Some(&':') && code.get(at + 1) == Some(&':')).then(|| skip_space(code, at + 2))
}

/// Calls `found` with the first segment of each path starting at `at`: one name, or every
/// branch of a `{..}` group (a `self` branch names nothing new).
fn first_segments(code: &[char], at: usize, found: &mut impl FnMut(usize, String)) {
    if code.get(at) != Some(&'{') {
        let name = read_ident(code, at);
        if !name.is_empty() && name != "self" {
            found(at, name);
        }
        return;
    }
    let mut depth = 0usize;
    let mut expect_branch = true;
    let mut i = at;
    while i < code.len() {
        match code[i] {
            '{' => {
                depth += 1;
                expect_branch = depth == 1;
            }
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return;
                }
            }
            ',' if depth == 1 => expect_branch = true,
            ch if expect_branch && is_ident(ch) => {
                let name = read_ident(code, i);
                if name != "self" {
                    found(i, name.clone());
                }
                expect_branch = false;
                i += name.len();
                continue;
            }
            _ => {}
        }
        i += 1;
    }
}

/// The top-level modules `lib.rs` declares (`mod x;`, with any visibility).
fn declared_modules(lib_rs: &str) -> Vec<String> {
    code_only(lib_rs)
        .lines()
        .filter_map(|l| {
            let words: Vec<&str> = l.split_whitespace().collect();
            let at = words.iter().position(|w| *w == "mod")?;
            words.get(at + 1)?.strip_suffix(';').map(str::to_owned)
        })
        .collect()
}

/// The top-level module of a file under `src/` and its depth below the crate root; `None` for
/// `lib.rs` itself.
fn module_of(relative: &Path) -> Option<(String, usize)> {
    let parts: Vec<String> = relative
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let (last, dirs) = parts.split_last()?;
    if dirs.is_empty() && last == "lib.rs" {
        return None;
    }
    let stem = last.strip_suffix(".rs")?;
    let depth = dirs.len() + usize::from(stem != "mod");
    let top = dirs.first().map_or(stem, String::as_str).to_owned();
    Some((top, depth))
}

impl Layers<'_> {
    /// Every breach of the layering in the crate whose `lib.rs` is `lib_rs` and whose other
    /// files are `files` (paths relative to `src/`), one readable line each.
    pub fn violations(&self, lib_rs: &str, files: &[(PathBuf, String)]) -> Vec<String> {
        let rule = format!(
            "a module may use only modules of its own layer or below ({})",
            self.table
        );
        let declared = declared_modules(lib_rs);
        let mut out: Vec<String> = declared
            .iter()
            .filter(|m| self.layer_of(m).is_none())
            .map(|m| format!("src/lib.rs: {}", self.unknown(m)))
            .collect();
        for (path, source) in files {
            let Some((from, depth)) = module_of(path) else {
                continue;
            };
            let shown = format!("src/{}", path.display());
            for r in references(source, depth) {
                let target = if declared.contains(&r.target) {
                    r.target.clone()
                } else {
                    ROOT.to_owned()
                };
                if target == from {
                    continue;
                }
                let at = format!("{shown}:{}: `{from}` -> `{target}`", r.line);
                match (self.layer_of(&from), self.layer_of(&target)) {
                    (None, _) => out.push(format!("{at}: `{from}` is not in the layer table")),
                    (_, None) => out.push(format!("{at}: `{target}` is not in the layer table")),
                    (Some(a), Some(b)) if b > a => {
                        out.push(format!("{at}: uses a higher layer; {rule}"))
                    }
                    _ => {}
                }
            }
        }
        out
    }

    /// Every breach of the layering in the crate whose sources are under `src` (its `lib.rs`
    /// and every other `.rs` file below).
    ///
    /// # Panics
    /// When `src` cannot be read (a test's setup fault).
    pub fn check_crate(&self, src: &Path) -> Vec<String> {
        let read = |p: &Path| {
            std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        };
        let mut paths = Vec::new();
        rust_files(src, &mut paths);
        paths.sort();
        let files: Vec<(PathBuf, String)> = paths
            .iter()
            .map(|p| {
                let relative = p.strip_prefix(src).expect("found under src/").to_path_buf();
                (relative, read(p))
            })
            .collect();
        assert!(files.len() > 5, "walked {} files only", files.len());
        self.violations(&read(&src.join("lib.rs")), &files)
    }
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let entries = std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    for entry in entries {
        let path = entry
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[cfg(test)]
mod tests {
    //! The checker itself, on inline sources with known breaches.
    use super::*;

    const LAYERS: Layers<'static> = Layers {
        rows: &[&["sync", "name"], &["node"], &["api"]],
        table: "LAYERS in tests/layering.rs",
    };

    fn violations(lib: &str, files: &[(PathBuf, String)]) -> Vec<String> {
        LAYERS.violations(lib, files)
    }

    const LIB: &str =
        "pub mod api;\npub(crate) mod node;\n#[cfg(unix)] mod sync;\npub use api::*;\n";

    fn check(path: &str, source: &str) -> Vec<String> {
        violations(LIB, &[(PathBuf::from(path), source.to_owned())])
    }

    /// Asserts that `found` holds one report per entry of `expected`, in order, each containing it.
    fn assert_reports(found: &[String], expected: &[&str]) {
        assert_eq!(found.len(), expected.len(), "{found:?}");
        for (report, wanted) in found.iter().zip(expected) {
            assert!(report.contains(wanted), "{report}\ndoes not say: {wanted}");
        }
    }

    /// The crate-root paths of `source` as (line, first segment).
    fn roots(source: &str, depth: usize) -> Vec<(usize, String)> {
        references(source, depth)
            .into_iter()
            .map(|r| (r.line, r.target))
            .collect()
    }

    #[test]
    fn an_upward_use_is_reported_with_file_line_and_modules() {
        let found = check(
            "node/gateway.rs",
            "use std::sync::Arc;\nuse crate::api::CallError;\n",
        );
        assert_reports(
            &found,
            &["src/node/gateway.rs:2: `node` -> `api`: uses a higher layer"],
        );
    }

    #[test]
    fn a_grouped_use_over_several_lines_is_read_branch_by_branch() {
        let source = "use crate::{\n    sync::lock,\n    api::{Node, CallError},\n};\n";
        assert_eq!(roots(source, 2), [(2, "sync".into()), (3, "api".into())]);
        assert_reports(
            &check("node/mod.rs", source),
            &["src/node/mod.rs:3: `node` -> `api`"],
        );
    }

    #[test]
    fn a_path_in_code_and_a_root_reexport_are_reported() {
        let source = "fn f() {\n    let p = crate::api::function::Provider::Local;\n}\n\
                      fn g(n: &crate::Node) {}\n";
        assert_reports(
            &check("sync.rs", source),
            &[
                "src/sync.rs:2: `sync` -> `api`",
                "src/sync.rs:4: `sync` -> `the crate root`",
            ],
        );
    }

    #[test]
    fn super_chains_that_climb_to_the_root_are_followed() {
        assert_eq!(roots("use super::super::api::X;\n", 2), [(1, "api".into())]);
        // Within the module: neither `super::x` in a sub-module nor a test module's `super::*`.
        assert!(references("use super::files::X;\n", 2).is_empty());
        assert!(references("#[cfg(test)]\nmod tests {\n    use super::*;\n}\n", 1).is_empty());
        assert_eq!(
            roots("mod tests {\n    use super::*;\n}\nuse super::api;\n", 1),
            [(4, "api".into())]
        );
    }

    #[test]
    fn comments_strings_and_macro_crate_paths_are_not_uses() {
        let source = "//! See [`crate::api`].\n/// [crate::api::Node]\nfn f() {\n    \
                      let s = \"crate::api\"; // crate::api\n    let r = r#\"crate::api\"#;\n    \
                      let c = '\"'; /* crate::api */\n    let l: &'static str = s;\n}\n\
                      macro_rules! m { () => { $crate::api::Node }; }\n";
        assert_eq!(references(source, 1), []);
        // What follows a char literal holding a quote is still read.
        for quote in ["'\"'", "'\\''"] {
            assert_eq!(
                roots(&format!("let c = {quote}; use crate::api;\n"), 1),
                [(1, "api".into())],
                "after {quote}"
            );
        }
    }

    #[test]
    fn own_and_lower_layers_pass() {
        assert!(check(
            "api/node.rs",
            "use crate::node::X;\nuse crate::{sync, api::Y};\n"
        )
        .is_empty());
        assert!(check("node/mod.rs", "pub(crate) use crate::sync::lock;\n").is_empty());
    }

    #[test]
    fn a_module_missing_from_the_table_fails_with_what_to_do() {
        let lib = "pub mod sync;\npub mod scratch;\n";
        let found = violations(
            lib,
            &[(
                PathBuf::from("scratch/mod.rs"),
                "use crate::sync::lock;\n".into(),
            )],
        );
        assert_reports(
            &found,
            &[
                "src/lib.rs: module `scratch` is not in the layer table: add it to LAYERS",
                "src/scratch/mod.rs:1: `scratch` -> `sync`",
            ],
        );
        assert_eq!(declared_modules(LIB), ["api", "node", "sync"]);
    }

    #[test]
    fn a_unit_test_module_may_reach_up_and_the_code_after_it_may_not() {
        let source = "use crate::sync::lock;\n#[cfg(test)]\nmod tests {\n    \
                      use crate::api::Node;\n    mod inner { use crate::api::X; }\n}\n\
                      use crate::api::Late;\n";
        assert_reports(
            &check("node/mod.rs", source),
            &["src/node/mod.rs:7: `node` -> `api`"],
        );
        let plain = "mod helpers {\n    use crate::api::Node;\n}\n";
        assert_reports(
            &check("node/mod.rs", plain),
            &["src/node/mod.rs:2: `node` -> `api`"],
        );
    }
}

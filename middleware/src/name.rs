//! Hierarchical names (`namespace/service/item`) and subscription patterns with wildcards.
//!
//! A name is a `/`-separated list of non-empty segments made of letters, digits, `_`, `-` and
//! `.`. A pattern may also hold `*` (exactly one segment) and `**` (zero or more segments), so a
//! ground station can follow a fleet with `*/vas/position` or everything of one vehicle with
//! `rover1/**`.

/// Why a name or pattern was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameParseError {
    /// The string was empty.
    #[error("name is empty")]
    Empty,
    /// A segment between two `/` was empty (`a//b`, leading or trailing `/`).
    #[error("name {0:?} has an empty segment")]
    EmptySegment(String),
    /// A segment held a character outside `[A-Za-z0-9_.-]`.
    #[error("name {name:?} has an invalid character {ch:?} (allowed: letters, digits, _ - .)")]
    InvalidChar {
        /// The whole name.
        name: String,
        /// The first offending character.
        ch: char,
    },
    /// Longer than [`MAX_NAME_LEN`] bytes.
    #[error("name of {0} bytes is longer than {MAX_NAME_LEN}")]
    TooLong(usize),
    /// A wildcard was used where only a plain name is allowed (publications, functions).
    #[error("name {0:?} contains a wildcard; only subscriptions may use * and **")]
    WildcardNotAllowed(String),
    /// More than [`MAX_SEGMENTS`] segments.
    #[error("name of {0} segments has more than {MAX_SEGMENTS}")]
    TooManySegments(usize),
    /// Two `**` in a row (`a/**/**/b`): they match exactly what one does, and a pattern of
    /// thousands of them is only ever an attempt to make matching slow.
    #[error("pattern {0:?} repeats ** (one ** already matches any number of segments)")]
    RepeatedDoubleWildcard(String),
}

/// The longest name or pattern accepted, in bytes: far above any real one, and a bound on what
/// a peer's declaration can make the node store and match against.
pub const MAX_NAME_LEN: usize = 1024;

/// The most segments a name or pattern may have: real names have three or four, and a bound
/// on segments bounds the work of matching a peer's pattern (segments × segments at worst).
pub const MAX_SEGMENTS: usize = 64;

fn check(name: &str, allow_wildcards: bool) -> Result<(), NameParseError> {
    if name.is_empty() {
        return Err(NameParseError::Empty);
    }
    if name.len() > MAX_NAME_LEN {
        return Err(NameParseError::TooLong(name.len()));
    }
    let segments = name.split('/').count();
    if segments > MAX_SEGMENTS {
        return Err(NameParseError::TooManySegments(segments));
    }
    let mut previous = "";
    for seg in name.split('/') {
        if seg.is_empty() {
            return Err(NameParseError::EmptySegment(name.to_owned()));
        }
        if seg == "*" || seg == "**" {
            if !allow_wildcards {
                return Err(NameParseError::WildcardNotAllowed(name.to_owned()));
            }
            if seg == "**" && previous == "**" {
                return Err(NameParseError::RepeatedDoubleWildcard(name.to_owned()));
            }
            previous = seg;
            continue;
        }
        previous = seg;
        if let Some(ch) = seg
            .chars()
            .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.')))
        {
            if ch == '*' && !allow_wildcards {
                return Err(NameParseError::WildcardNotAllowed(name.to_owned()));
            }
            return Err(NameParseError::InvalidChar {
                name: name.to_owned(),
                ch,
            });
        }
    }
    Ok(())
}

/// Checks a concrete name (no wildcards).
///
/// # Errors
/// [`NameParseError`] naming what is wrong.
pub fn validate_name(name: &str) -> Result<(), NameParseError> {
    check(name, false)
}

/// Checks a subscription pattern (wildcards allowed).
///
/// # Errors
/// [`NameParseError`] naming what is wrong.
pub fn validate_pattern(pattern: &str) -> Result<(), NameParseError> {
    check(pattern, true)
}

/// Joins a namespace (possibly empty), a service and an item into a full name.
pub fn join(namespace: Option<&str>, service: &str, item: &str) -> String {
    match namespace {
        Some(ns) if !ns.is_empty() => format!("{ns}/{service}/{item}"),
        _ => format!("{service}/{item}"),
    }
}

/// Whether `pattern` has a wildcard segment (`*` or `**`).
pub fn is_wildcard(pattern: &str) -> bool {
    pattern.split('/').any(|seg| seg == "*" || seg == "**")
}

/// Whether `pattern` (with `*` and `**`) matches the concrete `name`.
///
/// Linear in the common case and never worse than (pattern segments × name segments): a `**`
/// is tried against growing runs of the name only from the last `**` met, never by recursion
/// over every `**` (a peer's pattern of two thousand `**` once pinned a core for 37 s).
pub fn matches(pattern: &str, name: &str) -> bool {
    let p: Vec<&str> = pattern.split('/').collect();
    let n: Vec<&str> = name.split('/').collect();
    let (mut pi, mut ni) = (0, 0);
    // After the last `**` met: where the pattern resumes, and the name segment from which
    // that `**` stops swallowing.
    let mut resume: Option<(usize, usize)> = None;
    while ni < n.len() {
        match p.get(pi) {
            Some(&"**") => {
                pi += 1;
                resume = Some((pi, ni));
            }
            Some(&seg) if seg == "*" || seg == n[ni] => {
                pi += 1;
                ni += 1;
            }
            _ => match resume {
                // The last `**` swallows one more segment and the rest is tried again. An
                // earlier `**` never needs to: whatever it could swallow, the later one can.
                Some((rp, rn)) => {
                    resume = Some((rp, rn + 1));
                    pi = rp;
                    ni = rn + 1;
                }
                None => return false,
            },
        }
    }
    p[pi..].iter().all(|seg| *seg == "**")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wildcards_match_as_documented() {
        assert!(matches("*/vas/position", "rover1/vas/position"));
        assert!(!matches("*/vas/position", "vas/position"));
        assert!(matches("**/vas/position", "vas/position"));
        assert!(matches("**/vas/position", "fleet/rover1/vas/position"));
        assert!(matches("rover1/**", "rover1/vas/position"));
        assert!(matches("rover1/**", "rover1"));
        assert!(!matches("rover1/**", "rover2/vas/position"));
        assert!(matches("a/b", "a/b"));
        assert!(!matches("a/b", "a/b/c"));
        assert!(!matches("a/*", "a/b/c"));
    }

    /// The matcher as it was written first: obviously right, exponential in the `**` count.
    fn reference(p: &[&str], n: &[&str]) -> bool {
        match p.first() {
            None => n.is_empty(),
            Some(&"**") => (0..=n.len()).any(|skip| reference(&p[1..], &n[skip..])),
            Some(&seg) => match n.first() {
                Some(&first) if seg == "*" || seg == first => reference(&p[1..], &n[1..]),
                _ => false,
            },
        }
    }

    proptest::proptest! {
        #[test]
        fn agrees_with_the_reference_matcher(
            p in proptest::collection::vec(proptest::sample::select(vec!["**", "*", "a", "b"]), 1..8),
            n in proptest::collection::vec(proptest::sample::select(vec!["a", "b", "c"]), 1..8),
        ) {
            let (pattern, name) = (p.join("/"), n.join("/"));
            proptest::prop_assert_eq!(matches(&pattern, &name), reference(&p, &n), "{} ~ {}", pattern, name);
        }
    }

    #[test]
    fn a_pattern_of_thousands_of_double_wildcards_is_answered() {
        // The attacker's declaration: 2,000 `**` then a segment the name does not end with.
        // The recursive matcher would never finish; the bound only keeps a regression from
        // hanging the suite.
        let pattern = format!("{}zz", "**/".repeat(2000));
        let name = vec!["a"; 200].join("/");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send((
                matches(&pattern, &name),
                matches(&pattern, &format!("{name}/zz")),
            ));
        });
        let answers = rx
            .recv_timeout(std::time::Duration::from_secs(30))
            .expect("matching finished");
        assert_eq!(answers, (false, true));
    }

    #[test]
    fn patterns_are_bounded_in_segments_bytes_and_double_wildcards() {
        let at_cap = vec!["a"; MAX_SEGMENTS].join("/");
        assert!(validate_name(&at_cap).is_ok());
        assert!(validate_pattern(&at_cap).is_ok());
        let over = vec!["a"; MAX_SEGMENTS + 1].join("/");
        assert_eq!(
            validate_pattern(&over),
            Err(NameParseError::TooManySegments(MAX_SEGMENTS + 1))
        );
        assert_eq!(
            validate_name(&over),
            Err(NameParseError::TooManySegments(MAX_SEGMENTS + 1))
        );
        // Few segments but too many bytes.
        let long = format!("{}/b", "a".repeat(MAX_NAME_LEN));
        assert_eq!(
            validate_pattern(&long),
            Err(NameParseError::TooLong(MAX_NAME_LEN + 2))
        );
        // `**` twice in a row, anywhere, is refused, and said so.
        for p in ["**/**", "a/**/**/b", "**/**/**/zz", "a/**/**"] {
            assert_eq!(
                validate_pattern(p),
                Err(NameParseError::RepeatedDoubleWildcard(p.to_owned())),
                "{p}"
            );
        }
        let err = validate_pattern("a/**/**/b").unwrap_err().to_string();
        assert!(err.contains("repeats **"), "{err}");
        // The attacker's shape within the byte bound: refused for its segments.
        let many = format!("{}zz", "*/".repeat(100));
        assert_eq!(
            validate_pattern(&many),
            Err(NameParseError::TooManySegments(101))
        );
    }

    #[test]
    fn names_are_validated() {
        assert_eq!(validate_name(""), Err(NameParseError::Empty));
        assert!(matches!(
            validate_name("a//b"),
            Err(NameParseError::EmptySegment(_))
        ));
        assert!(matches!(
            validate_name("a/*"),
            Err(NameParseError::WildcardNotAllowed(_))
        ));
        assert!(matches!(
            validate_name("a/b c"),
            Err(NameParseError::InvalidChar { ch: ' ', .. })
        ));
        assert!(validate_pattern("*/vas/**").is_ok());
        assert!(validate_pattern("**/vas/**").is_ok());
        assert!(validate_pattern("**/*/**").is_ok());
        assert!(validate_name("rover-1/vas/position_2.x").is_ok());
        assert_eq!(
            join(Some("rover1"), "vas", "position"),
            "rover1/vas/position"
        );
        assert_eq!(join(None, "vas", "position"), "vas/position");
    }
}

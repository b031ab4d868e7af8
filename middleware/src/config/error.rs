//! Why a `network.xml` could not be loaded, and where: [`ConfigLoadError`] and [`Location`].

use std::fmt;
use std::path::{Path, PathBuf};

/// A place in a `network.xml`: 1-based line and column (in characters).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// The file, or `None` for text given to [`NetworkConfig::parse`](super::NetworkConfig::parse) without a source.
    // Boxed rather than a `PathBuf` to keep `ConfigLoadError` small (clippy::result_large_err).
    pub file: Option<Box<Path>>,
    /// Line number, from 1.
    pub line: usize,
    /// Column number in characters, from 1.
    pub column: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.file {
            Some(file) => write!(f, "{}:{}:{}", file.display(), self.line, self.column),
            None => write!(f, "<input>:{}:{}", self.line, self.column),
        }
    }
}

/// Why a `network.xml` could not be loaded. Displays as `file:line:column: message`
/// (`<input>:line:column: ...` for text without a source).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigLoadError {
    /// The file could not be read (missing, no permission, a directory...).
    #[error("{}: cannot read network config: {source}", path.display())]
    Unreadable {
        /// The path that was read.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file is not UTF-8; `at` is the first invalid byte.
    #[error("{at}: not valid UTF-8: {source}")]
    NotUtf8 {
        /// Where.
        at: Location,
        /// The decoding error.
        #[source]
        source: std::str::Utf8Error,
    },
    /// The text is not well-formed XML (an unclosed tag, a bad attribute, an unknown entity...).
    #[error("{at}: malformed XML: {source}")]
    MalformedXml {
        /// Where.
        at: Location,
        /// quick-xml's description.
        #[source]
        source: quick_xml::Error,
    },
    /// The text holds no element at all.
    #[error("{at}: expected a <network> root element, found the end of the input")]
    NoRootElement {
        /// Where (the end of the input).
        at: Location,
    },
    /// The root element is not the document's (`<network>`, or `<access>` for an access file).
    #[error("{at}: expected the root element <{expected}>, found <{found}>")]
    WrongRoot {
        /// Where.
        at: Location,
        /// The root element the document must have.
        expected: &'static str,
        /// The root element's name.
        found: String,
    },
    /// An element that is not allowed where it appears.
    #[error("{at}: <{parent}>: unknown element <{found}>{}", element_hint(*.suggestion, expected))]
    UnknownElement {
        /// Where.
        at: Location,
        /// The enclosing element.
        parent: &'static str,
        /// The element found.
        found: String,
        /// A close allowed name, if any.
        suggestion: Option<&'static str>,
        /// The elements allowed there.
        expected: &'static [&'static str],
    },
    /// An attribute the element does not take.
    #[error("{at}: <{element}>: unknown attribute {found}{}", attribute_hint(*.suggestion, expected))]
    UnknownAttribute {
        /// Where.
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute found.
        found: String,
        /// A close allowed name, if any.
        suggestion: Option<&'static str>,
        /// The attributes the element takes.
        expected: &'static [&'static str],
    },
    /// The same attribute given twice on one element.
    #[error("{at}: <{element}>: attribute {attribute} given twice")]
    DuplicateAttribute {
        /// Where (the second occurrence).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
    },
    /// A required attribute is absent.
    #[error("{at}: <{element}>: missing required attribute {attribute} ({expected})")]
    MissingAttribute {
        /// Where (the element).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
        /// What it should hold.
        expected: &'static str,
    },
    /// An attribute value of the wrong form (not a number, address, boolean or name).
    #[error("{at}: <{element}>: attribute {attribute}: expected {expected}, found {found:?}")]
    BadValue {
        /// Where (the attribute).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
        /// What it should hold.
        expected: &'static str,
        /// The value found.
        found: String,
    },
    /// A number outside its allowed range.
    #[error(
        "{at}: <{element}>: attribute {attribute}: {found} is out of range, expected {min} to {max} {unit}"
    )]
    OutOfRange {
        /// Where (the attribute).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
        /// The value found.
        found: String,
        /// Smallest allowed value.
        min: u64,
        /// Largest allowed value.
        max: u64,
        /// Unit of the value.
        unit: &'static str,
    },
    /// `leaseMs` is not longer than the heartbeat period, so a live peer would be dropped.
    #[error(
        "{at}: <{element}>: attribute leaseMs: {lease_ms} must be greater than heartbeatMs ({heartbeat_ms})"
    )]
    LeaseNotAboveHeartbeat {
        /// Where (the `leaseMs` attribute).
        at: Location,
        /// The element.
        element: &'static str,
        /// The lease, in milliseconds.
        lease_ms: u64,
        /// The heartbeat period, in milliseconds.
        heartbeat_ms: u64,
    },
    /// Text (or CDATA, or an entity) where only elements and comments may appear.
    #[error("{at}: unexpected text {found:?} {}; only elements and comments are allowed", within(*.element))]
    UnexpectedText {
        /// Where.
        at: Location,
        /// The enclosing element, `None` outside the root.
        element: Option<&'static str>,
        /// The text found (shortened).
        found: String,
    },
    /// An element after the root element closed.
    #[error("{at}: unexpected <{found}> after the root element </network>")]
    TrailingContent {
        /// Where.
        at: Location,
        /// The element found.
        found: String,
    },
    /// `<network>` enables no link, so the node could talk to nobody.
    #[error(
        "{at}: <network>: no link; expected at least one enabled <ethernet>, <shm>, <serial> or <serialduo>"
    )]
    NoLinks {
        /// Where (the `<network>` element).
        at: Location,
    },
    /// Two links share a name (given or defaulted).
    #[error("{at}: duplicate link name {name:?} (first used at line {}, column {})", first.line, first.column)]
    DuplicateLinkName {
        /// Where (the second link's name, or the element when defaulted).
        at: Location,
        /// The name.
        name: String,
        /// Where the first link with this name is.
        first: Location,
    },
    /// An element that may appear once appears again (`<access>`).
    #[error("{at}: <{element}> may appear only once")]
    DuplicateElement {
        /// Where (the second one).
        at: Location,
        /// The element.
        element: &'static str,
    },
    /// A second `<security>` element.
    #[error("{at}: <network>: a second <security> element (the first is at line {}, column {})", first.line, first.column)]
    DuplicateSecurity {
        /// Where (the second element).
        at: Location,
        /// Where the first is.
        first: Location,
    },
    /// A `<serialduo>` whose `addressTx` and `addressRx` are the same port.
    #[error(
        "{at}: <serialduo>: addressTx and addressRx are both {address:?}; a serialduo needs two different ports (use <serial> for one)"
    )]
    SerialDuoSamePort {
        /// Where (the `addressRx` attribute).
        at: Location,
        /// The port.
        address: String,
    },
    /// A serial port already used by another enabled link.
    #[error("{at}: serial port {address:?} is already used by link {first_link:?} (line {}, column {})", first.line, first.column)]
    SerialPortReused {
        /// Where (the second use).
        at: Location,
        /// The port.
        address: String,
        /// The link that uses it first.
        first_link: String,
        /// Where the first use is.
        first: Location,
    },
}

impl ConfigLoadError {
    /// Where the error is, when it is inside the text.
    pub fn location(&self) -> Option<&Location> {
        use ConfigLoadError as E;
        match self {
            E::Unreadable { .. } => None,
            E::NotUtf8 { at, .. }
            | E::MalformedXml { at, .. }
            | E::NoRootElement { at }
            | E::WrongRoot { at, .. }
            | E::UnknownElement { at, .. }
            | E::UnknownAttribute { at, .. }
            | E::DuplicateAttribute { at, .. }
            | E::MissingAttribute { at, .. }
            | E::BadValue { at, .. }
            | E::OutOfRange { at, .. }
            | E::LeaseNotAboveHeartbeat { at, .. }
            | E::UnexpectedText { at, .. }
            | E::TrailingContent { at, .. }
            | E::NoLinks { at }
            | E::DuplicateLinkName { at, .. }
            | E::DuplicateElement { at, .. }
            | E::SerialDuoSamePort { at, .. }
            | E::SerialPortReused { at, .. }
            | E::DuplicateSecurity { at, .. } => Some(at),
        }
    }

    /// The 1-based line of the error, when it is inside the text.
    pub fn line(&self) -> Option<usize> {
        self.location().map(|at| at.line)
    }

    /// The 1-based column (in characters) of the error, when it is inside the text.
    pub fn column(&self) -> Option<usize> {
        self.location().map(|at| at.column)
    }
}

fn element_hint(suggestion: Option<&str>, expected: &[&str]) -> String {
    match (suggestion, expected) {
        (Some(s), _) => format!(" (did you mean <{s}>?)"),
        (None, []) => "; no child elements are allowed here".to_owned(),
        (None, list) => {
            let names: Vec<String> = list.iter().map(|n| format!("<{n}>")).collect();
            format!("; expected {}", names.join(", "))
        }
    }
}

fn attribute_hint(suggestion: Option<&str>, expected: &[&str]) -> String {
    match suggestion {
        Some(s) => format!(" (did you mean {s}?)"),
        None => format!("; expected one of {}", expected.join(", ")),
    }
}

fn within(element: Option<&str>) -> String {
    match element {
        Some(e) => format!("inside <{e}>"),
        None => "outside the root element".to_owned(),
    }
}

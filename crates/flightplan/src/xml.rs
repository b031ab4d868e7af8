//! Flight plans read with [`marea::xml`] (positions of every element and attribute), its errors
//! worded for plan authors: the format has elements and attributes only.

pub use marea::xml::{Attr, Element, Pos};
use marea::xml::{TextKind, XmlReadError, XmlReadErrorKind};

/// A syntax error with its position.
#[derive(Debug, Clone, PartialEq)]
pub struct XmlError {
    /// Where.
    pub pos: Pos,
    /// What.
    pub message: String,
}

impl From<XmlReadError> for XmlError {
    fn from(e: XmlReadError) -> Self {
        // Attribute errors point at their element, as plan errors always have.
        let (element, element_pos) = e
            .element
            .map_or((String::new(), e.pos), |el| (el.name, el.pos));
        let (pos, message) = match e.kind {
            XmlReadErrorKind::Syntax(err) => (e.pos, format!("malformed XML: {err}")),
            XmlReadErrorKind::Attribute(err) => (
                element_pos,
                format!("malformed attribute in <{element}>: {err}"),
            ),
            XmlReadErrorKind::AttributeValue { name, source } => (
                element_pos,
                format!("bad value of attribute `{name}` in <{element}>: {source}"),
            ),
            XmlReadErrorKind::Unclosed(name) => (e.pos, format!("<{name}> is never closed")),
            XmlReadErrorKind::TooDeep => (e.pos, "elements nested too deeply".into()),
            XmlReadErrorKind::Text(t) if t.kind == TextKind::Chars => (
                e.pos,
                format!(
                    "unexpected text `{}`; the format has attributes only",
                    excerpt(t.content.trim())
                ),
            ),
            XmlReadErrorKind::Text(_) => (
                e.pos,
                "unexpected text; the format has attributes only".into(),
            ),
            XmlReadErrorKind::NoRoot => (e.pos, "the document has no root element".into()),
            XmlReadErrorKind::SecondRoot(_) => (
                e.pos,
                "a second root element; a plan has exactly one <flightPlan>".into(),
            ),
        };
        XmlError { pos, message }
    }
}

/// Parses a whole document and returns its root element.
///
/// # Errors
/// Malformed XML, text where only elements belong, several roots or none.
pub fn parse_document(src: &str) -> Result<Element, XmlError> {
    Ok(marea::xml::parse_document(src)?)
}

/// Parses a sequence of top-level elements (a fragment, e.g. legs to insert).
///
/// # Errors
/// As [`parse_document`].
pub fn parse_elements(src: &str) -> Result<Vec<Element>, XmlError> {
    Ok(marea::xml::parse_fragment(src)?)
}

/// The start of `text` as an error quotes it: its first line, at most 40 characters, `…` where
/// cut (a whole foreign file once came back inside its own error).
fn excerpt(text: &str) -> String {
    let line = text.lines().next().unwrap_or("");
    let mut out: String = line.chars().take(40).collect();
    if out.len() < text.len() {
        out.push('…');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn foreign_text_is_quoted_by_its_start_only() {
        let json = format!(
            "{{\n  \"fileType\": \"Plan\",\n{}}}",
            "  \"x\": 1,\n".repeat(500)
        );
        let err = parse_document(&json).unwrap_err();
        assert_eq!(
            err.message,
            "unexpected text `{…`; the format has attributes only"
        );
        let err = parse_document("<a>hello</a>").unwrap_err();
        assert_eq!(
            err.message,
            "unexpected text `hello`; the format has attributes only"
        );
    }

    #[test]
    fn errors_keep_the_plan_wording() {
        let err = parse_document("<a>\n<b>\n</c>\n</a>").unwrap_err();
        assert_eq!(err.pos.line, 3, "{err:?}");
        assert!(err.message.starts_with("malformed XML: "), "{err:?}");
        assert!(parse_document("<a><b/>").is_err());
        let err = parse_document("<a>\n hello</a>").unwrap_err();
        assert_eq!(err.pos, Pos { line: 2, col: 2 });
        assert_eq!(
            err.message,
            "unexpected text `hello`; the format has attributes only"
        );
        let err = parse_document("<a>\n  <b x=\"1\" x=\"2\"/></a>").unwrap_err();
        assert_eq!(err.pos, Pos { line: 2, col: 3 });
        assert!(
            err.message.starts_with("malformed attribute in <b>: "),
            "{err:?}"
        );
        let err = parse_document("<a/><a/>").unwrap_err();
        assert_eq!(
            (err.pos, err.message.as_str()),
            (
                Pos { line: 1, col: 5 },
                "a second root element; a plan has exactly one <flightPlan>"
            )
        );
    }
}

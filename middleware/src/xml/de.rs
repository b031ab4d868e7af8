//! Serde-described XML files read with positions: a configuration whose reader is a
//! `#[derive(Deserialize)]` (quick-xml's serde support) still names the line and column of the
//! attribute or element it refuses.
//!
//! The text is first read by [`parse_document`] (malformed XML is refused there, at its
//! position), then deserialized. When serde refuses it, the offending attribute or element is
//! found by deserializing the same document with parts of it left out (serde's messages carry
//! no position): an attribute whose removal makes its element acceptable, else one that is
//! refused on its own, else the innermost element whose subtree is refused.
//!
//! ```
//! #[derive(serde::Deserialize, Debug, Default)]
//! #[serde(default, deny_unknown_fields)]
//! struct Cfg {
//!     #[serde(rename = "@rate")]
//!     rate: u32,
//! }
//! let e = marea::xml::de::from_document::<Cfg>("<cfg\n  rate=\"fast\"/>").unwrap_err();
//! assert!(e.to_string().starts_with("2:3: rate:"), "{e}");
//! ```

use serde::de::DeserializeOwned;

use super::{parse_document, Element, Pos, XmlReadError};

/// Why a serde-described XML document was refused, and where.
#[derive(Debug, thiserror::Error)]
pub enum XmlDeError {
    /// Not well-formed XML, or text where the format has none.
    #[error(transparent)]
    Read(#[from] XmlReadError),
    /// Well-formed, but not what the format describes: an unknown attribute or element, a
    /// value of the wrong type, a missing field.
    #[error("{pos}: {what}{message}")]
    Refused {
        /// The attribute, else the element, serde refused.
        pos: Pos,
        /// `name: ` of the attribute, or empty where the element is meant.
        what: String,
        /// Serde's message.
        message: String,
    },
}

impl XmlDeError {
    /// Where the document was refused.
    pub fn pos(&self) -> Pos {
        match self {
            Self::Read(e) => e.pos,
            Self::Refused { pos, .. } => *pos,
        }
    }
}

/// Reads `text` as a `T`.
///
/// # Errors
/// [`XmlDeError::Read`] for malformed XML, [`XmlDeError::Refused`] naming the position of
/// what `T`'s deserializer refused.
pub fn from_document<T: DeserializeOwned>(text: &str) -> Result<T, XmlDeError> {
    let root = parse_document(text)?;
    match quick_xml::de::from_str::<T>(text) {
        Ok(v) => Ok(v),
        Err(e) => {
            let whole = readable(&e.to_string());
            let (pos, what, message) =
                locate::<T>(&[], &root).unwrap_or((root.pos, String::new(), whole));
            Err(XmlDeError::Refused { pos, what, message })
        }
    }
}

/// Serde's message without quick-xml's `@` before attribute names.
fn readable(message: &str) -> String {
    message.replace("`@", "`")
}

/// The position, attribute name (with `: `, or empty) and message of what `T` refuses in
/// `el` (under the ancestors `path`), if its subtree is refused at all.
fn locate<T: DeserializeOwned>(path: &[&Element], el: &Element) -> Option<(Pos, String, String)> {
    let whole = probe::<T>(path, el).err()?;
    let with_attrs = |keep: &dyn Fn(usize) -> bool| Element {
        attrs: el
            .attrs
            .iter()
            .enumerate()
            .filter(|(i, _)| keep(*i))
            .map(|(_, a)| a.clone())
            .collect(),
        ..el.clone()
    };
    let blamed = |i: usize, message: String| {
        let a = &el.attrs[i];
        Some((a.pos, format!("{}: ", a.name), message))
    };
    // An attribute whose removal makes the element acceptable.
    for i in 0..el.attrs.len() {
        if probe::<T>(path, &with_attrs(&|j| j != i)).is_ok() {
            let alone = probe::<T>(path, &with_attrs(&|j| j == i)).err();
            return blamed(i, alone.unwrap_or_else(|| whole.clone()));
        }
    }
    // One refused on its own, for another reason than the element's missing fields.
    let bare = Element {
        children: Vec::new(),
        ..with_attrs(&|_| false)
    };
    let bare_err = probe::<T>(path, &bare).err();
    for i in 0..el.attrs.len() {
        let alone = Element {
            children: Vec::new(),
            ..with_attrs(&|j| j == i)
        };
        if let Err(m) = probe::<T>(path, &alone) {
            if Some(&m) != bare_err.as_ref() {
                return blamed(i, m);
            }
        }
    }
    // Deeper.
    let mut inner: Vec<&Element> = path.to_vec();
    inner.push(el);
    for c in &el.children {
        if let Some(found) = locate::<T>(&inner, c) {
            return Some(found);
        }
    }
    Some((el.pos, String::new(), whole))
}

/// Deserializes `el` under `path` (each ancestor with its attributes, without its other
/// children).
fn probe<T: DeserializeOwned>(path: &[&Element], el: &Element) -> Result<(), String> {
    let mut doc = String::new();
    for a in path {
        write_start(&mut doc, a);
        doc.push('>');
    }
    write_element(&mut doc, el);
    for a in path.iter().rev() {
        doc.push_str("</");
        doc.push_str(&a.name);
        doc.push('>');
    }
    quick_xml::de::from_str::<T>(&doc)
        .map(drop)
        .map_err(|e| readable(&e.to_string()))
}

/// `<name a="v" ...` (not closed).
fn write_start(out: &mut String, el: &Element) {
    out.push('<');
    out.push_str(&el.name);
    for a in &el.attrs {
        out.push(' ');
        out.push_str(&a.name);
        out.push_str("=\"");
        out.push_str(&quick_xml::escape::escape(a.value.as_str()));
        out.push('"');
    }
}

fn write_element(out: &mut String, el: &Element) {
    write_start(out, el);
    if el.children.is_empty() {
        out.push_str("/>");
        return;
    }
    out.push('>');
    for c in &el.children {
        write_element(out, c);
    }
    out.push_str("</");
    out.push_str(&el.name);
    out.push('>');
}

#[cfg(test)]
mod tests {
    use serde::Deserialize;

    use super::*;

    #[derive(Debug, Default, Deserialize, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Cfg {
        #[serde(rename = "@name")]
        name: String,
        #[serde(rename = "@rate")]
        rate: u32,
        #[serde(rename = "link")]
        links: Vec<Link>,
    }

    #[derive(Debug, Default, Deserialize, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Link {
        #[serde(rename = "@to")]
        to: String,
        #[serde(rename = "@port", default)]
        port: u16,
        #[serde(rename = "pt", default)]
        points: Vec<Pt>,
    }

    #[derive(Debug, Default, Deserialize, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Pt {
        #[serde(rename = "@x")]
        x: f64,
    }

    fn refused(text: &str) -> (String, String) {
        match from_document::<Cfg>(text) {
            Err(e @ XmlDeError::Refused { .. }) => (e.pos().to_string(), e.to_string()),
            other => panic!("not refused by serde: {other:?}"),
        }
    }

    #[test]
    fn a_good_document_reads_as_serde_reads_it() {
        let c: Cfg =
            from_document("<cfg name=\"a &amp; b\" rate=\"3\"><link to=\"x\" port=\"9\"/></cfg>")
                .unwrap();
        assert_eq!(c.name, "a & b");
        assert_eq!((c.rate, c.links[0].port), (3, 9));
    }

    #[test]
    fn a_bad_value_or_an_unknown_attribute_is_named_where_it_is() {
        let (pos, e) = refused("<cfg name=\"a\"\n     rate=\"fast\"/>");
        assert_eq!(pos, "2:6");
        assert!(e.starts_with("2:6: rate: "), "{e}");
        let (pos, e) = refused("<cfg rate=\"1\" speed=\"2\"/>");
        assert_eq!(pos, "1:15");
        assert!(e.contains("unknown field `speed`"), "{e}");
    }

    #[test]
    fn errors_inside_child_elements_are_found_there() {
        // A bad port of the second link.
        let (pos, e) =
            refused("<cfg>\n  <link to=\"a\"/>\n  <link to=\"b\" port=\"99999\"/>\n</cfg>");
        assert_eq!(pos, "3:16", "{e}");
        // A required attribute missing: the element is named.
        let (pos, e) = refused("<cfg>\n  <link port=\"1\"/>\n</cfg>");
        assert_eq!(pos, "2:3");
        assert!(e.contains("missing field `to`"), "{e}");
        // A grandchild's bad value.
        let (pos, _) = refused("<cfg><link to=\"a\">\n<pt x=\"1\"/><pt x=\"one\"/></link></cfg>");
        assert_eq!(pos, "2:16");
        // An unknown element.
        let (pos, e) = refused("<cfg>\n <wire/></cfg>");
        assert_eq!(pos, "2:2");
        assert!(e.contains("wire"), "{e}");
    }

    #[test]
    fn malformed_xml_is_refused_by_the_reader_at_its_position() {
        match from_document::<Cfg>("<cfg>\n<link to=\"a\">\n</cfg>") {
            Err(XmlDeError::Read(e)) => assert_eq!(e.pos.line, 3, "{e}"),
            other => panic!("{other:?}"),
        }
    }
}

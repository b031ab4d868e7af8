//! A small element tree read with quick-xml that keeps the line and column of every element and
//! attribute, so plan errors can point at the source.

use quick_xml::events::{BytesStart, Event};
use quick_xml::Reader;
use serde::{Deserialize, Serialize};

/// A 1-based line and column.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Pos {
    /// Line, from 1.
    pub line: u32,
    /// Column in characters, from 1.
    pub col: u32,
}

/// An attribute with its value (entities resolved) and position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Attr {
    /// Name.
    pub name: String,
    /// Unescaped value.
    pub value: String,
    /// Where the name starts.
    pub pos: Pos,
}

/// An element with its attributes and child elements (text is not part of the format).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Element {
    /// Tag name.
    pub name: String,
    /// Attributes in document order.
    pub attrs: Vec<Attr>,
    /// Child elements.
    pub children: Vec<Element>,
    /// Where the `<` is.
    pub pos: Pos,
}

impl Element {
    /// A new element built in code (position 0:0).
    pub fn new(name: &str) -> Self {
        Self {
            name: name.to_string(),
            attrs: Vec::new(),
            children: Vec::new(),
            pos: Pos::default(),
        }
    }
    /// Sets (or replaces) an attribute, keeping the position of an existing one.
    pub fn set_attr(&mut self, name: &str, value: &str) {
        if let Some(a) = self.attrs.iter_mut().find(|a| a.name == name) {
            a.value = value.to_string();
        } else {
            self.attrs.push(Attr {
                name: name.to_string(),
                value: value.to_string(),
                pos: self.pos,
            });
        }
    }
    /// Builder form of [`Element::set_attr`].
    pub fn with_attr(mut self, name: &str, value: &str) -> Self {
        self.set_attr(name, value);
        self
    }
    /// The attribute `name`.
    pub fn attr(&self, name: &str) -> Option<&Attr> {
        self.attrs.iter().find(|a| a.name == name)
    }
}

/// A syntax error with its position.
#[derive(Debug, Clone, PartialEq)]
pub struct XmlError {
    /// Where.
    pub pos: Pos,
    /// What.
    pub message: String,
}

/// Line and column of byte `offset` in `src`.
pub fn pos_at(src: &str, offset: usize) -> Pos {
    let mut off = offset.min(src.len());
    while !src.is_char_boundary(off) {
        off -= 1;
    }
    let before = &src[..off];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let col = before[line_start..].chars().count() + 1;
    Pos {
        line: u32::try_from(line).unwrap_or(u32::MAX),
        col: u32::try_from(col).unwrap_or(u32::MAX),
    }
}

/// Nesting beyond this depth is refused (the format needs a handful of levels).
const MAX_DEPTH: usize = 256;

/// Parses a whole document and returns its root element.
///
/// # Errors
/// Malformed XML, text where only elements belong, several roots or none.
pub fn parse_document(src: &str) -> Result<Element, XmlError> {
    let roots = parse_elements(src)?;
    let mut it = roots.into_iter();
    match (it.next(), it.next()) {
        (Some(r), None) => Ok(r),
        (None, _) => Err(XmlError {
            pos: pos_at(src, src.len()),
            message: "the document has no root element".into(),
        }),
        (Some(_), Some(second)) => Err(XmlError {
            pos: second.pos,
            message: "a second root element; a plan has exactly one <flightPlan>".into(),
        }),
    }
}

/// Parses a sequence of top-level elements (a fragment, e.g. legs to insert).
///
/// # Errors
/// As [`parse_document`].
pub fn parse_elements(src: &str) -> Result<Vec<Element>, XmlError> {
    let mut reader = Reader::from_str(src);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<Element> = Vec::new();
    let mut roots = Vec::new();
    loop {
        let start = usize::try_from(reader.buffer_position()).unwrap_or(usize::MAX);
        let ev = reader.read_event().map_err(|e| XmlError {
            pos: pos_at(
                src,
                usize::try_from(reader.error_position()).unwrap_or(usize::MAX),
            ),
            message: format!("malformed XML: {e}"),
        })?;
        match ev {
            Event::Start(e) => {
                let el = element_from(src, start, &e)?;
                if stack.len() >= MAX_DEPTH {
                    return Err(XmlError {
                        pos: el.pos,
                        message: "elements nested too deeply".into(),
                    });
                }
                stack.push(el);
            }
            Event::Empty(e) => {
                let el = element_from(src, start, &e)?;
                stack.push(el);
                close(&mut stack, &mut roots);
            }
            Event::End(_) => close(&mut stack, &mut roots),
            Event::Text(t) => {
                let raw = String::from_utf8_lossy(t.as_ref()).into_owned();
                if !raw.trim().is_empty() {
                    let skip = raw.len() - raw.trim_start().len();
                    return Err(XmlError {
                        pos: pos_at(src, start + skip),
                        message: format!(
                            "unexpected text `{}`; the format has attributes only",
                            raw.trim()
                        ),
                    });
                }
            }
            Event::CData(_) | Event::GeneralRef(_) => {
                return Err(XmlError {
                    pos: pos_at(src, start),
                    message: "unexpected text; the format has attributes only".into(),
                })
            }
            Event::Eof => {
                if let Some(open) = stack.last() {
                    return Err(XmlError {
                        pos: open.pos,
                        message: format!("<{}> is never closed", open.name),
                    });
                }
                return Ok(roots);
            }
            Event::Decl(_) | Event::PI(_) | Event::Comment(_) | Event::DocType(_) => {}
        }
    }
}

fn close(stack: &mut Vec<Element>, roots: &mut Vec<Element>) {
    // quick-xml checks end names, so an End always matches the element on top.
    if let Some(done) = stack.pop() {
        match stack.last_mut() {
            Some(parent) => parent.children.push(done),
            None => roots.push(done),
        }
    }
}

fn element_from(src: &str, start: usize, e: &BytesStart<'_>) -> Result<Element, XmlError> {
    let pos = pos_at(src, start);
    let name = String::from_utf8_lossy(e.name().as_ref()).into_owned();
    // The tag's raw text starts right after '<'; attribute positions are found in it.
    let raw = String::from_utf8_lossy(e.as_ref()).into_owned();
    let mut attrs = Vec::new();
    let mut search_from = name.len();
    for a in e.attributes() {
        let a = a.map_err(|err| XmlError {
            pos,
            message: format!("malformed attribute in <{name}>: {err}"),
        })?;
        let key = String::from_utf8_lossy(a.key.as_ref()).into_owned();
        let value = a
            .unescape_value()
            .map_err(|err| XmlError {
                pos,
                message: format!("bad value of attribute `{key}` in <{name}>: {err}"),
            })?
            .into_owned();
        let rel = raw[search_from.min(raw.len())..]
            .find(&key)
            .map(|i| i + search_from);
        let apos = match rel {
            Some(r) => {
                search_from = r + key.len();
                pos_at(src, start + 1 + r)
            }
            None => pos,
        };
        if attrs.iter().any(|x: &Attr| x.name == key) {
            return Err(XmlError {
                pos: apos,
                message: format!("attribute `{key}` given twice in <{name}>"),
            });
        }
        attrs.push(Attr {
            name: key,
            value,
            pos: apos,
        });
    }
    Ok(Element {
        name,
        attrs,
        children: Vec::new(),
        pos,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_of_elements_and_attributes() {
        let src = "<a>\n  <b x=\"1\"\n     y=\"2\"/>\n  <c></c>\n</a>";
        let root = parse_document(src).unwrap();
        assert_eq!(root.children.len(), 2);
        let b = &root.children[0];
        assert_eq!(b.pos, Pos { line: 2, col: 3 });
        assert_eq!(b.attr("x").unwrap().pos, Pos { line: 2, col: 6 });
        assert_eq!(b.attr("y").unwrap().pos, Pos { line: 3, col: 6 });
        assert_eq!(root.children[1].pos, Pos { line: 4, col: 3 });
    }

    #[test]
    fn mismatched_end_names_the_line() {
        let err = parse_document("<a>\n<b>\n</c>\n</a>").unwrap_err();
        assert_eq!(err.pos.line, 3, "{err:?}");
    }

    #[test]
    fn unclosed_and_text_are_errors() {
        assert!(parse_document("<a><b/>").is_err());
        let err = parse_document("<a>\n hello</a>").unwrap_err();
        assert_eq!(err.pos, Pos { line: 2, col: 2 });
    }
}

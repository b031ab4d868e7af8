//! Reading XML with positions: the one quick-xml walker behind `network.xml`, the launcher's
//! mission files and the FPMa's flight plans. Generic: it knows no element of any format.
//!
//! - [`LineIndex`] maps a byte offset to a 1-based line and column (in characters). It is built
//!   once per text, so each lookup is a binary search rather than a rescan from the start (the
//!   FPMa's old walker rescanned for every element, which made a 1 MB plan take tens of
//!   seconds).
//! - [`Reader`] is a pull reader for callers that validate as they read (errors come in document
//!   order): it yields start tags with the position of every attribute, end tags, and text that
//!   is not whitespace; comments, declarations, processing instructions and DOCTYPEs are skipped.
//! - [`parse_document`] and [`parse_fragment`] build an [`Element`] tree on top of it for formats
//!   that have attributes and elements only; text there is an error.
//! - [`de::from_document`] reads a serde-described configuration file (the VAS's, the FPMa's)
//!   and names the line and column of what it refuses.
//!
//! Bounds: nesting is limited to [`MAX_DEPTH`] open elements (so is quick-xml's own stack of
//! open names); everything else is proportional to the text the caller already holds: the index
//! keeps one offset per line and one per non-ASCII byte, the tree one node per element.
//!
//! ```
//! let doc = marea::xml::parse_document("<a>\n  <b x=\"1\"/>\n</a>").unwrap();
//! let b = &doc.children[0];
//! assert_eq!((b.pos.line, b.pos.col), (2, 3));
//! assert_eq!(b.attr("x").map(|a| (a.value.as_str(), a.pos.col)), Some(("1", 6)));
//! ```

pub mod de;

use std::fmt;

use quick_xml::events::attributes::{AttrError, Attribute};
use quick_xml::events::{BytesStart, Event};
use serde::{Deserialize, Serialize};

/// Most elements open at once; a deeper start tag is [`XmlReadErrorKind::TooDeep`].
pub const MAX_DEPTH: usize = 256;

/// A 1-based line and column; the column counts characters, not bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Pos {
    /// Line, from 1 (0 for something built in code).
    pub line: u32,
    /// Column in characters, from 1.
    pub col: u32,
}

impl fmt::Display for Pos {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.line, self.col)
    }
}

/// Line starts and non-ASCII bytes of a text, for [`LineIndex::pos`].
#[derive(Clone, Debug)]
pub struct LineIndex {
    /// Byte offset where each line starts; the first is 0.
    starts: Vec<usize>,
    /// Offsets of UTF-8 continuation bytes (they do not start a character), ascending.
    continuations: Vec<usize>,
    /// Length of the text.
    len: usize,
}

impl LineIndex {
    /// Indexes `text` in one pass.
    pub fn new(text: &str) -> Self {
        let bytes = text.as_bytes();
        let mut starts = vec![0];
        let mut continuations = Vec::new();
        for (i, &b) in bytes.iter().enumerate() {
            if b == b'\n' {
                starts.push(i + 1);
            } else if b & 0xC0 == 0x80 {
                continuations.push(i);
            }
        }
        Self {
            starts,
            continuations,
            len: bytes.len(),
        }
    }

    /// Line and column of byte `offset`. An offset inside a character is taken as that
    /// character's start; one past the end as the end of the text.
    pub fn pos(&self, offset: usize) -> Pos {
        let mut offset = offset.min(self.len);
        // Back to the character's first byte. `k` is the first continuation at or after
        // `offset`; a continuation byte before `offset - 1` is then at `k - 1` at the latest.
        let mut k = self.continuations.partition_point(|&c| c < offset);
        while offset > 0 && self.continuations.get(k) == Some(&offset) {
            offset -= 1;
            k = k.saturating_sub(1);
        }
        let line = self.starts.partition_point(|&s| s <= offset).max(1);
        let start = self.starts[line - 1];
        let below_start = self.continuations.partition_point(|&c| c < start);
        let below_offset = self.continuations.partition_point(|&c| c < offset);
        let col = offset - start - (below_offset - below_start) + 1;
        Pos {
            line: u32::try_from(line).unwrap_or(u32::MAX),
            col: u32::try_from(col).unwrap_or(u32::MAX),
        }
    }
}

/// An element's name and where its `<` is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ElementAt {
    /// Tag name.
    pub name: String,
    /// Where its `<` is.
    pub pos: Pos,
}

/// Why the XML could not be read, and where.
#[derive(Debug, thiserror::Error)]
#[error("{pos}: {kind}")]
pub struct XmlReadError {
    /// Where exactly: quick-xml's error position, the attribute, the text, the element.
    pub pos: Pos,
    /// The element it is in: the tag being read for attribute errors, else the innermost open
    /// element (`None` outside the root).
    pub element: Option<ElementAt>,
    /// What is wrong.
    pub kind: XmlReadErrorKind,
}

/// What is wrong with the XML.
#[derive(Debug, thiserror::Error)]
pub enum XmlReadErrorKind {
    /// Not well-formed (quick-xml's description), e.g. a mismatched end tag.
    #[error("{0}")]
    Syntax(#[source] quick_xml::Error),
    /// An attribute without `=`, value or quotes, or given twice; positions in it are relative
    /// to the tag's content (after `<`).
    #[error("{0}")]
    Attribute(#[source] AttrError),
    /// An attribute value with a bad entity or character reference.
    #[error("attribute `{name}`: {source}")]
    AttributeValue {
        /// The attribute.
        name: String,
        /// quick-xml's description.
        #[source]
        source: quick_xml::Error,
    },
    /// The input ended with this element open (`pos` is its start tag).
    #[error("<{0}> is never closed")]
    Unclosed(String),
    /// More than [`MAX_DEPTH`] elements open at once.
    #[error("elements nested deeper than {MAX_DEPTH}")]
    TooDeep,
    /// Text, CDATA or an entity reference where the tree builders take elements only.
    #[error("unexpected {}", .0.describe())]
    Text(Text),
    /// A document with no element.
    #[error("no root element")]
    NoRoot,
    /// A document with a second top-level element (`pos` is its start tag).
    #[error("a second root element <{0}>")]
    SecondRoot(String),
}

/// Content between tags that is not whitespace.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Text {
    /// Which kind.
    pub kind: TextKind,
    /// Character data as written (from its first non-whitespace character), the CDATA content,
    /// or the entity's name.
    pub content: String,
    /// Where it starts: its first non-whitespace character, the `<![CDATA[` or the `&`.
    pub pos: Pos,
}

impl Text {
    fn describe(&self) -> String {
        match self.kind {
            TextKind::Chars => format!("text `{}`", self.content.trim()),
            TextKind::CData => "CDATA".into(),
            TextKind::Reference => format!("entity reference `&{};`", self.content),
        }
    }
}

/// What kind of content a [`Text`] is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TextKind {
    /// Character data.
    Chars,
    /// A `<![CDATA[...]]>` section.
    CData,
    /// An entity or character reference such as `&amp;`.
    Reference,
}

/// One step of a [`Reader`].
#[derive(Debug)]
pub enum XmlEvent<'a> {
    /// A start tag, or an empty-element tag (`<x/>`, see [`Tag::is_empty`]).
    Start(Tag<'a>),
    /// The end tag of the innermost open element (quick-xml checks that the names match).
    End,
    /// Content that is not whitespace.
    Text(Text),
    /// The end of the input, every element closed.
    Eof,
}

/// A start tag as read, its attributes not yet parsed.
#[derive(Debug)]
pub struct Tag<'a> {
    start: BytesStart<'a>,
    name: String,
    offset: usize,
    pos: Pos,
    empty: bool,
    index: &'a LineIndex,
}

impl<'a> Tag<'a> {
    /// The tag name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Where the `<` is.
    pub fn pos(&self) -> Pos {
        self.pos
    }

    /// Byte offset of the `<`.
    pub fn offset(&self) -> usize {
        self.offset
    }

    /// `true` for an empty-element tag (`<x/>`): no content and no end tag follow.
    pub fn is_empty(&self) -> bool {
        self.empty
    }

    fn at(&self) -> ElementAt {
        ElementAt {
            name: self.name.clone(),
            pos: self.pos,
        }
    }

    /// The attributes in document order, each parsed when the iterator reaches it (so a caller
    /// that stops at the first bad one reports errors in document order). Repeated names are
    /// not checked here; [`parse_document`] and [`parse_fragment`] check them.
    pub fn attributes(&self) -> impl Iterator<Item = Result<RawAttr<'_>, XmlReadError>> + '_ {
        let content: &[u8] = &self.start;
        // Tag content starts after '<'; quick-xml's attribute error positions count from there.
        let base = self.offset + 1;
        let mut attributes = self.start.attributes();
        attributes.with_checks(false);
        attributes.map(move |attribute| match attribute {
            Ok(inner) => {
                let key = inner.key.as_ref();
                // The key is a slice of the tag's content; its address gives its position.
                let relative = (key.as_ptr() as usize)
                    .wrapping_sub(content.as_ptr() as usize)
                    .min(content.len());
                Ok(RawAttr {
                    name: String::from_utf8_lossy(key).into_owned(),
                    relative,
                    pos: self.index.pos(base + relative),
                    inner,
                })
            }
            Err(err) => Err(XmlReadError {
                pos: self.index.pos(base + attr_error_offset(&err)),
                element: Some(self.at()),
                kind: XmlReadErrorKind::Attribute(err),
            }),
        })
    }
}

/// An attribute whose value is not unescaped yet.
#[derive(Debug)]
pub struct RawAttr<'t> {
    /// Its name as written.
    pub name: String,
    /// Where its name starts.
    pub pos: Pos,
    /// Offset of its name in the tag's content (after `<`), as quick-xml counts.
    relative: usize,
    inner: Attribute<'t>,
}

impl RawAttr<'_> {
    /// The value with entity and character references resolved.
    ///
    /// # Errors
    /// [`XmlReadErrorKind::AttributeValue`] for an unknown entity or a bad reference, at the
    /// attribute; `element` is `None` (the caller knows its tag).
    pub fn value(&self) -> Result<String, XmlReadError> {
        match self.inner.unescape_value() {
            Ok(v) => Ok(v.into_owned()),
            Err(source) => Err(XmlReadError {
                pos: self.pos,
                element: None,
                kind: XmlReadErrorKind::AttributeValue {
                    name: self.name.clone(),
                    source,
                },
            }),
        }
    }
}

/// A pull reader over a text, with positions from a [`LineIndex`] of the same text.
pub struct Reader<'a> {
    text: &'a str,
    index: &'a LineIndex,
    inner: quick_xml::Reader<&'a [u8]>,
    /// The open elements, innermost last; at most [`MAX_DEPTH`].
    open: Vec<ElementAt>,
    /// Bytes quick-xml leaves out of its positions: a leading byte-order mark.
    bom: usize,
}

impl<'a> Reader<'a> {
    /// A reader of `text`; `index` must be `LineIndex::new(text)`.
    pub fn new(text: &'a str, index: &'a LineIndex) -> Self {
        let mut inner = quick_xml::Reader::from_str(text);
        let config = inner.config_mut();
        config.trim_text(false);
        config.check_end_names = true;
        config.check_comments = false;
        config.expand_empty_elements = false;
        Self {
            text,
            index,
            inner,
            open: Vec::new(),
            bom: if text.starts_with('\u{feff}') { 3 } else { 0 },
        }
    }

    /// Refuses comments that contain `--` (as XML does; off by default, since hand-written
    /// files often have them and nothing is lost by reading them).
    pub fn check_comments(&mut self, check: bool) -> &mut Self {
        self.inner.config_mut().check_comments = check;
        self
    }

    /// Line and column of byte `offset` of the text.
    pub fn pos(&self, offset: usize) -> Pos {
        self.index.pos(offset)
    }

    /// The innermost open element.
    pub fn innermost(&self) -> Option<&ElementAt> {
        self.open.last()
    }

    fn error(&self, pos: Pos, kind: XmlReadErrorKind) -> XmlReadError {
        XmlReadError {
            pos,
            element: self.open.last().cloned(),
            kind,
        }
    }

    /// The next start tag, end tag, text or the end of the input.
    ///
    /// # Errors
    /// [`XmlReadErrorKind::Syntax`] where quick-xml finds the text malformed,
    /// [`XmlReadErrorKind::Unclosed`] at the innermost open element when the input ends, and
    /// [`XmlReadErrorKind::TooDeep`] at a start tag beyond [`MAX_DEPTH`].
    pub fn read_event(&mut self) -> Result<XmlEvent<'a>, XmlReadError> {
        loop {
            let before = to_usize(self.inner.buffer_position()).saturating_add(self.bom);
            let event = match self.inner.read_event() {
                Ok(event) => event,
                Err(source) => {
                    let at =
                        self.pos(to_usize(self.inner.error_position()).saturating_add(self.bom));
                    return Err(self.error(at, XmlReadErrorKind::Syntax(source)));
                }
            };
            let (start, empty) = match event {
                Event::Start(start) => (start, false),
                Event::Empty(start) => (start, true),
                Event::End(_) => {
                    self.open.pop();
                    return Ok(XmlEvent::End);
                }
                Event::Text(text) => {
                    let Some(skip) = text.iter().position(|b| !b" \t\r\n".contains(b)) else {
                        continue;
                    };
                    let content = String::from_utf8_lossy(&text[skip..]).into_owned();
                    return Ok(self.text(TextKind::Chars, content, before + skip));
                }
                Event::CData(data) => {
                    let content = String::from_utf8_lossy(&data).into_owned();
                    return Ok(self.text(TextKind::CData, content, before));
                }
                Event::GeneralRef(name) => {
                    let content = String::from_utf8_lossy(&name).into_owned();
                    return Ok(self.text(TextKind::Reference, content, before));
                }
                Event::Eof => {
                    return match self.open.last() {
                        Some(open) => {
                            Err(self.error(open.pos, XmlReadErrorKind::Unclosed(open.name.clone())))
                        }
                        None => Ok(XmlEvent::Eof),
                    };
                }
                Event::Decl(_) | Event::PI(_) | Event::Comment(_) | Event::DocType(_) => continue,
            };
            // The reader may skip a byte-order mark before the first event, so locate the
            // tag's `<` rather than trusting the previous end position.
            let offset = self
                .text
                .as_bytes()
                .get(before..)
                .and_then(|rest| rest.iter().position(|&b| b == b'<'))
                .map_or(before, |i| before + i);
            let tag = Tag {
                name: String::from_utf8_lossy(start.name().as_ref()).into_owned(),
                start,
                offset,
                pos: self.pos(offset),
                empty,
                index: self.index,
            };
            if !empty {
                if self.open.len() >= MAX_DEPTH {
                    return Err(self.error(tag.pos, XmlReadErrorKind::TooDeep));
                }
                self.open.push(tag.at());
            }
            return Ok(XmlEvent::Start(tag));
        }
    }

    fn text(&self, kind: TextKind, content: String, offset: usize) -> XmlEvent<'a> {
        XmlEvent::Text(Text {
            kind,
            content,
            pos: self.pos(offset),
        })
    }
}

/// An attribute with its value (references resolved) and position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Attr {
    /// Name.
    pub name: String,
    /// Unescaped value.
    pub value: String,
    /// Where the name starts.
    pub pos: Pos,
}

/// An element with its attributes and child elements (a tree of a format without text).
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
            name: name.to_owned(),
            attrs: Vec::new(),
            children: Vec::new(),
            pos: Pos::default(),
        }
    }

    /// Sets (or replaces) an attribute, keeping the position of an existing one.
    pub fn set_attr(&mut self, name: &str, value: &str) {
        if let Some(a) = self.attrs.iter_mut().find(|a| a.name == name) {
            value.clone_into(&mut a.value);
        } else {
            self.attrs.push(Attr {
                name: name.to_owned(),
                value: value.to_owned(),
                pos: self.pos,
            });
        }
    }

    /// Builder form of [`Element::set_attr`].
    #[must_use]
    pub fn with_attr(mut self, name: &str, value: &str) -> Self {
        self.set_attr(name, value);
        self
    }

    /// The attribute `name`.
    pub fn attr(&self, name: &str) -> Option<&Attr> {
        self.attrs.iter().find(|a| a.name == name)
    }
}

/// Parses a whole document: exactly one root element, no text outside or inside elements.
///
/// # Errors
/// Whatever [`Reader::read_event`] reports, [`XmlReadErrorKind::Attribute`] (a repeated attribute is
/// [`AttrError::Duplicated`]), [`XmlReadErrorKind::AttributeValue`],
/// [`XmlReadErrorKind::Text`], [`XmlReadErrorKind::SecondRoot`] at the second root's start tag,
/// and [`XmlReadErrorKind::NoRoot`] at the end of the text.
pub fn parse_document(text: &str) -> Result<Element, XmlReadError> {
    let index = LineIndex::new(text);
    let mut roots = build(text, &index, true)?;
    roots.pop().ok_or_else(|| XmlReadError {
        pos: index.pos(text.len()),
        element: None,
        kind: XmlReadErrorKind::NoRoot,
    })
}

/// Parses a sequence of top-level elements (a fragment, e.g. legs to insert); no text.
///
/// # Errors
/// As [`parse_document`], less the root checks.
pub fn parse_fragment(text: &str) -> Result<Vec<Element>, XmlReadError> {
    build(text, &LineIndex::new(text), false)
}

fn build(text: &str, index: &LineIndex, one_root: bool) -> Result<Vec<Element>, XmlReadError> {
    let mut reader = Reader::new(text, index);
    // Built elements whose end tag has not come yet, innermost last.
    let mut stack: Vec<Element> = Vec::new();
    let mut roots = Vec::new();
    loop {
        match reader.read_event()? {
            XmlEvent::Start(tag) => {
                if one_root && stack.is_empty() && !roots.is_empty() {
                    return Err(XmlReadError {
                        pos: tag.pos(),
                        element: None,
                        kind: XmlReadErrorKind::SecondRoot(tag.name().to_owned()),
                    });
                }
                stack.push(element(&tag)?);
                if tag.is_empty() {
                    close(&mut stack, &mut roots);
                }
            }
            XmlEvent::End => close(&mut stack, &mut roots),
            XmlEvent::Text(t) => {
                return Err(XmlReadError {
                    pos: t.pos,
                    element: reader.innermost().cloned(),
                    kind: XmlReadErrorKind::Text(t),
                })
            }
            XmlEvent::Eof => return Ok(roots),
        }
    }
}

fn close(stack: &mut Vec<Element>, roots: &mut Vec<Element>) {
    // quick-xml checks end names, so an end always closes the element on top.
    if let Some(done) = stack.pop() {
        match stack.last_mut() {
            Some(parent) => parent.children.push(done),
            None => roots.push(done),
        }
    }
}

fn element(tag: &Tag<'_>) -> Result<Element, XmlReadError> {
    let mut attrs: Vec<(usize, Attr)> = Vec::new();
    for raw in tag.attributes() {
        let raw = raw?;
        if let Some((first, _)) = attrs.iter().find(|(_, a)| a.name == raw.name) {
            // What quick-xml's own check says, positions relative to the tag's content.
            return Err(XmlReadError {
                pos: raw.pos,
                element: Some(tag.at()),
                kind: XmlReadErrorKind::Attribute(AttrError::Duplicated(raw.relative, *first)),
            });
        }
        let value = raw.value().map_err(|mut e| {
            e.element = Some(tag.at());
            e
        })?;
        attrs.push((
            raw.relative,
            Attr {
                name: raw.name,
                value,
                pos: raw.pos,
            },
        ));
    }
    Ok(Element {
        name: tag.name().to_owned(),
        attrs: attrs.into_iter().map(|(_, a)| a).collect(),
        children: Vec::new(),
        pos: tag.pos(),
    })
}

fn attr_error_offset(err: &AttrError) -> usize {
    match *err {
        AttrError::ExpectedEq(p)
        | AttrError::ExpectedValue(p)
        | AttrError::UnquotedValue(p)
        | AttrError::ExpectedQuote(p, _)
        | AttrError::Duplicated(p, _) => p,
    }
}

fn to_usize(position: u64) -> usize {
    usize::try_from(position).unwrap_or(usize::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Line and column by rescanning the prefix: what the index must agree with.
    fn slow_pos(text: &str, offset: usize) -> Pos {
        let mut off = offset.min(text.len());
        while !text.is_char_boundary(off) {
            off -= 1;
        }
        let before = &text[..off];
        let line = before.matches('\n').count() + 1;
        let start = before.rfind('\n').map_or(0, |i| i + 1);
        let col = before[start..].chars().count() + 1;
        Pos {
            line: line as u32,
            col: col as u32,
        }
    }

    #[test]
    fn the_index_agrees_with_a_rescan_at_every_offset() {
        let text = "a\né✈b\n\n\u{feff}<x y='ü'/>\r\nlast";
        let index = LineIndex::new(text);
        for offset in 0..=text.len() + 2 {
            assert_eq!(index.pos(offset), slow_pos(text, offset), "offset {offset}");
        }
        assert_eq!(LineIndex::new("").pos(0), Pos { line: 1, col: 1 });
    }

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
    fn an_attribute_name_inside_an_earlier_value_does_not_move_its_position() {
        let root = parse_document("<a fix=\"id\" id=\"x\"/>").unwrap();
        assert_eq!(root.attr("id").unwrap().pos, Pos { line: 1, col: 13 });
    }

    #[test]
    fn errors_say_where_and_in_which_element() {
        let err = parse_document("<a>\n<b>\n</c>\n</a>").unwrap_err();
        assert!(matches!(err.kind, XmlReadErrorKind::Syntax(_)), "{err}");
        assert_eq!(err.pos, Pos { line: 3, col: 1 });
        assert_eq!(err.element.unwrap().name, "b");

        let err = parse_document("<a>\n hello</a>").unwrap_err();
        assert_eq!(err.pos, Pos { line: 2, col: 2 });
        assert_eq!(err.to_string(), "2:2: unexpected text `hello`");

        let err = parse_document("<a>\n  <b>\n").unwrap_err();
        assert_eq!(err.pos, Pos { line: 2, col: 3 });
        assert_eq!(err.to_string(), "2:3: <b> is never closed");

        let err = parse_document("<a/>\n<b/>").unwrap_err();
        assert_eq!(err.to_string(), "2:1: a second root element <b>");
        assert_eq!(parse_fragment("<a/>\n<b/>").unwrap().len(), 2);

        let err = parse_document("<!-- -->\n").unwrap_err();
        assert!(matches!(err.kind, XmlReadErrorKind::NoRoot));
        assert_eq!(err.pos, Pos { line: 2, col: 1 });

        let err = parse_document("<a>\n<b x=\"1\" y=\"2\" x=\"3\"/></a>").unwrap_err();
        assert!(
            matches!(
                err.kind,
                XmlReadErrorKind::Attribute(AttrError::Duplicated(14, 2))
            ),
            "{err:?}"
        );
        assert_eq!(
            (err.pos, err.element.unwrap().name.as_str()),
            (Pos { line: 2, col: 16 }, "b")
        );

        let err = parse_document("<a>\n  <b x=\"&bogus;\"/></a>").unwrap_err();
        assert!(matches!(err.kind, XmlReadErrorKind::AttributeValue { .. }));
        assert_eq!(err.pos, Pos { line: 2, col: 6 });
    }

    #[test]
    fn nesting_is_bounded() {
        let deep = |n: usize| format!("{}{}", "<a>".repeat(n), "</a>".repeat(n));
        parse_document(&deep(MAX_DEPTH)).unwrap();
        let err = parse_document(&deep(MAX_DEPTH + 1)).unwrap_err();
        assert!(matches!(err.kind, XmlReadErrorKind::TooDeep), "{err}");
        assert_eq!(err.pos.col as usize, 3 * MAX_DEPTH + 1);
    }

    #[test]
    fn the_reader_yields_tags_ends_and_text_in_order() {
        let text =
            "\u{feff}<?xml version=\"1.0\"?><a k=\"v\"><!-- c --><b/> t <![CDATA[x]]>&amp;</a>";
        let index = LineIndex::new(text);
        let mut r = Reader::new(text, &index);
        let mut seen = Vec::new();
        loop {
            match r.read_event().unwrap() {
                XmlEvent::Start(tag) => {
                    let attrs: Vec<_> = tag
                        .attributes()
                        .map(|a| a.unwrap().value().unwrap())
                        .collect();
                    seen.push(format!(
                        "<{}{attrs:?}{}@{}",
                        tag.name(),
                        tag.is_empty(),
                        tag.pos()
                    ));
                }
                XmlEvent::End => seen.push("end".into()),
                XmlEvent::Text(t) => seen.push(format!("{:?}:{}@{}", t.kind, t.content, t.pos)),
                XmlEvent::Eof => break,
            }
        }
        assert_eq!(
            seen,
            [
                "<a[\"v\"]false@1:23",
                "<b[]true@1:42",
                "Chars:t @1:47",
                "CData:x@1:49",
                "Reference:amp@1:62",
                "end"
            ]
        );
    }

    #[test]
    fn a_large_document_is_indexed_once() {
        // 20,000 elements: a rescan per element would take seconds; this takes milliseconds.
        let body: String = (0..20_000).map(|i| format!("  <e i=\"{i}\"/>\n")).collect();
        let text = format!("<r>\n{body}  <e i=\"x\" i=\"y\"/>\n</r>");
        let err = parse_document(&text).unwrap_err();
        assert_eq!(
            err.pos,
            Pos {
                line: 20_002,
                col: 12
            }
        );
    }
}

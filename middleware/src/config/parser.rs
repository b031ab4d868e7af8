//! The walk over a `network.xml` with [`crate::xml::Reader`]: each element and attribute is
//! checked as it is read, so errors come in document order, each with its line and column.

use std::path::Path;
use std::time::Duration;

use quick_xml::errors::IllFormedError;

use super::access::{AccessConfig, AccessKind, AccessRule};
use super::error::{ConfigLoadError, Location};
use super::model::*;
use super::values::*;
use super::DEFAULT_DOMAIN;
use crate::xml::{
    LineIndex, Pos, Reader, Tag, Text, TextKind, XmlEvent, XmlReadError, XmlReadErrorKind,
};

/// The attributes of one element, checked against the element's allowed list.
struct Attrs {
    element: &'static str,
    /// Where the element's `<` is.
    pos: Pos,
    list: Vec<Attr>,
}

struct Attr {
    key: &'static str,
    value: String,
    /// Where the attribute's name is.
    pos: Pos,
}

impl Attrs {
    fn get(&self, key: &str) -> Option<&Attr> {
        self.list.iter().find(|a| a.key == key)
    }

    /// Where `key` is, or where the element is when `key` is absent.
    fn pos_of(&self, key: &str) -> Pos {
        self.get(key).map_or(self.pos, |a| a.pos)
    }
}

/// An element's start tag and where it is.
type Element<'a> = Tag<'a>;

/// What a parsed link contributes to the cross-link checks.
struct ParsedLink {
    link: LinkConfig,
    enabled: bool,
    name_at: Location,
    /// Serial ports it opens, with where each is named.
    ports: Vec<(String, Location)>,
}

pub(super) struct Parser<'a> {
    text: &'a str,
    source: Option<&'a Path>,
    reader: Reader<'a>,
}

impl<'a> Parser<'a> {
    /// A parser of `text`; `index` is `LineIndex::new(text)`.
    pub(super) fn new(text: &'a str, index: &'a LineIndex, source: Option<&'a Path>) -> Self {
        let mut reader = Reader::new(text, index);
        reader.check_comments(true);
        Self {
            text,
            source,
            reader,
        }
    }

    fn at(&self, pos: Pos) -> Location {
        Location {
            file: self.source.map(Box::from),
            line: pos.line as usize,
            column: pos.col as usize,
        }
    }

    /// A reader error as the loader reports it.
    fn malformed(&self, e: XmlReadError) -> ConfigLoadError {
        let source = match e.kind {
            XmlReadErrorKind::Syntax(source) | XmlReadErrorKind::AttributeValue { source, .. } => {
                source
            }
            XmlReadErrorKind::Attribute(err) => err.into(),
            // quick-xml reports a missing end tag only as the end of input.
            XmlReadErrorKind::Unclosed(name) => IllFormedError::MissingEndTag(name).into(),
            // The reader reports nothing else: the grammar refuses an element below
            // <network>/<ethernet>/<peer> as soon as it is read, long before the depth limit,
            // and text comes as an event, not an error.
            _ => {
                let open = e.element.map(|el| el.name).unwrap_or_default();
                IllFormedError::MissingEndTag(open).into()
            }
        };
        ConfigLoadError::MalformedXml {
            at: self.at(e.pos),
            source,
        }
    }

    /// The next start tag, end tag, text or end of input.
    fn event(&mut self) -> Result<XmlEvent<'a>, ConfigLoadError> {
        self.reader.read_event().map_err(|e| self.malformed(e))
    }

    pub(super) fn document(self) -> Result<NetworkConfig, ConfigLoadError> {
        self.document_of("network", Self::network)
    }

    /// An access file: `<access>` as the root (see [`AccessConfig::parse`]).
    pub(super) fn access_document(self) -> Result<AccessConfig, ConfigLoadError> {
        self.document_of("access", Self::access)
    }

    /// A document whose one root element is `root`, read by `read`.
    fn document_of<T>(
        mut self,
        root: &'static str,
        read: fn(&mut Self, &Element<'a>) -> Result<T, ConfigLoadError>,
    ) -> Result<T, ConfigLoadError> {
        let config = loop {
            match self.event()? {
                XmlEvent::Start(found) => {
                    if found.name() != root {
                        return Err(ConfigLoadError::WrongRoot {
                            at: self.at(found.pos()),
                            expected: root,
                            found: found.name().to_owned(),
                        });
                    }
                    break read(&mut self, &found)?;
                }
                XmlEvent::Eof => {
                    return Err(ConfigLoadError::NoRootElement {
                        at: self.at(self.reader.pos(self.text.len())),
                    })
                }
                XmlEvent::Text(text) => return Err(self.unexpected_text(&text, None)),
                // quick-xml rejects unmatched end tags itself.
                XmlEvent::End => {}
            }
        };
        loop {
            match self.event()? {
                XmlEvent::Start(tag) => {
                    return Err(ConfigLoadError::TrailingContent {
                        at: self.at(tag.pos()),
                        found: tag.name().to_owned(),
                    })
                }
                XmlEvent::Eof => return Ok(config),
                XmlEvent::Text(text) => return Err(self.unexpected_text(&text, None)),
                XmlEvent::End => {}
            }
        }
    }

    /// Text, CDATA or an entity reference, where only elements and comments may appear.
    fn unexpected_text(&self, text: &Text, element: Option<&'static str>) -> ConfigLoadError {
        let found = match text.kind {
            TextKind::Chars => text.content.trim().to_owned(),
            TextKind::CData => format!("<![CDATA[{}]]>", text.content),
            TextKind::Reference => format!("&{};", text.content),
        };
        ConfigLoadError::UnexpectedText {
            at: self.at(text.pos),
            element,
            found: shorten(&found),
        }
    }

    /// The next child element of `parent`, or `None` once `parent` has ended. Call it until it
    /// returns `None`, and no further.
    fn child(
        &mut self,
        name: &'static str,
        parent: &Element<'a>,
    ) -> Result<Option<Element<'a>>, ConfigLoadError> {
        if parent.is_empty() {
            return Ok(None);
        }
        match self.event()? {
            XmlEvent::Start(child) => Ok(Some(child)),
            // quick-xml checks that end names match, so this is `parent`'s end.
            XmlEvent::End => Ok(None),
            XmlEvent::Text(text) => Err(self.unexpected_text(&text, Some(name))),
            // The reader reports an open element at the end of input as an error.
            XmlEvent::Eof => Ok(None),
        }
    }

    /// Consumes the content of an element that takes no child elements.
    fn no_children(
        &mut self,
        name: &'static str,
        element: &Element<'a>,
    ) -> Result<(), ConfigLoadError> {
        match self.child(name, element)? {
            None => Ok(()),
            Some(child) => Err(self.unknown_element(name, &child, NO_ELEMENTS)),
        }
    }

    fn unknown_element(
        &self,
        parent: &'static str,
        child: &Element<'_>,
        expected: &'static [&'static str],
    ) -> ConfigLoadError {
        let found = child.name().to_owned();
        ConfigLoadError::UnknownElement {
            at: self.at(child.pos()),
            parent,
            suggestion: closest(&found, expected),
            found,
            expected,
        }
    }

    /// Reads an element's attributes, rejecting unknown and repeated ones.
    fn attributes(
        &self,
        name: &'static str,
        element: &Element<'_>,
        allowed: &'static [&'static str],
    ) -> Result<Attrs, ConfigLoadError> {
        let mut attrs = Attrs {
            element: name,
            pos: element.pos(),
            list: Vec::new(),
        };
        for attribute in element.attributes() {
            let attribute = attribute.map_err(|e| self.malformed(e))?;
            let key = attribute.name.as_str();
            if key == "xmlns" || key.starts_with("xmlns:") {
                continue;
            }
            let Some(&known) = allowed.iter().find(|&&name| name == key) else {
                return Err(ConfigLoadError::UnknownAttribute {
                    at: self.at(attribute.pos),
                    element: name,
                    suggestion: closest(key, allowed),
                    found: key.to_owned(),
                    expected: allowed,
                });
            };
            if attrs.get(known).is_some() {
                return Err(ConfigLoadError::DuplicateAttribute {
                    at: self.at(attribute.pos),
                    element: name,
                    attribute: known,
                });
            }
            let value = attribute.value().map_err(|e| self.malformed(e))?;
            attrs.list.push(Attr {
                key: known,
                value,
                pos: attribute.pos,
            });
        }
        Ok(attrs)
    }

    /// Parses an optional attribute with `parse`.
    fn value<T>(
        &self,
        attrs: &Attrs,
        key: &'static str,
        parse: impl FnOnce(&str) -> Result<T, Invalid>,
    ) -> Result<Option<T>, ConfigLoadError> {
        let Some(attr) = attrs.get(key) else {
            return Ok(None);
        };
        parse(&attr.value)
            .map(Some)
            .map_err(|invalid| match invalid {
                Invalid::Syntax(expected) => ConfigLoadError::BadValue {
                    at: self.at(attr.pos),
                    element: attrs.element,
                    attribute: key,
                    expected,
                    found: attr.value.clone(),
                },
                Invalid::Range(spec) => ConfigLoadError::OutOfRange {
                    at: self.at(attr.pos),
                    element: attrs.element,
                    attribute: key,
                    found: attr.value.trim().to_owned(),
                    min: spec.min,
                    max: spec.max,
                    unit: spec.unit,
                },
            })
    }

    /// Parses a required attribute with `parse`.
    fn required<T>(
        &self,
        attrs: &Attrs,
        key: &'static str,
        expected: &'static str,
        parse: impl FnOnce(&str) -> Result<T, Invalid>,
    ) -> Result<T, ConfigLoadError> {
        self.value(attrs, key, parse)?
            .ok_or_else(|| ConfigLoadError::MissingAttribute {
                at: self.at(attrs.pos),
                element: attrs.element,
                attribute: key,
                expected,
            })
    }

    fn int(
        &self,
        attrs: &Attrs,
        key: &'static str,
        spec: &'static IntSpec,
    ) -> Result<Option<u64>, ConfigLoadError> {
        self.value(attrs, key, |s| parse_int(s, spec))
    }

    /// `heartbeatMs` and `leaseMs`, the lease defaulting to a multiple of the heartbeat.
    fn timing(
        &self,
        attrs: &Attrs,
        default_heartbeat_ms: u64,
        factor: LeaseFactor,
    ) -> Result<(Duration, Duration), ConfigLoadError> {
        let heartbeat_ms = self
            .int(attrs, "heartbeatMs", &HEARTBEAT_MS)?
            .unwrap_or(default_heartbeat_ms);
        let lease_ms = match self.int(attrs, "leaseMs", &LEASE_MS)? {
            Some(lease) if lease <= heartbeat_ms => {
                return Err(ConfigLoadError::LeaseNotAboveHeartbeat {
                    at: self.at(attrs.pos_of("leaseMs")),
                    element: attrs.element,
                    lease_ms: lease,
                    heartbeat_ms,
                })
            }
            Some(lease) => lease,
            None => lease_ms(heartbeat_ms, factor),
        };
        Ok((
            Duration::from_millis(heartbeat_ms),
            Duration::from_millis(lease_ms),
        ))
    }

    /// `enabled` (default true) and `name` (default `<kind><index>`) with where the name is.
    fn link_common(
        &self,
        attrs: &Attrs,
        index: usize,
    ) -> Result<(bool, String, Location), ConfigLoadError> {
        let enabled = self.value(attrs, "enabled", parse_bool)?.unwrap_or(true);
        let name = self
            .value(attrs, "name", |s| parse_name(s, NAME_SYNTAX))?
            .unwrap_or_else(|| format!("{}{index}", attrs.element));
        let name_at = self.at(attrs.pos_of("name"));
        Ok((enabled, name, name_at))
    }

    fn network(&mut self, root: &Element<'a>) -> Result<NetworkConfig, ConfigLoadError> {
        let attrs = self.attributes("network", root, NETWORK_ATTRS)?;
        let node = self.required(&attrs, "node", NAME_SYNTAX, |s| parse_name(s, NAME_SYNTAX))?;
        let namespace = self.value(&attrs, "namespace", parse_namespace)?;
        let domain = self
            .value(&attrs, "domain", |s| parse_name(s, NAME_SYNTAX))?
            .unwrap_or_else(|| DEFAULT_DOMAIN.to_owned());
        let gateway = self.value(&attrs, "gateway", parse_bool)?;

        let mut links = Vec::new();
        let mut names: Vec<(String, Location)> = Vec::new();
        let mut ports: Vec<(String, String, Location)> = Vec::new();
        // Kinds of the link elements so far, for default names (`<kind><index>`). Disabled
        // links count too, so that switching one off does not rename the others.
        let mut kinds: Vec<String> = Vec::new();
        let mut access: Option<AccessConfig> = None;
        let mut security: Option<(SecurityConfig, Location)> = None;
        while let Some(child) = self.child("network", root)? {
            let kind = child.name().to_owned();
            if kind == "access" {
                if access.is_some() {
                    return Err(ConfigLoadError::DuplicateElement {
                        at: self.at(child.pos()),
                        element: "access",
                    });
                }
                access = Some(self.access(&child)?);
                continue;
            }
            if kind == "security" {
                let at = self.at(child.pos());
                if let Some((_, first)) = &security {
                    return Err(ConfigLoadError::DuplicateSecurity {
                        at,
                        first: first.clone(),
                    });
                }
                security = Some((self.security(&child)?, at));
                continue;
            }
            let index = kinds.iter().filter(|&k| *k == kind).count();
            let parsed = match kind.as_str() {
                "ethernet" => self.ethernet(&child, index)?,
                "shm" => self.shm(&child, index)?,
                "serial" => self.serial(&child, index)?,
                "serialduo" => self.serialduo(&child, index)?,
                "zenoh" => self.zenoh(&child, index)?,
                _ => return Err(self.unknown_element("network", &child, NETWORK_ELEMENTS)),
            };
            kinds.push(kind);
            let name = parsed.link.name().to_owned();
            if let Some((_, first)) = names.iter().find(|(n, _)| *n == name) {
                return Err(ConfigLoadError::DuplicateLinkName {
                    at: parsed.name_at,
                    name,
                    first: first.clone(),
                });
            }
            names.push((name.clone(), parsed.name_at));
            if !parsed.enabled {
                continue;
            }
            for (address, at) in parsed.ports {
                if let Some((_, first_link, first)) = ports.iter().find(|(a, ..)| *a == address) {
                    return Err(ConfigLoadError::SerialPortReused {
                        at,
                        address,
                        first_link: first_link.clone(),
                        first: first.clone(),
                    });
                }
                ports.push((address, name.clone(), at));
            }
            links.push(parsed.link);
        }
        if links.is_empty() {
            return Err(ConfigLoadError::NoLinks {
                at: self.at(root.pos()),
            });
        }
        Ok(NetworkConfig {
            node,
            namespace,
            domain,
            links,
            gateway,
            source: self.source.map(Path::to_path_buf),
            access,
            security: security.map(|(s, _)| s),
        })
    }

    /// A path attribute's value: relative to the network file's folder when relative.
    fn file_path(&self, s: &str) -> Result<std::path::PathBuf, Invalid> {
        let s = s.trim();
        if s.is_empty() {
            return Err(Invalid::Syntax(PATH_SYNTAX));
        }
        let p = std::path::PathBuf::from(s);
        Ok(match self.source.and_then(Path::parent) {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p,
        })
    }

    /// `<security keyFile=".." encrypt="none|radio"/>`; the key file itself is read when the
    /// node opens.
    fn security(&mut self, element: &Element<'a>) -> Result<SecurityConfig, ConfigLoadError> {
        let attrs = self.attributes("security", element, SECURITY_ATTRS)?;
        let path = |s: &str| self.file_path(s);
        let key_file = self.required(&attrs, "keyFile", KEY_FILE_SYNTAX, |s| {
            path(s).map_err(|_| Invalid::Syntax(KEY_FILE_SYNTAX))
        })?;
        let encrypt_radio = self
            .value(&attrs, "encrypt", parse_encrypt)?
            .unwrap_or(false);
        let identity_file = self.value(&attrs, "identityFile", path)?;
        let identities = self.value(&attrs, "identities", path)?;
        self.no_children("security", element)?;
        Ok(SecurityConfig {
            key_file,
            encrypt_radio,
            identity_file,
            identities,
        })
    }

    fn ethernet(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("ethernet", element, ETHERNET_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let defaults = EthernetConfig::default();
        let bind = self
            .value(&attrs, "bind", parse_bind)?
            .unwrap_or(defaults.bind);
        let multicast = self
            .value(&attrs, "multicast", parse_multicast)?
            .unwrap_or(defaults.multicast);
        let interface = self
            .value(&attrs, "interface", |s| {
                s.trim()
                    .parse()
                    .map_err(|_| Invalid::Syntax(INTERFACE_SYNTAX))
            })?
            .unwrap_or(defaults.interface);
        let (heartbeat, lease) = self.timing(&attrs, ETHERNET_HEARTBEAT_MS, ETHERNET_LEASE)?;
        let ttl = self
            .int(&attrs, "ttl", &TTL)?
            .map_or(defaults.ttl, saturate_u32);

        let mut peers = Vec::new();
        while let Some(peer) = self.child("ethernet", element)? {
            if peer.name() != "peer" {
                return Err(self.unknown_element("ethernet", &peer, PEER_ELEMENTS));
            }
            let attrs = self.attributes("peer", &peer, PEER_ATTRS)?;
            peers.push(self.required(&attrs, "address", PEER_SYNTAX, parse_peer)?);
            self.no_children("peer", &peer)?;
        }
        Ok(ParsedLink {
            link: LinkConfig::Ethernet(EthernetConfig {
                name,
                bind,
                multicast,
                interface,
                heartbeat,
                lease,
                ttl,
                peers,
            }),
            enabled,
            name_at,
            ports: Vec::new(),
        })
    }

    /// `<zenoh mode=".." connect=".." listen=".." config=".."/>`.
    fn zenoh(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("zenoh", element, ZENOH_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let mode = self
            .value(&attrs, "mode", parse_zenoh_mode)?
            .unwrap_or_default();
        let connect = self
            .value(&attrs, "connect", parse_zenoh_endpoints)?
            .unwrap_or_default();
        let listen = self
            .value(&attrs, "listen", parse_zenoh_endpoints)?
            .unwrap_or_default();
        let config_file = self.value(&attrs, "config", |s| self.file_path(s))?;
        if mode == ZenohMode::Client && connect.is_empty() && config_file.is_none() {
            return Err(ConfigLoadError::MissingAttribute {
                at: self.at(attrs.pos),
                element: "zenoh",
                attribute: "connect",
                expected: "the endpoint of the router a client reaches the others through, like tcp/10.0.0.1:7447",
            });
        }
        if mode == ZenohMode::Client && !listen.is_empty() {
            return Err(ConfigLoadError::BadValue {
                at: self.at(attrs.pos_of("listen")),
                element: "zenoh",
                attribute: "listen",
                expected:
                    "no listening endpoint: a client only connects (use mode=\"peer\" to listen)",
                found: listen.join(","),
            });
        }
        let (heartbeat, lease) = self.timing(&attrs, ZENOH_HEARTBEAT_MS, ZENOH_LEASE)?;
        self.no_children("zenoh", element)?;
        Ok(ParsedLink {
            link: LinkConfig::Zenoh(ZenohConfig {
                name,
                mode,
                connect,
                listen,
                config_file,
                heartbeat,
                lease,
            }),
            enabled,
            name_at,
            ports: Vec::new(),
        })
    }

    fn shm(&mut self, element: &Element<'a>, index: usize) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("shm", element, SHM_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let service = self
            .value(&attrs, "service", |s| parse_name(s, NAME_SYNTAX))?
            .unwrap_or_else(|| ShmConfig::default().service);
        let (heartbeat, lease) = self.timing(&attrs, SHM_HEARTBEAT_MS, SHM_LEASE)?;
        let wait = self.value(&attrs, "wait", parse_wait)?.unwrap_or_default();
        let max_peers = self
            .int(&attrs, "maxPeers", &MAX_PEERS)?
            .unwrap_or(SHM_MAX_PEERS);
        self.no_children("shm", element)?;
        Ok(ParsedLink {
            link: LinkConfig::Shm(ShmConfig {
                name,
                service,
                heartbeat,
                lease,
                wait,
                max_peers: max_peers as usize, // at most 1024
            }),
            enabled,
            name_at,
            ports: Vec::new(),
        })
    }

    /// `TimeToResend`, `MaxPacketSize` and `MaxMessageQueue`, shared by both serial kinds.
    fn serial_protocol(&self, attrs: &Attrs) -> Result<(Duration, usize, usize), ConfigLoadError> {
        let time_to_resend = self
            .int(attrs, "TimeToResend", &TIME_TO_RESEND)?
            .unwrap_or(SERIAL_TIME_TO_RESEND_MS);
        let max_packet_size = self
            .int(attrs, "MaxPacketSize", &MAX_PACKET_SIZE)?
            .map_or(SERIAL_MAX_PACKET_SIZE, saturate_usize);
        let max_message_queue = self
            .int(attrs, "MaxMessageQueue", &MAX_MESSAGE_QUEUE)?
            .map_or(SERIAL_MAX_MESSAGE_QUEUE, saturate_usize);
        Ok((
            Duration::from_millis(time_to_resend),
            max_packet_size,
            max_message_queue,
        ))
    }

    /// A serial port and its baud rate (`address`/`baudRate`, or the Tx or Rx pair of a
    /// `serialduo`), with where the port was named.
    fn port(
        &self,
        attrs: &Attrs,
        (address_key, baud_key): (&'static str, &'static str),
    ) -> Result<(String, u32, Location), ConfigLoadError> {
        let address = self.required(attrs, address_key, PORT_SYNTAX, parse_port)?;
        let baud_rate = self
            .int(attrs, baud_key, &BAUD_RATE)?
            .map_or(SERIAL_BAUD_RATE, saturate_u32);
        Ok((address, baud_rate, self.at(attrs.pos_of(address_key))))
    }

    fn serial(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("serial", element, SERIAL_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let (address, baud_rate, address_at) = self.port(&attrs, ("address", "baudRate"))?;
        let (time_to_resend, max_packet_size, max_message_queue) = self.serial_protocol(&attrs)?;
        let (heartbeat, lease) = self.timing(&attrs, SERIAL_HEARTBEAT_MS, SERIAL_LEASE)?;
        self.no_children("serial", element)?;
        Ok(ParsedLink {
            ports: vec![(address.clone(), address_at)],
            link: LinkConfig::Serial(SerialConfig {
                name,
                address,
                baud_rate,
                time_to_resend,
                max_packet_size,
                max_message_queue,
                heartbeat,
                lease,
            }),
            enabled,
            name_at,
        })
    }

    fn serialduo(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("serialduo", element, SERIALDUO_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let (address_tx, baud_rate_tx, tx_at) = self.port(&attrs, ("addressTx", "baudRateTx"))?;
        let (address_rx, baud_rate_rx, rx_at) = self.port(&attrs, ("addressRx", "baudRateRx"))?;
        if address_tx == address_rx {
            return Err(ConfigLoadError::SerialDuoSamePort {
                at: rx_at,
                address: address_rx,
            });
        }
        let (time_to_resend, max_packet_size, max_message_queue) = self.serial_protocol(&attrs)?;
        let (heartbeat, lease) = self.timing(&attrs, SERIAL_HEARTBEAT_MS, SERIAL_LEASE)?;
        self.no_children("serialduo", element)?;
        Ok(ParsedLink {
            ports: vec![(address_tx.clone(), tx_at), (address_rx.clone(), rx_at)],
            link: LinkConfig::SerialDuo(SerialDuoConfig {
                name,
                address_tx,
                baud_rate_tx,
                address_rx,
                baud_rate_rx,
                time_to_resend,
                max_packet_size,
                max_message_queue,
                heartbeat,
                lease,
            }),
            enabled,
            name_at,
        })
    }
}

/// `<access>` (see `config::access`): kept apart from the links' parsing.
impl<'a> Parser<'a> {
    fn access(&mut self, element: &Element<'a>) -> Result<AccessConfig, ConfigLoadError> {
        let attrs = self.attributes("access", element, ACCESS_ATTRS)?;
        let mut config = AccessConfig {
            trust_claims: self
                .value(&attrs, "trustClaims", parse_yes_no)?
                .unwrap_or(false),
            ..AccessConfig::default()
        };
        while let Some(child) = self.child("access", element)? {
            let rule = match child.name() {
                "allow" => "allow",
                "deny" => "deny",
                _ => return Err(self.unknown_element("access", &child, ACCESS_ELEMENTS)),
            };
            let attrs = if rule == "allow" {
                self.attributes("allow", &child, ALLOW_ATTRS)?
            } else {
                self.attributes("deny", &child, DENY_ATTRS)?
            };
            let kind = self.required(&attrs, "kind", ACCESS_KIND_SYNTAX, |s| {
                AccessKind::parse(s.trim()).ok_or(Invalid::Syntax(ACCESS_KIND_SYNTAX))
            })?;
            if rule == "deny" {
                config.closed.push(kind);
            } else {
                let pattern = |s: &str| {
                    crate::name::validate_pattern(s.trim())
                        .map(|()| s.trim().to_owned())
                        .map_err(|_| Invalid::Syntax(ACCESS_PATTERN_SYNTAX))
                };
                let item = self
                    .value(&attrs, "item", pattern)?
                    .unwrap_or_else(|| "**".to_owned());
                let from = self.required(&attrs, "from", ACCESS_PATTERN_SYNTAX, pattern)?;
                config.rules.push(AccessRule { kind, item, from });
            }
            self.no_children(rule, &child)?;
        }
        Ok(config)
    }
}

//! The `<access>` element of `network.xml`: which peers may call this node's functions, send
//! to its file sinks, publish what its subscribers receive, and forward other nodes' offers
//! (act as gateways towards it).
//!
//! ```xml
//! <access>
//!   <allow kind="call"    item="rover1/vas/*"              from="ground/*"/>
//!   <allow kind="file"    item="rover1/fpma/plans"         from="ground/fpmo"/>
//!   <allow kind="publish" item="rover1/vas/manual_control" from="ground/fmo"/>
//!   <allow kind="gateway"                                  from="relay"/>
//! </access>
//! ```
//!
//! Without `<access>` everything is open (the zero-configuration demo). With it, each kind the
//! element mentions is **default-deny**: only what an `<allow>` of that kind names passes; the
//! kinds it does not mention stay open. `item` is a name pattern (`*`, `**`) matched against the
//! item's full name (`**` when absent); `from` is a name pattern matched against the peer's
//! `namespace/node` (just `node` for a node without namespace): `ground/*` is every node of
//! namespace `ground`, `**/fmo` every node named `fmo`. A call or file relayed by a gateway
//! comes from the gateway.

use std::path::Path;

use super::ConfigLoadError;
use crate::name;
use crate::xml::LineIndex;

/// What an access rule governs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AccessKind {
    /// Calling a function this node provides (`call`).
    Call,
    /// Sending a file to a sink of this node (`file`).
    File,
    /// Publishing a variable or event that this node's subscribers receive (`publish`).
    Publish,
    /// Declaring offers on behalf of other nodes, as a gateway does (`gateway`); `item` is
    /// ignored.
    Gateway,
}

impl AccessKind {
    /// The `kind` attribute's value.
    pub fn as_str(self) -> &'static str {
        match self {
            AccessKind::Call => "call",
            AccessKind::File => "file",
            AccessKind::Publish => "publish",
            AccessKind::Gateway => "gateway",
        }
    }

    /// Parses the `kind` attribute.
    pub fn parse(s: &str) -> Option<AccessKind> {
        Some(match s {
            "call" => AccessKind::Call,
            "file" => AccessKind::File,
            "publish" => AccessKind::Publish,
            "gateway" => AccessKind::Gateway,
            _ => return None,
        })
    }
}

/// One `<allow kind=".." item=".." from=".."/>`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AccessRule {
    /// What it allows.
    pub kind: AccessKind,
    /// Pattern of the item names it covers (`**` when absent).
    pub item: String,
    /// Pattern of the peers (`namespace/node`) it lets through.
    pub from: String,
}

/// The `<access>` element: its rules, in file order.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AccessConfig {
    /// The `<allow>` rules.
    pub rules: Vec<AccessRule>,
    /// Kinds that are default-deny although no rule allows anything of them
    /// (`<deny kind="..."/>`): a node that accepts no calls at all, say.
    pub closed: Vec<AccessKind>,
    /// `trustClaims="yes"`: the rules may match the `namespace/node` peers *claim*, with no
    /// roster to prove them (`<security identities=..>`). Without it a node with rules and
    /// no roster refuses to open: anyone on its links could name itself what a rule allows.
    pub trust_claims: bool,
}

impl AccessConfig {
    /// Parses an access file: the `<access>` element of `network.xml` as the root of its own
    /// document (what `usal run` writes for a mission node's `<access>`). `source` names the
    /// text in errors.
    ///
    /// # Errors
    /// As [`super::NetworkConfig::parse`], with the line and column of what is wrong.
    pub fn parse(text: &str, source: Option<&Path>) -> Result<Self, ConfigLoadError> {
        let index = LineIndex::new(text);
        super::parser::Parser::new(text, &index, source).access_document()
    }

    /// Reads and parses an access file (see [`AccessConfig::parse`]).
    ///
    /// # Errors
    /// [`ConfigLoadError::Unreadable`] when it cannot be read as text, else as
    /// [`AccessConfig::parse`].
    pub fn load(path: &Path) -> Result<Self, ConfigLoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigLoadError::Unreadable {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, Some(path))
    }

    /// The element as XML, which [`AccessConfig::parse`] reads back as it is.
    pub fn to_xml(&self) -> String {
        let mut out = String::from(if self.trust_claims {
            "<access trustClaims=\"yes\">\n"
        } else {
            "<access>\n"
        });
        for r in &self.rules {
            out.push_str(&format!(
                "  <allow kind=\"{}\" item=\"{}\" from=\"{}\"/>\n",
                r.kind.as_str(),
                escape_attr(&r.item),
                escape_attr(&r.from)
            ));
        }
        for k in &self.closed {
            out.push_str(&format!("  <deny kind=\"{}\"/>\n", k.as_str()));
        }
        out.push_str("</access>\n");
        out
    }

    /// Whether the element says anything about `kind` (then it is default-deny).
    pub fn governs(&self, kind: AccessKind) -> bool {
        self.closed.contains(&kind) || self.rules.iter().any(|r| r.kind == kind)
    }

    /// Whether peer `from` (`namespace/node`, or `node`) may do `kind` on item `item`.
    pub fn allows(&self, kind: AccessKind, item: &str, from: &str) -> bool {
        if !self.governs(kind) {
            return true;
        }
        self.rules.iter().any(|r| {
            r.kind == kind
                && (kind == AccessKind::Gateway || name::matches(&r.item, item))
                && name::matches(&r.from, from)
        })
    }
}

/// `s` fit for a double-quoted XML attribute.
fn escape_attr(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('"', "&quot;")
        .replace('<', "&lt;")
}

/// The name access rules match a peer by: `namespace/node`, or `node` without a namespace.
pub fn peer_path(namespace: &str, node: &str) -> String {
    if namespace.is_empty() {
        node.to_owned()
    } else {
        format!("{namespace}/{node}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rule(kind: AccessKind, item: &str, from: &str) -> AccessRule {
        AccessRule {
            kind,
            item: item.into(),
            from: from.into(),
        }
    }

    #[test]
    fn a_mentioned_kind_is_default_deny_and_the_others_stay_open() {
        let a = AccessConfig {
            rules: vec![
                rule(AccessKind::Call, "rover1/vas/*", "ground/*"),
                rule(AccessKind::Call, "rover1/vas/emergency", "**"),
            ],
            closed: vec![],
            trust_claims: false,
        };
        assert!(a.allows(AccessKind::Call, "rover1/vas/retask", "ground/fmo"));
        assert!(!a.allows(AccessKind::Call, "rover1/vas/retask", "evil/fmo"));
        assert!(!a.allows(AccessKind::Call, "rover1/vas/retask", "fmo"));
        assert!(a.allows(AccessKind::Call, "rover1/vas/emergency", "anyone"));
        assert!(!a.allows(AccessKind::Call, "rover1/fpma/skip", "ground/fmo"));
        // Not mentioned: open.
        assert!(a.allows(AccessKind::File, "rover1/fpma/plans", "evil/x"));
        assert!(a.allows(AccessKind::Publish, "rover1/vas/manual_control", "evil/x"));
        // Closed without a rule.
        let closed = AccessConfig {
            rules: vec![],
            closed: vec![AccessKind::Gateway],
            trust_claims: false,
        };
        assert!(!closed.allows(AccessKind::Gateway, "", "relay"));
        assert!(AccessConfig::default().allows(AccessKind::Gateway, "", "relay"));
    }

    #[test]
    fn an_access_file_reads_back_what_to_xml_wrote_and_errors_name_the_line() {
        let a = AccessConfig {
            rules: vec![
                rule(AccessKind::Call, "rover1/**", "gcs/*"),
                rule(AccessKind::File, "rover1/fpma/plans", "*"),
            ],
            closed: vec![AccessKind::Publish],
            trust_claims: false,
        };
        assert_eq!(AccessConfig::parse(&a.to_xml(), None).unwrap(), a);
        let wrong = AccessConfig::parse(
            "<access>\n  <allow kind=\"fly\" from=\"*\"/>\n</access>",
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(wrong.contains("2:") && wrong.contains("kind"), "{wrong}");
        let root = AccessConfig::parse("<network node=\"x\"/>", None)
            .unwrap_err()
            .to_string();
        assert!(
            root.contains("expected the root element <access>"),
            "{root}"
        );
    }

    #[test]
    fn peers_are_named_namespace_slash_node() {
        assert_eq!(peer_path("ground", "fmo"), "ground/fmo");
        assert_eq!(peer_path("", "fmo"), "fmo");
    }
}

//! The bridge: a marea node that shows every item of its domain to any Zenoh client, as
//! `docs/zenoh.md` fixes it:
//!
//! | marea | Zenoh |
//! |---|---|
//! | variable or event `ns/service/item` of domain `D` | a publication on `usal/D/ns/service/item` |
//! | a value of a type the tools describe | JSON (`application/json`) |
//! | a value of any other type | postcard bytes, encoding `application/octet-stream;postcard;type=<Rust type>;fingerprint=<16 hex digits>` |
//! | a variable's last value | the reply to a `get` on its key (wildcards too) |
//! | function `ns/service/fn` | a `get` on its key: the JSON argument as payload, the JSON result as reply, a `CallError` as an error reply `{"error": kind, "message": ..}` |
//! | a node of the domain | liveliness token `usal/D/@node/<node>` |
//! | function `ns/service/fn` called as Zenoh identity `who` | a `get` on `usal/D/@as/<who>/ns/service/fn` |
//!
//! The bridge relays each call as a gateway does, for its Zenoh caller: marea's `<access>`
//! rules see `zenoh/<who>` for a call under `@as/<who>` (a key only the sessions the router
//! authenticated as `who` may query: [`crate::identity`]), and `zenoh/anonymous` for a call on
//! the plain key; a function a rule keeps from that caller is `Denied` to it.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use marea::protocol::ItemKind;
use marea::sync::lock;
use marea::{CallError, Node, RawSubscription};

use crate::identity;
use serde_json::{json, Value};
use tokio_util::sync::CancellationToken;
use zenoh::bytes::{Encoding, ZBytes};
use zenoh::key_expr::KeyExpr;
use zenoh::qos::CongestionControl;

/// How long a call made for a Zenoh client may take unless its query says
/// (`?timeout_ms=N` in the selector).
pub const DEFAULT_CALL_TIMEOUT: Duration = Duration::from_secs(5);

/// Service name the bridge's items are declared under.
const SERVICE: &str = "zenoh-bridge";

/// A value as the bridge shows it to Zenoh.
#[derive(Clone)]
struct Shown {
    bytes: Vec<u8>,
    encoding: Encoding,
}

/// `bytes` of Rust type `type_name` (fingerprint `fingerprint`): JSON when the tools know the
/// type, postcard otherwise, with an encoding naming the type and its fingerprint.
fn show(type_name: &str, fingerprint: u64, bytes: &[u8]) -> Shown {
    match usal_json::to_json(type_name, bytes) {
        Some(Ok(v)) => Shown {
            bytes: v.to_string().into_bytes(),
            encoding: Encoding::APPLICATION_JSON,
        },
        // Unknown, or bytes that do not decode as their declared type: passed on as they are.
        _ => Shown {
            bytes: bytes.to_vec(),
            encoding: Encoding::APPLICATION_OCTET_STREAM.with_schema(format!(
                "postcard;type={type_name};fingerprint={fingerprint:016x}"
            )),
        },
    }
}

/// The `CallError` as an error reply's JSON.
fn call_error_json(e: &CallError) -> Value {
    let kind = e.kind();
    json!({"error": kind, "message": e.to_string()})
}

/// Shares `node`'s domain with Zenoh through `session` until `cancel`; a Zenoh client may call
/// as one of `identities` (the router proves them: [`identity::restrict_calls_as`]).
///
/// # Errors
/// The bridge's items cannot be declared on the node or on Zenoh.
pub async fn run(
    session: zenoh::Session,
    node: &Node,
    domain: String,
    identities: Vec<String>,
    cancel: CancellationToken,
) -> anyhow::Result<()> {
    let svc = node
        .service(SERVICE)
        .context("declaring the bridge service")?;
    let variables = svc
        .subscribe_raw(ItemKind::Variable, "**")
        .context("subscribing to every variable")?;
    let events = svc
        .subscribe_raw(ItemKind::Event, "**")
        .context("subscribing to every event")?;
    let prefix = format!("usal/{domain}");
    let last: Arc<Mutex<BTreeMap<String, Shown>>> = Arc::default();
    let queryable = session
        .declare_queryable(format!("{prefix}/**"))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("declaring the bridge's queryable")?;
    // `@as` is verbatim: `**` above does not reach it.
    let queryable_as = session
        .declare_queryable(format!("{prefix}/{}/*/**", identity::AS))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("declaring the bridge's queryable for calls made as an identity")?;
    let identities: Arc<Vec<String>> = Arc::new(identities);

    let forward = |sub: RawSubscription, is_event: bool| {
        let session = session.clone();
        let prefix = prefix.clone();
        let last = last.clone();
        let cancel = cancel.clone();
        async move {
            loop {
                let v = tokio::select! {
                    _ = cancel.cancelled() => break,
                    v = sub.recv() => match v { Ok(v) => v, Err(_) => break },
                };
                let shown = show(&v.type_name, v.fingerprint, &v.payload);
                if !is_event {
                    lock(&last).insert(v.name.clone(), shown.clone());
                }
                // Events wait for a congested router (each one counts); variables give way to
                // their next value.
                let cc = if is_event {
                    CongestionControl::Block
                } else {
                    CongestionControl::Drop
                };
                let put = session
                    .put(format!("{prefix}/{}", v.name), shown.bytes)
                    .encoding(shown.encoding)
                    .congestion_control(cc)
                    .await;
                if let Err(e) = put {
                    tracing::debug!(item = %v.name, error = %e, "not published on Zenoh");
                }
            }
        }
    };
    let mut tasks = tokio::task::JoinSet::new();
    tasks.spawn(forward(variables, false));
    tasks.spawn(forward(events, true));
    let mut tokens = NodeTokens::default();
    // The tokens follow the nodes every half second (at once the first time), not per query.
    let mut resync = tokio::time::interval(Duration::from_millis(500));
    resync.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let query = tokio::select! {
            _ = cancel.cancelled() => break,
            _ = resync.tick() => {
                tokens.sync(&session, node, &domain).await;
                continue;
            }
            q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
            q = queryable_as.recv_async() => match q { Ok(q) => q, Err(_) => break },
        };
        let svc = svc.clone();
        let last = last.clone();
        let prefix = prefix.clone();
        let identities = identities.clone();
        tasks.spawn(async move { answer(query, &svc, &last, &prefix, &identities).await });
    }
    tasks.shutdown().await;
    Ok(())
}

/// Answers a `get`: the last values of the variables it matches; on one exact name that is no
/// variable, a call of that function for the Zenoh caller the key names (see
/// [`caller_and_item`]).
async fn answer(
    query: zenoh::query::Query,
    svc: &marea::Service,
    last: &Mutex<BTreeMap<String, Shown>>,
    prefix: &str,
    identities: &[String],
) {
    let asked = query.key_expr().clone();
    let Some((caller, wanted)) = caller_and_item(asked.as_str(), prefix) else {
        return;
    };
    // What the replies' keys start with: `usal/D`, or `usal/D/@as/<caller>`.
    let space = &asked.as_str()[..asked.as_str().len() - wanted.len() - 1];
    let matching: Vec<(String, Shown)> = lock(last)
        .iter()
        .filter(|(name, _)| {
            KeyExpr::try_from(format!("{space}/{name}")).is_ok_and(|k| asked.intersects(&k))
        })
        .map(|(n, s)| (n.clone(), s.clone()))
        .collect();
    let exact = !asked.as_str().contains('*');
    if !matching.is_empty() || !exact {
        for (name, shown) in matching {
            let _ = query
                .reply(format!("{space}/{name}"), shown.bytes)
                .encoding(shown.encoding)
                .await;
        }
        return;
    }
    let timeout = query
        .parameters()
        .get("timeout_ms")
        .and_then(|t| t.parse().ok())
        .map_or(DEFAULT_CALL_TIMEOUT, Duration::from_millis);
    let reply = if caller == identity::ANONYMOUS || identities.iter().any(|i| i == caller) {
        call(svc, caller, wanted, query.payload(), timeout).await
    } else {
        Err(json!({"error": "denied", "message": format!(
            "{caller} is no identity of this router (its users and --identity names)"
        )}))
    };
    let _ = match reply {
        Ok(v) => {
            query
                .reply(asked.clone(), v.to_string())
                .encoding(Encoding::APPLICATION_JSON)
                .await
        }
        Err(v) => {
            query
                .reply_err(v.to_string())
                .encoding(Encoding::APPLICATION_JSON)
                .await
        }
    };
}

/// Who a query on `asked` is from, and the item name (or pattern) it asks about: under
/// `<prefix>/@as/<identity>/` that identity, which the router proved ([`identity`]);
/// elsewhere under `<prefix>/` anyone ([`identity::ANONYMOUS`]).
fn caller_and_item<'k>(asked: &'k str, prefix: &str) -> Option<(&'k str, &'k str)> {
    let rest = asked.strip_prefix(prefix)?.strip_prefix('/')?;
    match rest
        .strip_prefix(identity::AS)
        .and_then(|r| r.strip_prefix('/'))
    {
        Some(r) => r.split_once('/'),
        None => Some((identity::ANONYMOUS, rest)),
    }
}

/// Calls function `name` for Zenoh client `caller` with the JSON argument in `payload` (none:
/// `null`); the JSON result, or the error as JSON.
async fn call(
    svc: &marea::Service,
    caller: &str,
    name: &str,
    payload: Option<&ZBytes>,
    timeout: Duration,
) -> Result<Value, Value> {
    let arg: Value = match payload {
        None => Value::Null,
        Some(p) => serde_json::from_slice(&p.to_bytes())
            .map_err(|e| json!({"error": "bad_argument", "message": format!("the argument is not JSON: {e}")}))?,
    };
    let Some(ty) = svc.function_type(name) else {
        return Err(call_error_json(&CallError::NoProvider {
            name: name.to_owned(),
        }));
    };
    let (a, r) = usal_json::split_fn(&ty.name).ok_or_else(
        || json!({"error": "type_mismatch", "message": format!("unexpected function type {}", ty.name)}),
    )?;
    let bytes = usal_json::from_json(a, &arg)
        .map_err(|e| json!({"error": "bad_argument", "message": e}))?;
    let out = svc
        .call_raw_for(identity::NAMESPACE, caller, name, bytes, timeout)
        .await
        .map_err(|e| call_error_json(&e))?;
    match usal_json::to_json(r, &out) {
        Some(Ok(v)) => Ok(v),
        _ => Err(
            json!({"error": "codec", "message": format!("the result's type {r} cannot be shown as JSON")}),
        ),
    }
}

/// A liveliness token `usal/<domain>/@node/<name>` for each node of the domain the bridge
/// knows (itself, its peers and the nodes whose offers gateways forward to it), dropped when
/// the node goes.
#[derive(Default)]
struct NodeTokens(HashMap<String, zenoh::liveliness::LivelinessToken>);

impl NodeTokens {
    async fn sync(&mut self, session: &zenoh::Session, node: &Node, domain: &str) {
        let mut alive = node.node_names();
        alive.push(node.name().to_owned());
        self.0.retain(|n, _| alive.contains(n));
        for name in alive {
            if self.0.contains_key(&name) {
                continue;
            }
            match session
                .liveliness()
                .declare_token(format!("usal/{domain}/@node/{name}"))
                .await
            {
                Ok(t) => {
                    self.0.insert(name, t);
                }
                Err(e) => tracing::debug!(node = %name, error = %e, "no liveliness token"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_key_names_its_caller_and_item() {
        let p = "usal/d";
        assert_eq!(
            caller_and_item("usal/d/rover1/vas/position", p),
            Some((identity::ANONYMOUS, "rover1/vas/position"))
        );
        assert_eq!(
            caller_and_item("usal/d/@as/pilot/rover1/vas/change_state", p),
            Some(("pilot", "rover1/vas/change_state"))
        );
        assert_eq!(caller_and_item("usal/d/@as/pilot", p), None);
        assert_eq!(caller_and_item("usal/other/x", p), None);
        assert_eq!(caller_and_item("usal/dx/x", p), None);
    }

    #[test]
    fn a_value_of_an_unknown_type_names_its_type_and_fingerprint() {
        let shown = show("my_crate::Odd", 0x0123_4567_89ab_cdef, &[1, 2, 3]);
        assert_eq!(shown.bytes, [1, 2, 3]);
        assert_eq!(
            shown.encoding.to_string(),
            "application/octet-stream;postcard;type=my_crate::Odd;fingerprint=0123456789abcdef"
        );
        let known = show("f64", 0, &postcard::to_allocvec(&2.5f64).unwrap());
        assert_eq!(known.encoding, Encoding::APPLICATION_JSON);
        assert_eq!(known.bytes, b"2.5");
    }
}

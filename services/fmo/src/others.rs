//! The vehicle's other services: a user's own service beside the VAS (`<service>` in a
//! mission) shows in the pilot's station with no change to the station. Every variable that a
//! service other than the built-ins publishes in a followed vehicle's namespace is found in the
//! catalog, subscribed to by its exact name, and shown with its latest value: as JSON where
//! `usal` knows its type (USAL's types, the plain Rust ones), else as its size.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use marea::protocol::ItemKind;
use marea::ItemRole;
use serde_json::json;

use crate::Shared;

/// How often the catalog is read for new variables.
const DISCOVER_EVERY: Duration = Duration::from_secs(2);

/// The services whose items the station shows in their own panels, or not at all.
const SHOWN_ELSEWHERE: &[&str] = &["vas", "fpma", "links", "fleet", "fmo", "fpmo", "station"];

/// The namespace of the vehicle whose VAS is at `prefix` (`rover1/vas` -> `rover1`); `None`
/// for a VAS without one (its node's other services cannot be told from anyone else's).
fn namespace_of(prefix: &str) -> Option<&str> {
    prefix.strip_suffix("/vas").filter(|ns| !ns.is_empty())
}

/// A variable's value as the page shows it.
fn shown(type_name: &str, bytes: &[u8]) -> serde_json::Value {
    match usal_json::to_json(type_name, bytes) {
        Some(Ok(v)) => v,
        Some(Err(e)) => json!({"undecodable": e}),
        None => json!({"bytes": bytes.len(), "note": "a type the station does not know"}),
    }
}

/// Follows the other services' variables of every vehicle heard of, until the station stops.
pub(crate) async fn follow_other_services(me: Arc<Shared>) {
    let mut followed: HashSet<String> = HashSet::new();
    loop {
        tokio::select! {
            () = tokio::time::sleep(DISCOVER_EVERY) => {}
            () = me.live.cancel.cancelled() => return,
        }
        let vehicles = me.station().vehicle_ids();
        for node in me.svc.catalog().nodes.into_iter().filter(|n| !n.local) {
            for svc in node.services {
                if SHOWN_ELSEWHERE.contains(&svc.name.as_str()) {
                    continue;
                }
                for item in svc.items {
                    if item.kind != ItemKind::Variable || item.role != ItemRole::Offer {
                        continue;
                    }
                    let Some(vehicle) = vehicles.iter().find(|v| {
                        namespace_of(v).is_some_and(|ns| {
                            item.name
                                .strip_prefix(ns)
                                .is_some_and(|r| r.starts_with('/'))
                        })
                    }) else {
                        continue;
                    };
                    if !followed.insert(item.name.clone()) {
                        continue;
                    }
                    follow_one(&me, vehicle.clone(), item.name);
                }
            }
        }
    }
}

fn follow_one(me: &Arc<Shared>, vehicle: String, name: String) {
    let sub = match me.svc.subscribe_raw(ItemKind::Variable, &name) {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!("cannot follow {name}: {e}");
            return;
        }
    };
    let me = me.clone();
    let cancel = me.live.cancel.clone();
    me.live.tasks.clone().spawn(async move {
        loop {
            let v = tokio::select! {
                v = sub.recv() => v,
                () = cancel.cancelled() => return,
            };
            let Ok(v) = v else { return };
            let value = shown(&v.type_name, &v.payload);
            me.station()
                .update_other(&vehicle, &v.name, &v.type_name, value, Instant::now());
            me.live.changed.notify_waiters();
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vehicle_is_known_by_its_vas_namespace_and_values_are_shown_as_json() {
        assert_eq!(namespace_of("rover1/vas"), Some("rover1"));
        assert_eq!(namespace_of("fleet/a/vas"), Some("fleet/a"));
        assert_eq!(namespace_of("vas"), None);
        let bytes = postcard::to_stdvec(&42.5f64).unwrap();
        assert_eq!(shown("f64", &bytes), json!(42.5));
        assert_eq!(shown("my::Secret", &[1, 2, 3])["bytes"], 3);
        assert!(shown("f64", &[1]).get("undecodable").is_some());
    }
}

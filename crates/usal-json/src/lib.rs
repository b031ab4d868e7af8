//! The payload types the `usal` tools and the Zenoh bridge can decode and encode by name:
//! USAL's message types and the plain Rust types, keyed by `std::any::type_name` as
//! declarations carry it. A value of any of them is shown to people and to Zenoh clients as
//! JSON; anything else stays postcard bytes.

use marea::protocol::ItemKind;
use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;

/// Decodes postcard bytes of a known type into JSON.
type Decode = fn(&[u8]) -> Result<Value, String>;
/// Encodes JSON into postcard bytes of a known type.
type Encode = fn(&Value) -> Result<Vec<u8>, String>;

/// Declares a publisher of a known type on a service (for `usal replay`).
type MakeReplayer = fn(&marea::Service, ItemKind, &str) -> Result<Replayer, String>;

/// Publishes postcard bytes of a known type as the variable or event it was declared as.
pub type Replayer = Box<dyn Fn(&[u8]) -> Result<(), String> + Send + Sync>;

struct Known {
    name: String,
    decode: Decode,
    encode: Encode,
    replayer: MakeReplayer,
}

fn decode<T: DeserializeOwned + Serialize>(b: &[u8]) -> Result<Value, String> {
    let v: T = postcard::from_bytes(b).map_err(|e| e.to_string())?;
    serde_json::to_value(v).map_err(|e| e.to_string())
}

fn encode<T: DeserializeOwned + Serialize>(v: &Value) -> Result<Vec<u8>, String> {
    let t: T = serde_json::from_value(v.clone()).map_err(|e| e.to_string())?;
    postcard::to_stdvec(&t).map_err(|e| e.to_string())
}

fn make_replayer<T: marea::Payload>(
    svc: &marea::Service,
    kind: ItemKind,
    item: &str,
) -> Result<Replayer, String> {
    let value = |b: &[u8]| postcard::from_bytes::<T>(b).map_err(|e| e.to_string());
    match kind {
        ItemKind::Variable => {
            let v = svc.publish_variable::<T>(item).map_err(|e| e.to_string())?;
            Ok(Box::new(move |b| {
                v.set(&value(b)?).map_err(|e| e.to_string())
            }))
        }
        ItemKind::Event => {
            let e = svc.publish_event::<T>(item).map_err(|e| e.to_string())?;
            // Raised in order without waiting for acknowledgements: a replay keeps its pace.
            Ok(Box::new(move |b| {
                e.raise_nowait(&value(b)?)
                    .map(drop)
                    .map_err(|e| e.to_string())
            }))
        }
        other => Err(format!("cannot replay a {}", other.as_str())),
    }
}

macro_rules! known {
    ($($t:ty),* $(,)?) => {
        vec![$(Known {
            name: std::any::type_name::<$t>().to_owned(),
            decode: decode::<$t>,
            encode: encode::<$t>,
            replayer: make_replayer::<$t>,
        }),*]
    };
}

fn registry() -> Vec<Known> {
    use usal_types::*;
    known![
        Position,
        Attitude,
        Speeds,
        Home,
        PoiDetection,
        VehicleKind,
        FlightState,
        Vec<FlightState>,
        AutopilotStatus,
        WaypointKind,
        Waypoint,
        Vec<Waypoint>,
        WaypointReached,
        QueueStatus,
        Severity,
        Alarm,
        ManualControl,
        ManualCommand,
        StateChangeRequest,
        StateChangeReply,
        StateChanged,
        MissionTime,
        Battery,
        AltRef,
        VehicleCommand,
        DirectedTarget,
        CommandReply,
        AllowedChanges,
        CommandRecord,
        MissionChanged,
        ReplayStatus,
        ParamValue,
        Vec<ParamValue>,
        (u16, u16),
        Failsafe,
        FailsafeKind,
        StationHeartbeat,
        Fence,
        Option<Fence>,
        FenceAction,
        flightplan::api::Readiness,
        marea::LinkHealth,
        flightplan::api::Progress,
        flightplan::api::PlanState,
        flightplan::api::PlanEvent,
        flightplan::api::PlanGeometry,
        flightplan::api::PlanLoaded,
        flightplan::api::PlanRejected,
        flightplan::api::CommandAck,
        flightplan::api::ModifyLeg,
        flightplan::api::SetVar,
        flightplan::api::HoldHereArgs,
        flightplan::api::Retask,
        flightplan::fleet_api::FleetStatus,
        flightplan::fleet_api::PointEdit,
        (),
        bool,
        u8,
        u16,
        u32,
        u64,
        i8,
        i16,
        i32,
        i64,
        f32,
        f64,
        String,
        Vec<u8>,
        Vec<String>,
        Option<String>,
    ]
}

/// The registry, built once: `usal echo` and the FMo decode every sample through it.
fn find(type_name: &str) -> Option<&'static Known> {
    static REGISTRY: std::sync::OnceLock<Vec<Known>> = std::sync::OnceLock::new();
    REGISTRY
        .get_or_init(registry)
        .iter()
        .find(|k| k.name == type_name)
}

/// Whether the tools can show and write values of `type_name`: a payload type of the
/// registry, or a function type `fn(A) -> R` whose argument and result both are.
pub fn knows(type_name: &str) -> bool {
    let known = |t: &str| find(t).is_some();
    match split_fn(type_name) {
        Some((args, ret)) => known(args) && known(ret),
        None => known(type_name),
    }
}

/// Decodes `bytes` of type `type_name` into JSON; `None` when the type is unknown to the tool.
pub fn to_json(type_name: &str, bytes: &[u8]) -> Option<Result<Value, String>> {
    find(type_name).map(|k| (k.decode)(bytes))
}

/// Encodes JSON as `type_name`.
///
/// # Errors
/// The type is unknown to the tool, or the JSON does not fit it.
pub fn from_json(type_name: &str, v: &Value) -> Result<Vec<u8>, String> {
    let k = find(type_name).ok_or_else(|| format!("type {type_name} is not known to usal"))?;
    (k.encode)(v).map_err(|e| format!("arguments do not fit {type_name}: {e}"))
}

/// A publisher of `item` on `svc` for values of `type_name` (postcard bytes), as a `kind`.
///
/// # Errors
/// The type is unknown to the tool, or the item cannot be declared.
pub fn replayer(
    type_name: &str,
    svc: &marea::Service,
    kind: ItemKind,
    item: &str,
) -> Result<Replayer, String> {
    let k = find(type_name).ok_or_else(|| format!("type {type_name} is not known to usal"))?;
    (k.replayer)(svc, kind, item)
}

/// Splits a function's declared type `fn(A) -> R` into `A` and `R`.
pub fn split_fn(ty: &str) -> Option<(&str, &str)> {
    let inner = ty.strip_prefix("fn(")?;
    let (args, ret) = inner.rsplit_once(") -> ")?;
    Some((args, ret))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_types_round_trip_and_unknown_ones_say_so() {
        let p = usal_types::Position {
            lat: 41.0,
            lon: 1.9,
            alt: 3.0,
            heading: 90.0,
            speed: 1.5,
            alt_rel: 2.0,
        };
        let bytes = postcard::to_stdvec(&p).unwrap();
        let json = to_json(std::any::type_name::<usal_types::Position>(), &bytes)
            .unwrap()
            .unwrap();
        assert_eq!(json["lat"], 41.0);
        let back = from_json(std::any::type_name::<usal_types::Position>(), &json).unwrap();
        assert_eq!(back, bytes);
        assert!(to_json("my::Secret", &bytes).is_none());
        assert!(from_json("u64", &serde_json::json!("x")).is_err());
        // The VAS's commands as `usal call rover1/vas/command '"ARM"'` writes them.
        let name = std::any::type_name::<usal_types::VehicleCommand>();
        let arm = from_json(name, &serde_json::json!("ARM")).unwrap();
        assert_eq!(
            postcard::from_bytes::<usal_types::VehicleCommand>(&arm).unwrap(),
            usal_types::VehicleCommand::Arm
        );
        let directed =
            serde_json::json!({"DIRECTED": {"alt": 30.0, "speed": 5.0, "bearing": 90.0}});
        let bytes = from_json(name, &directed).unwrap();
        assert_eq!(to_json(name, &bytes).unwrap().unwrap(), directed);
        // `usal call rover1/vas/allowed_states` answers a list of states.
        let states = vec![
            usal_types::FlightState::Parking,
            usal_types::FlightState::Manual,
        ];
        let bytes = postcard::to_stdvec(&states).unwrap();
        let json = to_json(
            std::any::type_name::<Vec<usal_types::FlightState>>(),
            &bytes,
        )
        .expect("a known type")
        .unwrap();
        assert_eq!(json, serde_json::json!(["PARKING", "MANUAL"]));
        assert_eq!(
            split_fn("fn(u64) -> alloc::string::String"),
            Some(("u64", "alloc::string::String"))
        );
        // Every item type the built-in services declared in a rover mission (`usal list`).
        for t in [
            "fn(()) -> alloc::vec::Vec<usal_types::FlightState>",
            "fn(()) -> flightplan::api::PlanGeometry",
            "fn(alloc::string::String) -> flightplan::api::PlanLoaded",
            "fn(alloc::vec::Vec<usal_types::Waypoint>) -> usal_types::QueueStatus",
            "fn(bool) -> flightplan::api::CommandAck",
            "fn(core::option::Option<alloc::string::String>) -> flightplan::api::CommandAck",
            "fn(core::option::Option<usal_types::safety::Fence>) -> alloc::string::String",
            "fn(flightplan::api::HoldHereArgs) -> flightplan::api::CommandAck",
            "fn(flightplan::api::ModifyLeg) -> flightplan::api::CommandAck",
            "fn(flightplan::api::Retask) -> flightplan::api::CommandAck",
            "fn(flightplan::api::SetVar) -> flightplan::api::CommandAck",
            "fn(usal_types::StateChangeRequest) -> usal_types::StateChangeReply",
            "fn(usal_types::VehicleCommand) -> usal_types::CommandReply",
            "usal_types::safety::Failsafe",
            "usal_types::safety::StationHeartbeat",
            "usal_types::MissionChanged",
            "usal_types::ManualCommand",
            "usal_types::AllowedChanges",
            "marea::node::health::LinkHealth",
        ] {
            assert!(knows(t), "{t}");
        }
        assert!(!knows("fn(my::Secret) -> u64"));
        assert!(!knows("my::Secret"));
    }
}

//! # marea
//!
//! A MAREA-like middleware: independent processes exchange **variables, events, remote
//! invocations and files**, discovering each other over the links of their `network.xml`.
//!
//! ## Layers, bottom to top
//!
//! A module uses (`use crate::…`, paths in code) only modules of its own row or of the rows
//! above it; `tests/layering.rs` checks this, with the same table.
//!
//! | layer | what |
//! |---|---|
//! | [`sync`], [`name`], [`typeinfo`], [`process`], [`xml`] | utilities: the poison-ignoring lock, names and patterns, type fingerprints, the process's shutdown signal, reading XML with line and column positions (for `network.xml` and the services' files) |
//! | [`protocol`] | the wire messages (Hello, Heartbeat, declarations, Var, Event, Call, Reply, File*) |
//! | [`codec`] | their bytes: postcard messages, varints |
//! | [`link`] | moving messages over a medium in two classes, fast and safe: [`link::udp`], [`link::serial`], `link::shm` (cargo feature `shm`, on by default), each with its own framing; the ARQ ([`link::arq`]) and the bounded newest-wins queue ([`link::coalesce`]) they share; the domain-key seal and replay window every link applies when keyed, and the seal of a pair's keys the datagram links apply between nodes that proved their identities ([`link::auth`]) |
//! | [`config`], [`identity`] | `network.xml` → [`NetworkConfig`] (names link options); per-node identity keys, the domain's roster of which key owns which namespaces and node names and may act as a gateway, and the key agreement that gives each proven pair its keys |
//! | `node` | each primitive's sending and receiving side by side (`variables`, `events`, `calls`, `files`; `data`: the receive path variables and events share), `declarations` and `routes` (routing by interest), discovery, dispatch, flow, policy, gateway forwarding |
//! | [`api`] | [`Node`], the typed handles, [`IService`]; re-exports the node's public types ([`CallError`], [`ReceivedFile`], …) |
//! | `fuzzing` | (feature `fuzzing` only) structure-aware input generators and harnesses for `fuzz/` and `tests/structured_fuzz.rs` |
//!
//! ## Concepts
//!
//! A process opens one [`Node`]; services declare items through a [`Service`]. Names are
//! `namespace/service/item`; subscriptions may use `*` (one segment) and `**` (any number).
//! Every declaration carries a type fingerprint: a subscriber expecting another type gets
//! [`RecvError::TypeMismatch`], never garbage. A service's catalogue of typed item handles
//! ([`VariableItem`], [`EventItem`], [`FunctionItem`]: a name and its type together) keeps its
//! subscribers, callers and providers from pairing a name with the wrong type in the first place.
//!
//! ## One example per primitive
//!
//! Variables (best effort, newest value wins, late joiners served at once):
//! ```no_run
//! # async fn f() -> Result<(), Box<dyn std::error::Error>> {
//! let node = marea::Node::open(&marea::NetworkConfig::ethernet_loopback("air")).await?;
//! let vas = node.service("vas")?;
//! let speed = vas.publish_variable::<f32>("speed")?;
//! speed.set(&1.5)?;
//! let sub = vas.subscribe_variable::<f32>("**/vas/speed")?;
//! println!("{}", sub.recv().await?.value);
//! # Ok(()) }
//! ```
//! Events (every subscriber, exactly once, in order; the report says who acknowledged):
//! ```no_run
//! # async fn f(vas: marea::Service) -> Result<(), Box<dyn std::error::Error>> {
//! let alarm = vas.publish_event::<String>("alarm")?;
//! let report = alarm.raise(&"battery low".to_owned()).await?;
//! assert!(report.all_acknowledged());
//! # Ok(()) }
//! ```
//! Functions (deadline; errors: no provider, timeout, remote error, link lost):
//! ```no_run
//! # async fn f(vas: marea::Service) -> Result<(), Box<dyn std::error::Error>> {
//! let _p = vas.provide_function("double", |x: u64| async move { Ok::<u64, String>(2 * x) })?;
//! let double = vas.function::<u64, u64>("vas/double")?;
//! let four = double.call(&2, std::time::Duration::from_secs(1)).await?;
//! # Ok(()) }
//! ```
//! Files (chunked, verified, atomic, resumable, with progress):
//! ```no_run
//! # async fn f(vas: marea::Service) -> Result<(), Box<dyn std::error::Error>> {
//! // Stored under the user's state directory (`$XDG_STATE_HOME/usal/sinks/<name>`), with the
//! // default caps; `file_sink("plans", dir)` names the directory instead.
//! let sink = vas.file_sink_with("plans", marea::FileSinkOptions::default())?;
//! let report = vas
//!     .send_file("plan.xml", "vas/plans", marea::SendFileOptions::default())
//!     .wait()
//!     .await?;
//! let received = sink.recv().await?;
//! # Ok(()) }
//! ```
//! Runnable versions: `middleware/examples/` (`cargo run -p marea --example variable`, `event`,
//! `function`, `file`, `list`, `demo`).
#![warn(missing_docs)]

pub mod api;
pub mod codec;
pub mod config;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
pub mod identity;
pub mod link;
pub mod name;
pub(crate) mod node;
pub mod process;
pub mod protocol;
pub mod sync;
pub mod typeinfo;
pub mod xml;

pub use api::*;
pub use config::NetworkConfig;
pub use node::health::LinkHealth;

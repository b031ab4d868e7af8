//! The public API: [`Node`], the typed handles of the four primitives, the typed item handles
//! (an item's name and type together: [`VariableItem`], [`EventItem`], [`FunctionItem`]), and
//! [`IService`].

mod blob;
mod errors;
mod event;
mod file;
mod function;
mod item;
mod node;
mod publisher;
mod raw;
mod service;
mod shared_str;
mod subscription;
mod variable;

pub use blob::{Blob, BlobLoan};
pub use errors::{DeclareError, NodeOpenError, RecvError};
pub use event::{
    Event, EventLoan, EventStream, PendingRaise, RaiseReport, StreamError, STREAM_WINDOW,
    STREAM_WINDOW_BYTES,
};
pub use file::{FileSink, FileTransfer};
pub use function::{Function, FunctionProvider};
pub use item::{EventItem, FunctionItem, VariableItem};
pub use node::{Catalog, ItemDescription, ItemRole, Node, NodeDescription, PeerInfo, PeerTrust};
pub use raw::{RawSubscription, RawValue};
pub use service::{IService, Service, ServiceDescription, ServiceError};
pub use shared_str::SharedStr;
pub use subscription::{CallbackSubscription, EventSubscriber, Subscription, VariableSubscriber};
pub use variable::{Sample, Variable, VariableLoan};

pub use crate::node::calls::{CallError, Caller};
pub use crate::node::data::PublishError;
pub use crate::node::files::{
    FileCheck, FileCheckFuture, FileProgress, FileReport, FileSendError, FileSinkOptions,
    FileSinkStats, FileToCheck, ReceivedFile, SendFileOptions,
};
pub use crate::node::gateway::ForwardedItem;
pub use crate::node::mailbox::TypeMismatch;
pub use crate::node::policy::RefusalReport;
pub use crate::process::state_dir;

/// Payload types: anything serde can encode, shared between processes.
pub trait Payload: serde::Serialize + serde::de::DeserializeOwned + Send + Sync + 'static {}
impl<T: serde::Serialize + serde::de::DeserializeOwned + Send + Sync + 'static> Payload for T {}

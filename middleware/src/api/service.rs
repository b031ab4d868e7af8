//! [`IService`] (the USAL service interface) and [`Service`], the context a service declares
//! its items through.

use std::path::PathBuf;
use std::sync::{Arc, Mutex, Weak};

use serde::{Deserialize, Serialize};

use super::errors::{DeclareError, RecvError};
use super::event::Event;
use super::file::{FileSink, FileTransfer};
use super::function::{Function, FunctionProvider};
use super::node::ItemDescription;
use super::publisher::Publisher;
use super::subscription::{CallbackSubscription, EventSubscriber, VariableSubscriber};
use super::variable::{decode_delivery, Sample, Variable};
use super::Payload;
use crate::name;
use crate::node::files::SendFileOptions;
use crate::node::files::{FileSinkOptions, SinkMailbox, SinkState};
use crate::node::mailbox::Mailbox;
use crate::node::{BoxFuture, LocalInterest, LocalOffer, NodeInner, OfferRole};
use crate::protocol::{Declaration, ItemKind};
use crate::typeinfo::TypeInfo;

/// A USAL service, hosted by a [`crate::Node`] (the seed's `IService`).
#[async_trait::async_trait]
pub trait IService: Send + 'static {
    /// The service's name (the middle segment of its items' names).
    fn name(&self) -> &str;
    /// Declares the service's items through `ctx` and starts its work (spawn loops with
    /// [`Service::spawn`] so they stop with the node).
    async fn start(&mut self, ctx: Service) -> Result<(), ServiceError>;
    /// Called once at node shutdown.
    async fn stop(&mut self) -> Result<(), ServiceError> {
        Ok(())
    }
}

/// A service failed to start or stop.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// Declaring an item failed.
    #[error(transparent)]
    Declare(#[from] DeclareError),
    /// The service's own failure.
    #[error("{0}")]
    Failed(String),
}

/// A service with its items, for listings.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ServiceDescription {
    /// Service name.
    pub name: String,
    /// What it publishes, subscribes, provides and calls.
    pub items: Vec<ItemDescription>,
}

/// Withdraws a declaration when the last handle to it is dropped.
pub(crate) struct Declared {
    pub node: Weak<NodeInner>,
    pub id: u32,
    /// The service an item belongs to stays declared while any of its items lives.
    pub(crate) _owner: Option<Arc<ServiceInner>>,
}

impl Drop for Declared {
    fn drop(&mut self) {
        if let Some(n) = self.node.upgrade() {
            n.withdraw(self.id);
        }
    }
}

pub(crate) struct ServiceInner {
    node: Arc<NodeInner>,
    name: Arc<str>,
    _declared: Declared,
    id: u32,
}

/// A service's context: declares its items (`namespace/service/item`), spawns its tasks.
/// Cloning is cheap; the service is withdrawn when the last clone and the last of its items
/// are dropped.
#[derive(Clone)]
pub struct Service {
    inner: Arc<ServiceInner>,
}

impl Service {
    pub(crate) fn create(node: Arc<NodeInner>, name: &str) -> Result<Self, DeclareError> {
        name::validate_name(name)?;
        if node.cancel.is_cancelled() {
            return Err(DeclareError::Closed);
        }
        let id = node.local.fresh_id();
        node.local.services.insert(id, name.into());
        node.declare(
            Declaration::Service {
                id,
                name: name.to_owned(),
            },
            None,
        );
        Ok(Service {
            inner: Arc::new(ServiceInner {
                _declared: Declared {
                    node: Arc::downgrade(&node),
                    id,
                    _owner: None,
                },
                node,
                name: name.into(),
                id,
            }),
        })
    }

    pub(super) fn node(&self) -> &Arc<NodeInner> {
        &self.inner.node
    }

    /// Everything its node knows: itself and every peer, with services and items (as
    /// [`crate::Node::catalog`]), for a service that discovers what to follow.
    pub fn catalog(&self) -> super::node::Catalog {
        super::node::catalog_of(&self.inner.node)
    }

    /// The service name.
    pub fn name(&self) -> &str {
        &self.inner.name
    }

    /// The name of this node.
    pub fn node_name(&self) -> &str {
        &self.inner.node.me.name
    }

    /// The full name of one of this service's items: `namespace/service/item`.
    pub fn full_name(&self, item: &str) -> String {
        name::join(
            self.inner.node.me.namespace.as_deref(),
            &self.inner.name,
            item,
        )
    }

    fn offer(
        &self,
        item: &str,
        kind: ItemKind,
        ty: TypeInfo,
        role: OfferRole,
    ) -> Result<(Arc<LocalOffer>, Declared), DeclareError> {
        name::validate_name(item)?;
        let node = &self.inner.node;
        if node.cancel.is_cancelled() {
            return Err(DeclareError::Closed);
        }
        let id = node.local.fresh_id();
        let offer = Arc::new(LocalOffer {
            id,
            service: self.inner.id,
            kind,
            name: self.full_name(item).into(),
            ty,
            role,
            remote: Default::default(),
            local: Mutex::default(),
            has_local: Default::default(),
            refused: Mutex::default(),
            origin: None,
            hidden_on: None,
        });
        node.add_offer(offer.clone());
        Ok((
            offer,
            Declared {
                node: Arc::downgrade(node),
                id,
                _owner: Some(self.inner.clone()),
            },
        ))
    }

    pub(super) fn interest(
        &self,
        pattern: &str,
        kind: ItemKind,
        ty: TypeInfo,
        mailbox: Option<Arc<Mailbox>>,
    ) -> Result<Declared, DeclareError> {
        name::validate_pattern(pattern)?;
        let node = &self.inner.node;
        if node.cancel.is_cancelled() {
            return Err(DeclareError::Closed);
        }
        let id = node.local.fresh_id();
        node.add_interest(Arc::new(LocalInterest {
            id,
            service: self.inner.id,
            service_name: self.inner.name.clone(),
            kind,
            pattern: pattern.to_owned(),
            ty,
            mailbox,
            reported: Mutex::default(),
            hidden_on: None,
        }));
        Ok(Declared {
            node: Arc::downgrade(node),
            id,
            _owner: Some(self.inner.clone()),
        })
    }

    /// Declares an interest delivered into a mailbox of its own, which keeps only the newest
    /// value per name for variables and every event in order for events.
    pub(super) fn mailbox_interest(
        &self,
        pattern: &str,
        kind: ItemKind,
        ty: TypeInfo,
    ) -> Result<(Arc<Mailbox>, Declared), DeclareError> {
        let congestion = self.inner.node.congestion.clone();
        let mailbox = Arc::new(Mailbox::counted_in(
            kind == ItemKind::Variable,
            Some(congestion),
        ));
        let declared = self.interest(pattern, kind, ty, Some(mailbox.clone()))?;
        Ok((mailbox, declared))
    }

    /// Declares an offer of a variable or an event and the handle keeping it declared.
    fn publisher(
        &self,
        item: &str,
        kind: ItemKind,
        ty: TypeInfo,
        role: OfferRole,
    ) -> Result<Publisher, DeclareError> {
        let (offer, declared) = self.offer(item, kind, ty, role)?;
        Ok(Publisher::new(self.inner.node.clone(), offer, declared))
    }

    /// Publishes a variable `item` of type `T`.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn publish_variable<T: Payload>(&self, item: &str) -> Result<Variable<T>, DeclareError> {
        let publisher = self.publisher(
            item,
            ItemKind::Variable,
            TypeInfo::of::<T>(),
            OfferRole::Variable {
                last: Mutex::new(None),
            },
        )?;
        Ok(Variable::new(publisher))
    }

    /// Subscribes to variables matching `pattern` (full names, wildcards allowed). The last
    /// value of every matching variable arrives at once.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe_variable<T: Payload>(
        &self,
        pattern: &str,
    ) -> Result<VariableSubscriber<T>, DeclareError> {
        let (mailbox, declared) =
            self.mailbox_interest(pattern, ItemKind::Variable, TypeInfo::of::<T>())?;
        Ok(VariableSubscriber::new(mailbox, declared))
    }

    /// Publishes an event `item` of type `T`.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn publish_event<T: Payload>(&self, item: &str) -> Result<Event<T>, DeclareError> {
        let publisher =
            self.publisher(item, ItemKind::Event, TypeInfo::of::<T>(), OfferRole::Event)?;
        Ok(Event::new(publisher))
    }

    /// Subscribes to events matching `pattern`.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe_event<T: Payload>(
        &self,
        pattern: &str,
    ) -> Result<EventSubscriber<T>, DeclareError> {
        let (mailbox, declared) =
            self.mailbox_interest(pattern, ItemKind::Event, TypeInfo::of::<T>())?;
        Ok(EventSubscriber::new(mailbox, declared))
    }

    /// Subscribes to events matching `pattern` with a callback instead of a mailbox: `callback`
    /// runs for each event (or a refusal or decode error, as [`Subscription::recv`] returns
    /// them) until the returned handle is dropped.
    ///
    /// An event from another node runs the callback on the task of the link it came in on,
    /// with no hand-off to another task; that task reads nothing more from the link until the
    /// callback returns, so nothing after it is acknowledged and a lossless stream
    /// ([`Event::stream`]) waits for a slow callback (at most the rest of one datagram's
    /// events may be acknowledged early). The callback therefore must not block: a long one
    /// holds back that link's other traffic (hand slow work to a task of your own). One that
    /// must wait should do so inside `tokio::task::block_in_place`, so the worker's other
    /// tasks move to another thread meanwhile (a task left waiting in the worker's slot for
    /// its next task was seen held up for as long as the callback). Events from this node's own
    /// publishers run it on a task of the subscription's. It may publish or declare.
    ///
    /// ```no_run
    /// # fn f(svc: &marea::Service) -> Result<(), marea::DeclareError> {
    /// let count = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    /// let c = count.clone();
    /// let _sub = svc.subscribe_event_with::<Vec<u8>, _>("**/telemetry", move |sample| {
    ///     if sample.is_ok() {
    ///         c.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    ///     }
    /// })?;
    /// # Ok(()) }
    /// ```
    ///
    /// [`Subscription::recv`]: crate::Subscription::recv
    /// [`Event::stream`]: crate::Event::stream
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe_event_with<T, F>(
        &self,
        pattern: &str,
        callback: F,
    ) -> Result<CallbackSubscription, DeclareError>
    where
        T: Payload,
        F: Fn(Result<Sample<T>, RecvError>) + Send + Sync + 'static,
    {
        self.callback_interest(pattern, ItemKind::Event, callback)
    }

    /// [`Service::subscribe_event_with`] for variables: `callback` runs for every value that
    /// arrives (none is coalesced away), the last value of each matching variable first.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe_variable_with<T, F>(
        &self,
        pattern: &str,
        callback: F,
    ) -> Result<CallbackSubscription, DeclareError>
    where
        T: Payload,
        F: Fn(Result<Sample<T>, RecvError>) + Send + Sync + 'static,
    {
        self.callback_interest(pattern, ItemKind::Variable, callback)
    }

    fn callback_interest<T, F>(
        &self,
        pattern: &str,
        kind: ItemKind,
        callback: F,
    ) -> Result<CallbackSubscription, DeclareError>
    where
        T: Payload,
        F: Fn(Result<Sample<T>, RecvError>) + Send + Sync + 'static,
    {
        let mailbox = Arc::new(Mailbox::calling(Arc::new(move |d| {
            callback(decode_delivery::<T>(d))
        })));
        let declared = self.interest(pattern, kind, TypeInfo::of::<T>(), Some(mailbox.clone()))?;
        // Ends with the subscription (its mailbox closed) or with the node.
        let stop = self.inner.node.cancel.clone();
        crate::sync::spawn_tracked(&self.inner.node.tasks, async move {
            tokio::select! {
                _ = stop.cancelled() => {}
                _ = mailbox.run_queued() => {}
            }
        });
        Ok(CallbackSubscription::new(declared))
    }

    /// Provides function `item`: `handler` gets the arguments and returns the result or an
    /// error message for the caller. The function is withdrawn when the handle is dropped.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn provide_function<A, R, F, Fut>(
        &self,
        item: &str,
        handler: F,
    ) -> Result<FunctionProvider, DeclareError>
    where
        A: Payload,
        R: Payload,
        F: Fn(A) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Result<R, String>> + Send + 'static,
    {
        self.provide_function_with_caller(item, move |a: A, _caller| handler(a))
    }

    /// Like [`Service::provide_function`], with the [`Caller`](crate::Caller) of each call
    /// given to `handler` beside its arguments: who sent a command, for its log.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn provide_function_with_caller<A, R, F, Fut>(
        &self,
        item: &str,
        handler: F,
    ) -> Result<FunctionProvider, DeclareError>
    where
        A: Payload,
        R: Payload,
        F: Fn(A, crate::node::calls::Caller) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Result<R, String>> + Send + 'static,
    {
        let handler = Arc::new(handler);
        let raw: crate::node::calls::RawHandler =
            Arc::new(move |args: Vec<u8>, caller: crate::node::calls::Caller| {
                let handler = handler.clone();
                let fut: BoxFuture<Result<Vec<u8>, crate::protocol::RemoteFailure>> =
                    Box::pin(async move {
                        use crate::protocol::RemoteFailure;
                        let a: A = crate::codec::decode_payload(&args)
                            .map_err(|e| RemoteFailure::BadArguments(e.to_string()))?;
                        let r = handler(a, caller).await.map_err(RemoteFailure::Handler)?;
                        crate::codec::encode_payload(&r).map_err(|e| {
                            RemoteFailure::Handler(format!("cannot encode result: {e}"))
                        })
                    });
                fut
            });
        let (offer, declared) = self.offer(
            item,
            ItemKind::Function,
            TypeInfo::of_function::<A, R>(),
            OfferRole::Function { handler: raw },
        )?;
        Ok(FunctionProvider::new(offer, declared))
    }

    /// A client for function `name` (a full name). Declares the intent, so listings show who
    /// calls what.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn function<A: Payload, R: Payload>(
        &self,
        name: &str,
    ) -> Result<Function<A, R>, DeclareError> {
        name::validate_name(name)?;
        let declared = self.interest(
            name,
            ItemKind::Function,
            TypeInfo::of_function::<A, R>(),
            None,
        )?;
        Ok(Function::new(
            self.inner.node.clone(),
            name.to_owned(),
            declared,
        ))
    }

    /// Accepts files sent to `item` into directory `dir` (created if missing), with the default
    /// limits of [`FileSinkOptions`].
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name, an unusable directory or a stopping node.
    pub fn file_sink(&self, item: &str, dir: impl Into<PathBuf>) -> Result<FileSink, DeclareError> {
        self.file_sink_with(
            item,
            FileSinkOptions {
                dir: Some(dir.into()),
                ..FileSinkOptions::default()
            },
        )
    }

    /// Accepts files sent to `item` with the given directory and limits (the directory, when
    /// not given, is under the user's state directory: [`crate::state_dir`]). Stale partial
    /// files are removed now and then periodically while the sink lives.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name, an unusable directory (or one whose private
    /// subdirectory of partial files belongs to someone else) or a stopping node.
    pub fn file_sink_with(
        &self,
        item: &str,
        options: FileSinkOptions,
    ) -> Result<FileSink, DeclareError> {
        name::validate_name(item)?;
        let state =
            SinkState::open(self.full_name(item).into(), options).map_err(|(dir, reason)| {
                DeclareError::SinkDir {
                    dir: dir.display().to_string(),
                    reason,
                }
            })?;
        let state = Arc::new(state);
        let mailbox = Arc::new(SinkMailbox::default());
        let (offer, declared) = self.offer(
            item,
            ItemKind::File,
            TypeInfo::of::<FileSink>(),
            OfferRole::File {
                state: state.clone(),
                mailbox: mailbox.clone(),
            },
        )?;
        let sweeping = self.inner.node.cancel.child_token();
        let stop = sweeping.clone();
        let sweeper = state.clone();
        crate::sync::spawn_tracked(&self.inner.node.tasks, async move {
            let period = sweeper.sweep_period();
            loop {
                tokio::select! {
                    _ = stop.cancelled() => break,
                    _ = tokio::time::sleep(period) => {}
                }
                let s = sweeper.clone();
                let _ = tokio::task::spawn_blocking(move || s.remove_stale_parts()).await;
            }
        });
        Ok(FileSink::new(offer, mailbox, declared, state, sweeping))
    }

    /// Sends a file to the sink named `to` (a full name), in the background. The returned handle
    /// shows progress and gives the outcome.
    pub fn send_file(
        &self,
        path: impl Into<PathBuf>,
        to: &str,
        options: SendFileOptions,
    ) -> FileTransfer {
        FileTransfer::start(self.inner.node.clone(), path.into(), to.to_owned(), options)
    }

    /// Spawns a task that belongs to the node: it is awaited at shutdown, and should stop when
    /// [`Service::cancelled`] resolves.
    pub fn spawn<F>(&self, fut: F)
    where
        F: std::future::Future<Output = ()> + Send + 'static,
    {
        crate::sync::spawn_tracked(&self.inner.node.tasks, fut);
    }

    /// Resolves when the node shuts down.
    pub async fn cancelled(&self) {
        self.inner.node.cancel.cancelled().await
    }

    /// Describes this service's items.
    pub fn describe(&self) -> ServiceDescription {
        use super::node::ItemRole;
        let node = &self.inner.node;
        let mut items: Vec<ItemDescription> = node
            .local
            .offers
            .iter()
            .filter(|o| o.service == self.inner.id)
            .map(|o| ItemDescription {
                kind: o.kind,
                role: ItemRole::Offer,
                name: o.name.to_string(),
                type_name: o.ty.name.clone(),
            })
            .chain(
                node.local
                    .interests
                    .iter()
                    .filter(|i| i.service == self.inner.id)
                    .map(|i| ItemDescription {
                        kind: i.kind,
                        role: ItemRole::Interest,
                        name: i.pattern.clone(),
                        type_name: i.ty.name.clone(),
                    }),
            )
            .collect();
        items.sort_by(|a, b| a.name.cmp(&b.name));
        ServiceDescription {
            name: self.inner.name.to_string(),
            items,
        }
    }
}

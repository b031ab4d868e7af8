//! Typed item handles: an item's name and its payload type together, so a service's catalogue
//! (a `const` per item, in the crate that owns the types) is the one place that pairs them, and a
//! subscriber, caller or provider cannot name the item with one type and decode it as another.
//!
//! A handle holds only the item's name inside its service (`position`); where it lives is given
//! at each use as a prefix: a service path (`rover1/vas`) or a pattern (`**/vas`).
//!
//! ```no_run
//! # fn f(svc: &marea::Service) -> Result<(), marea::DeclareError> {
//! const SPEED: marea::VariableItem<f32> = marea::VariableItem::new("speed");
//! let every_vas = SPEED.subscribe(svc, "**/vas")?; // `**/vas/speed`, decoded as f32
//! let mine = SPEED.publish(svc)?; // this service's `speed`
//! # Ok(()) }
//! ```

use std::fmt;
use std::marker::PhantomData;

use super::errors::DeclareError;
use super::event::Event;
use super::function::{Function, FunctionProvider};
use super::service::Service;
use super::subscription::{EventSubscriber, VariableSubscriber};
use super::variable::Variable;
use super::Payload;
use crate::node::calls::Caller;

/// `name` under `prefix`: `prefix/name`, or the bare name for an empty prefix.
fn full_name(prefix: &str, name: &str) -> String {
    if prefix.is_empty() {
        name.to_owned()
    } else {
        format!("{prefix}/{name}")
    }
}

/// A variable's name in its service and its type `T`.
pub struct VariableItem<T> {
    name: &'static str,
    // `fn() -> T`: the handle holds no `T`, so it is `Send`, `Sync` and `Copy` whatever `T` is.
    _t: PhantomData<fn() -> T>,
}

impl<T> VariableItem<T> {
    /// The variable `name` (one segment, e.g. `position`) of type `T`.
    pub const fn new(name: &'static str) -> Self {
        Self {
            name,
            _t: PhantomData,
        }
    }

    /// The variable's name in its service (`position`).
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// The variable's name under `prefix` (a service path such as `rover1/vas`, or a pattern
    /// such as `**/vas`): `prefix/name`; the bare name for an empty prefix.
    pub fn at(&self, prefix: &str) -> String {
        full_name(prefix, self.name)
    }
}

impl<T: Payload> VariableItem<T> {
    /// Subscribes through `svc` to the variable under `prefix` (see [`VariableItem::at`]), as
    /// [`Service::subscribe_variable`] does.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe(
        &self,
        svc: &Service,
        prefix: &str,
    ) -> Result<VariableSubscriber<T>, DeclareError> {
        svc.subscribe_variable(&self.at(prefix))
    }

    /// Publishes the variable as `svc`'s own (`namespace/service/name`), as
    /// [`Service::publish_variable`] does.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn publish(&self, svc: &Service) -> Result<Variable<T>, DeclareError> {
        svc.publish_variable(self.name)
    }
}

impl<T> Clone for VariableItem<T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for VariableItem<T> {}

impl<T> fmt::Debug for VariableItem<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VariableItem")
            .field("name", &self.name)
            .field("type", &std::any::type_name::<T>())
            .finish()
    }
}

/// An event's name in its service and its type `T`.
pub struct EventItem<T> {
    name: &'static str,
    // As in `VariableItem`.
    _t: PhantomData<fn() -> T>,
}

impl<T> EventItem<T> {
    /// The event `name` (one segment, e.g. `alarm`) of type `T`.
    pub const fn new(name: &'static str) -> Self {
        Self {
            name,
            _t: PhantomData,
        }
    }

    /// The event's name in its service (`alarm`).
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// The event's name under `prefix` (a service path or a pattern): `prefix/name`; the bare
    /// name for an empty prefix.
    pub fn at(&self, prefix: &str) -> String {
        full_name(prefix, self.name)
    }
}

impl<T: Payload> EventItem<T> {
    /// Subscribes through `svc` to the event under `prefix` (see [`EventItem::at`]), as
    /// [`Service::subscribe_event`] does.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe(
        &self,
        svc: &Service,
        prefix: &str,
    ) -> Result<EventSubscriber<T>, DeclareError> {
        svc.subscribe_event(&self.at(prefix))
    }

    /// Publishes the event as `svc`'s own (`namespace/service/name`), as
    /// [`Service::publish_event`] does.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn publish(&self, svc: &Service) -> Result<Event<T>, DeclareError> {
        svc.publish_event(self.name)
    }
}

impl<T> Clone for EventItem<T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for EventItem<T> {}

impl<T> fmt::Debug for EventItem<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("EventItem")
            .field("name", &self.name)
            .field("type", &std::any::type_name::<T>())
            .finish()
    }
}

/// A function's name in its service, its argument type `A` and its result type `R`.
pub struct FunctionItem<A, R> {
    name: &'static str,
    // As in `VariableItem`.
    _t: PhantomData<fn(A) -> R>,
}

impl<A, R> FunctionItem<A, R> {
    /// The function `name` (one segment, e.g. `change_state`) taking `A` and answering `R`.
    pub const fn new(name: &'static str) -> Self {
        Self {
            name,
            _t: PhantomData,
        }
    }

    /// The function's name in its service (`change_state`).
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// The function's name under `prefix` (a service path such as `rover1/vas`): `prefix/name`;
    /// the bare name for an empty prefix.
    pub fn at(&self, prefix: &str) -> String {
        full_name(prefix, self.name)
    }
}

impl<A: Payload, R: Payload> FunctionItem<A, R> {
    /// A client through `svc` of the function under `prefix` (see [`FunctionItem::at`]), as
    /// [`Service::function`] makes one.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn function(&self, svc: &Service, prefix: &str) -> Result<Function<A, R>, DeclareError> {
        svc.function(&self.at(prefix))
    }

    /// Provides the function as `svc`'s own (`namespace/service/name`) with `handler`, as
    /// [`Service::provide_function`] does.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn provide<F, Fut>(
        &self,
        svc: &Service,
        handler: F,
    ) -> Result<FunctionProvider, DeclareError>
    where
        F: Fn(A) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Result<R, String>> + Send + 'static,
    {
        svc.provide_function(self.name, handler)
    }

    /// Like [`FunctionItem::provide`], with the [`Caller`] of each call given to `handler`, as
    /// [`Service::provide_function_with_caller`] does.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid name or a stopping node.
    pub fn provide_with_caller<F, Fut>(
        &self,
        svc: &Service,
        handler: F,
    ) -> Result<FunctionProvider, DeclareError>
    where
        F: Fn(A, Caller) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Result<R, String>> + Send + 'static,
    {
        svc.provide_function_with_caller(self.name, handler)
    }
}

impl<A, R> Clone for FunctionItem<A, R> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<A, R> Copy for FunctionItem<A, R> {}

impl<A, R> fmt::Debug for FunctionItem<A, R> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("FunctionItem")
            .field("name", &self.name)
            .field("args", &std::any::type_name::<A>())
            .field("result", &std::any::type_name::<R>())
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Not `Clone`, `Debug` or `Payload`: the handles need none of it from their types.
    struct Opaque;

    const POSITION: VariableItem<Opaque> = VariableItem::new("position");
    const ALARM: EventItem<Opaque> = EventItem::new("alarm");
    const CHANGE_STATE: FunctionItem<Opaque, Opaque> = FunctionItem::new("change_state");

    #[test]
    fn at_puts_the_name_under_a_service_path_or_a_pattern() {
        assert_eq!(POSITION.at("rover1/vas"), "rover1/vas/position");
        assert_eq!(POSITION.at("**/vas"), "**/vas/position");
        assert_eq!(ALARM.at("*/vas"), "*/vas/alarm");
        assert_eq!(CHANGE_STATE.at("fleet/a/vas"), "fleet/a/vas/change_state");
    }

    #[test]
    fn at_an_empty_prefix_is_the_bare_name() {
        assert_eq!(POSITION.at(""), "position");
        assert_eq!(ALARM.at(""), "alarm");
        assert_eq!(CHANGE_STATE.at(""), "change_state");
    }

    #[test]
    fn handles_copy_and_show_name_and_types_whatever_the_types() {
        let (p, a, c) = (POSITION, ALARM, CHANGE_STATE);
        let (p2, a2, c2) = (p, a, c);
        assert_eq!(
            (p.name(), a.name(), c.name()),
            (p2.name(), a2.name(), c2.name())
        );
        let shown = format!("{p:?} {a:?} {c:?}");
        assert!(shown.contains("\"position\""), "{shown}");
        assert!(shown.contains("Opaque"), "{shown}");
        assert!(shown.starts_with("VariableItem"), "{shown}");
    }
}

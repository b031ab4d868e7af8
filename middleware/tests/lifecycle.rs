//! A node shuts down cleanly: hosted services are stopped, peers are told at once, and no task
//! is left behind, even with transfers, calls and subscriptions active.

mod common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use marea::{IService, NetworkConfig, Node, RecvError, Service, ServiceError};

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    common::loopback_config(node, domain, 3, port, Duration::from_secs(30))
}

struct Ticker {
    stopped: Arc<AtomicBool>,
}

#[async_trait::async_trait]
impl IService for Ticker {
    fn name(&self) -> &str {
        "ticker"
    }

    async fn start(&mut self, ctx: Service) -> Result<(), ServiceError> {
        let var = ctx.publish_variable::<u64>("tick")?;
        let c = ctx.clone();
        ctx.spawn(async move {
            let mut i = 0u64;
            loop {
                tokio::select! {
                    _ = c.cancelled() => break,
                    _ = tokio::time::sleep(Duration::from_millis(5)) => {}
                }
                i += 1;
                let _ = var.set(&i);
            }
        });
        Ok(())
    }

    async fn stop(&mut self) -> Result<(), ServiceError> {
        self.stopped.store(true, Ordering::SeqCst);
        Ok(())
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_stops_services_tells_peers_and_leaves_no_task() {
    let domain = format!("lifecycle-{}", std::process::id());
    let port = test_support::multicast_port(u64::from(std::process::id()) + 2_000);
    let a = Node::open(&cfg("a", &domain, port)).await.unwrap();
    let b = Node::open(&cfg("b", &domain, port)).await.unwrap();
    let stopped = Arc::new(AtomicBool::new(false));
    a.add_service(Box::new(Ticker {
        stopped: stopped.clone(),
    }))
    .await
    .unwrap();
    let sb = b.service("watch").unwrap();
    let sub = sb.subscribe_variable::<u64>("ticker/tick").unwrap();
    sub.recv_timeout(Duration::from_secs(10)).await.unwrap();
    assert!(
        b.wait_until(Duration::from_secs(5), |n| n.peers().len() == 1)
            .await
    );

    assert!(a.shutdown().await, "tasks left behind");
    assert!(
        stopped.load(Ordering::SeqCst),
        "IService::stop was not called"
    );
    // The peer learns of the departure from Bye, long before the 30 s lease.
    assert!(
        b.wait_until(Duration::from_secs(5), |n| n.peers().is_empty())
            .await,
        "peer still listed after Bye"
    );
    drop((sub, sb));
    assert!(b.shutdown().await);
}

/// Shutting a node down closes what its receivers wait on: an event subscription's `recv`, a
/// variable subscription's `recv_blocking` on a plain thread and a file sink's `recv` all return
/// `Closed` at once (as documented), instead of waiting for good.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_closes_the_subscriptions_receivers_wait_on() {
    let domain = format!("lifecycle-close-{}", std::process::id());
    let port = test_support::multicast_port(u64::from(std::process::id()) + 2_001);
    let n = Node::open(&cfg("n", &domain, port)).await.unwrap();
    let svc = n.service("watch").unwrap();
    let events = svc.subscribe_event::<u64>("*/nothing/ev").unwrap();
    let values = svc.subscribe_variable::<u64>("*/nothing/var").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let sink = svc.file_sink("inbox", dir.path()).unwrap();
    let event_wait = tokio::spawn(async move { events.recv().await.map(|s| s.value) });
    let file_wait = tokio::spawn(async move { sink.recv().await.map(|_| ()) });
    let value_wait = tokio::task::spawn_blocking(move || {
        values
            .recv_blocking_timeout(Duration::from_secs(20))
            .map(|s| s.value)
    });
    assert!(n.shutdown().await, "tasks left behind");
    let limit = Duration::from_secs(10);
    let ev = tokio::time::timeout(limit, event_wait)
        .await
        .expect("event recv returned");
    assert!(matches!(ev.unwrap(), Err(RecvError::Closed)));
    let file = tokio::time::timeout(limit, file_wait)
        .await
        .expect("sink recv returned");
    assert!(matches!(file.unwrap(), Err(RecvError::Closed)));
    let var = tokio::time::timeout(limit, value_wait)
        .await
        .expect("blocking recv returned");
    assert!(
        matches!(var.unwrap(), Err(RecvError::Closed)),
        "closed, not timed out"
    );
}

//! List what the network offers: nodes, services, and their items, as `usal list` will; and host
//! a service through the `IService` trait.
//!
//! `cargo run -p marea --example list`

use std::time::Duration;

use marea::{IService, NetworkConfig, Node, Service, ServiceError, Variable};

/// A tiny service: publishes a heartbeat counter and provides `ping`.
struct Beacon {
    counter: Option<Variable<u64>>,
}

#[async_trait::async_trait]
impl IService for Beacon {
    fn name(&self) -> &str {
        "beacon"
    }

    async fn start(&mut self, ctx: Service) -> Result<(), ServiceError> {
        let counter = ctx.publish_variable::<u64>("counter")?;
        counter
            .set(&1)
            .map_err(|e| ServiceError::Failed(e.to_string()))?;
        self.counter = Some(counter);
        let ping =
            ctx.provide_function("ping", |n: u64| async move { Ok::<u64, String>(n + 1) })?;
        let c = ctx.clone();
        ctx.spawn(async move {
            c.cancelled().await;
            drop(ping);
        });
        Ok(())
    }
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut cfg = NetworkConfig::ethernet_loopback("air");
    cfg.namespace = Some("rover1".into());
    let air = Node::open(&cfg).await?;
    air.add_service(Box::new(Beacon { counter: None })).await?;

    let ground = Node::open(&NetworkConfig::ethernet_loopback("ground")).await?;
    let station = ground.service("fmo")?;
    let _sub = station.subscribe_variable::<u64>("*/beacon/counter")?;
    ground
        .wait_until(Duration::from_secs(5), |n| {
            n.is_offered(marea::protocol::ItemKind::Function, "rover1/beacon/ping")
        })
        .await;
    for node in ground.catalog().nodes {
        println!(
            "node {} (namespace '{}'{})",
            node.name,
            node.namespace,
            if node.local { ", local" } else { "" }
        );
        for svc in node.services {
            println!("  service {}", svc.name);
            for item in svc.items {
                println!(
                    "    {:?} {:<9} {:<28} {}",
                    item.role,
                    item.kind.as_str(),
                    item.name,
                    item.type_name
                );
            }
        }
    }
    drop((_sub, station));
    air.shutdown().await;
    ground.shutdown().await;
    Ok(())
}

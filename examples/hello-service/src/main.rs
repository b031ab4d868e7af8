//! A service of your own, as a mission runs it: `<service name="hello" package="hello-service"/>`
//! in a `<node>` of the mission file. It shows the four things a service does:
//! - publishes a variable: `NS/hello/distance_m`, how far the vehicle is from where it was first
//!   seen (metres), and `NS/hello/uptime_s`;
//! - raises an event: `NS/hello/greeted`, each time someone is greeted;
//! - provides a function: `NS/hello/greet`, `"name"` -> `"hello, name"`;
//! - subscribes to another service's variable: the VAS's `position` (`HELLO_VEHICLE/vas/position`,
//!   by default its own node's namespace), through its typed handle in the VAS's catalogue
//!   (`usal_types::items::vas::POSITION`: the name and the type together).
//!
//! `usal run` starts it with the node's network in the environment (`MAREA_DOMAIN`,
//! `MAREA_NAMESPACE`, `MAREA_NODE`, `MAREA_NETWORK`), which `NetworkConfig::from_env` reads;
//! run by hand, it joins the default domain on the loopback as node `hello`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use marea::{IService, NetworkConfig, Node, Service, ServiceError};
use usal_types::items::vas;
use usal_types::Position;

/// The service: everything it needs is declared in `start`.
struct Hello {
    /// Whose position it follows: `rover1` follows `rover1/vas/position`.
    vehicle: String,
}

#[async_trait::async_trait]
impl IService for Hello {
    fn name(&self) -> &str {
        "hello"
    }

    async fn start(&mut self, ctx: Service) -> Result<(), ServiceError> {
        let distance = ctx.publish_variable::<f64>("distance_m")?;
        let uptime = ctx.publish_variable::<u64>("uptime_s")?;
        // Handles are shared between the function's calls through an Arc.
        let greeted = Arc::new(ctx.publish_event::<String>("greeted")?);
        let position = vas::POSITION.subscribe(&ctx, &format!("{}/vas", self.vehicle))?;
        // A function's handler answers each call; an Err is the caller's error message.
        let greet = ctx.provide_function("greet", move |name: String| {
            let greeted = Arc::clone(&greeted);
            async move {
                if name.trim().is_empty() {
                    return Err("greet whom? give a name".to_owned());
                }
                let text = format!("hello, {name}");
                greeted.raise(&text).await.map_err(|e| e.to_string())?;
                Ok::<String, String>(text)
            }
        })?;
        // Work runs in tasks the node stops when it shuts down.
        let stop = ctx.clone();
        ctx.spawn(async move {
            let _greet = greet;
            let started = Instant::now();
            let mut first: Option<Position> = None;
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tokio::select! {
                    () = stop.cancelled() => break,
                    _ = tick.tick() => {
                        let _ = uptime.set(&started.elapsed().as_secs());
                    }
                    p = position.recv() => {
                        let Ok(p) = p else { break };
                        let p = p.value;
                        let from = *first.get_or_insert(p);
                        let _ = distance.set(&metres_between(&from, &p));
                    }
                }
            }
        });
        Ok(())
    }
}

/// Distance along the ground between two positions, metres (equirectangular: fine over a
/// few kilometres).
fn metres_between(a: &Position, b: &Position) -> f64 {
    const EARTH_RADIUS_M: f64 = 6_371_000.0;
    let lat = (a.lat + b.lat).to_radians() / 2.0;
    let north = (b.lat - a.lat).to_radians() * EARTH_RADIUS_M;
    let east = (b.lon - a.lon).to_radians() * EARTH_RADIUS_M * lat.cos();
    north.hypot(east)
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let config = NetworkConfig::from_env("hello")?;
    let vehicle = std::env::var("HELLO_VEHICLE")
        .ok()
        .or_else(|| config.namespace.clone())
        .unwrap_or_else(|| "rover1".to_owned());
    eprintln!(
        "hello: node {} in domain {}, following {vehicle}/vas/position",
        config.node, config.domain
    );
    let node = Node::open(&config).await?;
    node.add_service(Box::new(Hello { vehicle })).await?;
    // Until Ctrl-C or SIGTERM (what usal run sends when the mission ends).
    marea::process::terminated().await;
    node.shutdown().await;
    Ok(())
}

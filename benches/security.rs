//! `cargo bench --bench security`: what trust costs and what attacks cost, as JSON lines
//! `{"metric": ..., "value": ..., "unit": ...}`.
//! - `auth`: the price of link authentication (wire bytes, round trip and rate with a key
//!   against the same run without one).
//! - `hostile`: how the node holds under adversarial input (worst pattern match, discovery
//!   during a heartbeat flood, share of the hostile suite's attacks refused).

#[path = "security/auth.rs"]
mod auth;
// The cross-process helpers and the hostile suite of the tests (`tests/common`).
#[path = "../tests/common/mod.rs"]
mod common;
#[path = "security/hostile.rs"]
mod hostile;
#[path = "security/metric.rs"]
mod metric;

fn main() {
    let only = std::env::args().skip(1).find(|a| !a.starts_with('-'));
    let wants = |group: &str| {
        only.as_deref()
            .is_none_or(|o| group.starts_with(o) || o.starts_with(group))
    };
    if wants("auth") {
        auth::run();
    }
    if wants("hostile") {
        hostile::run();
    }
}

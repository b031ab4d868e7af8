//! Adversarial-input figures (`hostile.*`). Filled in by the bounded-resources work.

#[allow(unused_imports)]
use super::metric::metric;

pub fn run() {}

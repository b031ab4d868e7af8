//! Link authentication figures (`auth.*`). Filled in by the link-authentication work.

#[allow(unused_imports)]
use super::metric::metric;

pub fn run() {}

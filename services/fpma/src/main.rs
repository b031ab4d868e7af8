//! The `fpma` command-line tool.
fn main() {}

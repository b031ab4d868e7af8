//! `usal`: the USAL-rs launcher and command-line tools (work in progress).
fn main() {
    println!("usal: launcher not built yet");
}

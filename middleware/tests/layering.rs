//! Keeps the layering of `marea` true: a top-level module names only modules of its own layer
//! or of a layer below (the checker: `test_support::layering`). The table is the one
//! `src/lib.rs` states.

use test_support::layering::Layers;

/// The layers, bottom to top. A new top-level module goes into the row it belongs to.
const LAYERS: Layers<'static> = Layers {
    rows: &[
        &["sync", "name", "typeinfo", "process", "xml"],
        &["protocol"],
        &["codec"],
        &["link"],
        &["config", "identity"],
        &["node"],
        &["api"],
        &["fuzzing"],
    ],
    table: "LAYERS in middleware/tests/layering.rs, the table in src/lib.rs",
};

#[test]
fn no_module_of_marea_uses_a_higher_layer() {
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let found = LAYERS.check_crate(&src);
    assert!(found.is_empty(), "layering broken:\n{}", found.join("\n"));
}

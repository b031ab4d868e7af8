//! Keeps the flight-plan library's layering true (the table in `src/lib.rs`): the parser knows
//! no vehicle and flies nothing; the check and the executive are one layer above the expansion;
//! the wire types are above everything they describe.

use test_support::layering::Layers;

/// The layers, bottom to top. A new top-level module goes into the row it belongs to.
const LAYERS: Layers<'static> = Layers {
    rows: &[
        &["xml"],
        &["expr", "geo", "vehicle"],
        &["model"],
        &["parse", "polygon"],
        &["expand", "eta"],
        &["exec", "check", "aircraft"],
        &["qgc"],
        &["plan_file"],
        &["api"],
        &["fleet_api"],
        &["fuzzing"],
    ],
    table: "LAYERS in crates/flightplan/tests/layering.rs, the table in src/lib.rs",
};

#[test]
fn no_module_of_the_fpma_uses_a_higher_layer() {
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let found = LAYERS.check_crate(&src);
    assert!(found.is_empty(), "layering broken:\n{}", found.join("\n"));
}

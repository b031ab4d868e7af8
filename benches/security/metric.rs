//! One JSON line per figure.

#[allow(dead_code)] // used once the groups are filled in
/// Prints `{"metric": name, "value": value, "unit": unit}`.
pub fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

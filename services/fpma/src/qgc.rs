//! QGroundControl `.plan` import and export (FLIGHTPLAN "Interchange").
use crate::model::FlightPlan;
use crate::vehicle::VehicleParams;
use thiserror::Error;

/// Why a plan cannot be exported to QGC.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum QgcExportError {
    /// A construct QGC cannot represent.
    #[error("leg `{leg}` cannot be exported: {why}")]
    Unrepresentable {
        /// The node.
        leg: String,
        /// Why.
        why: String,
    },
}

/// Exports a plan.
///
/// # Errors
/// See [`QgcExportError`].
pub fn export(
    _plan: &FlightPlan,
    _vehicle: &VehicleParams,
) -> Result<serde_json::Value, QgcExportError> {
    Err(QgcExportError::Unrepresentable {
        leg: String::new(),
        why: "not implemented yet".into(),
    })
}

//! The parameter protocol on [`MavlinkManager`]: read, set (checking the echo) and list, with
//! the cache every PARAM_VALUE seen updates.

use std::collections::BTreeMap;

use marea::sync::lock;
use mavlink::dialects::ardupilotmega::{
    MavMessage, MavParamType, PARAM_REQUEST_LIST_DATA, PARAM_REQUEST_READ_DATA, PARAM_SET_DATA,
};
use tokio::time::Instant;

use super::driver::wait_for;
use super::manager::MavlinkManager;
use super::types::*;

/// Every PARAM_VALUE seen: name -> (value, type, index), and the count the autopilot reports.
#[derive(Default)]
pub(crate) struct ParamCache {
    pub(crate) values: BTreeMap<String, (f32, MavParamType, u16)>,
    pub(crate) count: Option<u16>,
}

pub(crate) fn param_name(id: &mavlink::types::CharArray<16>) -> String {
    id.to_str().unwrap_or("").to_owned()
}

impl MavlinkManager {
    pub fn param_cached(&self, name: &str) -> Option<f32> {
        lock(&self.inner.params).values.get(name).map(|v| v.0)
    }

    /// All cached parameters.
    pub fn params_cached(&self) -> BTreeMap<String, f32> {
        lock(&self.inner.params)
            .values
            .iter()
            .map(|(k, v)| (k.clone(), v.0))
            .collect()
    }

    /// Reads one parameter from the autopilot (and caches it).
    ///
    /// # Errors
    /// No answer after the retries (ArduPilot ignores unknown names).
    pub async fn param_get(&self, name: &str) -> Result<f32, ParamError> {
        if name.len() > 16 {
            return Err(ParamError::NameTooLong(name.to_owned()));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let make = |_| {
            MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                param_index: -1,
                target_system: target.0,
                target_component: target.1,
                param_id: name.into(),
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::PARAM_VALUE(v) if param_name(&v.param_id) == name => Some(v.param_value),
            _ => None,
        };
        self.inner
            .transact(make, matcher)
            .await?
            .ok_or_else(|| ParamError::RetriesExhausted {
                name: name.to_owned(),
                attempts: self.inner.cfg.retries,
            })
    }

    /// Sets a parameter and checks the autopilot's PARAM_VALUE echoes it.
    ///
    /// # Errors
    /// No answer, or the autopilot reports another value.
    pub async fn param_set(&self, name: &str, value: f32) -> Result<f32, ParamError> {
        if name.len() > 16 {
            return Err(ParamError::NameTooLong(name.to_owned()));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let kind = lock(&self.inner.params)
            .values
            .get(name)
            .map_or(MavParamType::MAV_PARAM_TYPE_REAL32, |v| v.1);
        let make = |_| {
            MavMessage::PARAM_SET(PARAM_SET_DATA {
                param_value: value,
                target_system: target.0,
                target_component: target.1,
                param_id: name.into(),
                param_type: kind,
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::PARAM_VALUE(v) if param_name(&v.param_id) == name => Some(v.param_value),
            _ => None,
        };
        let actual = self.inner.transact(make, matcher).await?.ok_or_else(|| {
            ParamError::RetriesExhausted {
                name: name.to_owned(),
                attempts: self.inner.cfg.retries,
            }
        })?;
        let expected = if kind == MavParamType::MAV_PARAM_TYPE_REAL32 {
            value
        } else {
            value.round()
        };
        if (actual - expected).abs() > 1e-5 * expected.abs().max(1.0) {
            return Err(ParamError::NotApplied {
                name: name.to_owned(),
                requested: value,
                actual,
            });
        }
        Ok(actual)
    }

    /// Reads every parameter: PARAM_REQUEST_LIST, then PARAM_REQUEST_READ for
    /// each index that did not arrive.
    ///
    /// # Errors
    /// Parameters still missing after the retries.
    pub async fn params_list(&self) -> Result<BTreeMap<String, f32>, ParamError> {
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let mut rx = self.inner.raw_tx.subscribe();
        let mut seen: BTreeMap<u16, (String, f32)> = BTreeMap::new();
        let mut count: Option<u16> = None;
        let collect = |m: &MavMessage| match m {
            MavMessage::PARAM_VALUE(v) => Some((
                v.param_index,
                v.param_count,
                param_name(&v.param_id),
                v.param_value,
            )),
            _ => None,
        };
        for attempt in 0..self.inner.cfg.retries {
            if attempt == 0 || count.is_none() {
                self.inner
                    .send(MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
                        target_system: target.0,
                        target_component: target.1,
                    }))
                    .await?;
            } else {
                let missing = (0..count.unwrap_or(0))
                    .filter(|i| !seen.contains_key(i))
                    .collect::<Vec<_>>();
                for index in missing {
                    self.inner
                        .send(MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                            param_index: index as i16,
                            target_system: target.0,
                            target_component: target.1,
                            param_id: "".into(),
                        }))
                        .await?;
                }
            }
            // Collect until the list is complete or the autopilot goes quiet.
            loop {
                let deadline = Instant::now() + self.inner.cfg.request_timeout;
                match wait_for(&mut rx, deadline, collect).await? {
                    Some((index, total, name, value)) => {
                        count = Some(total);
                        if index < total {
                            seen.insert(index, (name, value));
                        }
                        if seen.len() >= usize::from(total) {
                            return Ok(seen.into_values().collect());
                        }
                    }
                    None => break,
                }
            }
            if count == Some(0) {
                return Ok(BTreeMap::new());
            }
        }
        Err(ParamError::RetriesExhausted {
            name: format!(
                "{} of {:?} parameters",
                count.unwrap_or(0) as usize - seen.len(),
                count
            ),
            attempts: self.inner.cfg.retries,
        })
    }
}

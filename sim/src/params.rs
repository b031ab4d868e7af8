//! A small, realistic set of ArduPilot parameters per vehicle kind, built for the autopilot
//! profile: the geofence's are ArduPilot's `FENCE_*` except on PX4, which keeps `GF_*` instead.
//!
//! Values travel as `f32` in PARAM_VALUE whatever their declared type, as
//! ArduPilot does (integers are sent by value, not bit-cast).

use mavlink::dialects::ardupilotmega::MavParamType;

use crate::kinematics::VehicleKind;
use crate::profile::Profile;

/// One parameter.
#[derive(Clone, Debug, PartialEq)]
pub struct Param {
    /// Name, at most 16 ASCII characters.
    pub name: &'static str,
    /// Current value.
    pub value: f32,
    /// Declared type.
    pub kind: MavParamType,
}

/// The parameter table, in index order.
#[derive(Clone, Debug)]
pub struct Params {
    list: Vec<Param>,
}

const I8: MavParamType = MavParamType::MAV_PARAM_TYPE_INT8;
const I16: MavParamType = MavParamType::MAV_PARAM_TYPE_INT16;
const I32: MavParamType = MavParamType::MAV_PARAM_TYPE_INT32;
const F32: MavParamType = MavParamType::MAV_PARAM_TYPE_REAL32;

fn p(name: &'static str, value: f32, kind: MavParamType) -> Param {
    Param { name, value, kind }
}

impl Params {
    /// The defaults of `kind` as `profile` keeps them, with SYSID_THISMAV set to `sysid`.
    pub fn defaults(kind: VehicleKind, sysid: u8, profile: Profile) -> Self {
        let mut list = vec![
            p("SYSID_THISMAV", f32::from(sysid), I16),
            p("SYSID_MYGCS", 255.0, I16),
            p("SR0_POSITION", 1.0, I16),
            p("SR0_EXTRA1", 1.0, I16),
            p("SR0_EXTRA2", 1.0, I16),
            p("SR0_EXT_STAT", 1.0, I16),
            p("MIS_RESTART", 0.0, I8),
            p("FS_ACTION", 2.0, I8),
            p("INITIAL_MODE", 0.0, I8),
        ];
        // The geofence (`fence.rs`): what each family keeps it as.
        if profile == Profile::Px4 {
            // PX4: no switch (an uploaded area is in force); `GF_ACTION` 0 none, 1 warning,
            // 2 hold, 3 return, 4 terminate, 5 land; the distances are metres from home, 0 off.
            list.extend([
                p("GF_ACTION", 2.0, I32),
                p("GF_MAX_HOR_DIST", 0.0, F32),
                p("GF_MAX_VER_DIST", 0.0, F32),
            ]);
        } else {
            // ArduPilot: off until a ground station sets it.
            list.extend([
                p("FENCE_ENABLE", 0.0, I8),
                p("FENCE_TYPE", 7.0, I8),
                p("FENCE_ACTION", 1.0, I8),
                p("FENCE_RADIUS", 300.0, F32),
                p("FENCE_ALT_MAX", 100.0, F32),
            ]);
        }
        match kind {
            VehicleKind::Rover => list.extend([
                p("WP_RADIUS", 2.0, F32),
                p("WP_OVERSHOOT", 2.0, F32),
                p("WP_SPEED", 0.0, F32),
                p("CRUISE_SPEED", 2.0, F32),
                p("CRUISE_THROTTLE", 50.0, I8),
                p("ATC_STR_RAT_MAX", 120.0, F32),
                p("ATC_ACCEL_MAX", 2.0, F32),
                p("MODE1", 0.0, I8),
                p("MODE2", 10.0, I8),
                p("MODE3", 4.0, I8),
            ]),
            VehicleKind::Copter => list.extend([
                p("WP_RADIUS", 2.0, F32),
                p("WPNAV_SPEED", 500.0, F32),
                p("WPNAV_SPEED_UP", 250.0, F32),
                p("WPNAV_ACCEL", 250.0, F32),
                p("ATC_RATE_Y_MAX", 90.0, F32),
                p("FLTMODE1", 0.0, I8),
                p("FLTMODE2", 3.0, I8),
            ]),
            VehicleKind::Plane => list.extend([
                p("WP_RADIUS", 90.0, I16),
                p("WP_LOITER_RAD", 60.0, I16),
                p("TKOFF_ALT", 50.0, I16),
                p("AIRSPEED_CRUISE", 15.0, F32),
                p("AIRSPEED_MIN", 9.0, I16),
                p("ROLL_LIMIT_DEG", 45.0, I16),
                p("TECS_CLMB_MAX", 5.0, F32),
                p("FLTMODE1", 0.0, I8),
                p("FLTMODE2", 10.0, I8),
            ]),
        }
        Self { list }
    }

    /// Number of parameters.
    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// Whether the table is empty (never, in practice).
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// The parameter at `index`.
    pub fn by_index(&self, index: usize) -> Option<&Param> {
        self.list.get(index)
    }

    /// Index and parameter named `name`.
    pub fn by_name(&self, name: &str) -> Option<(usize, &Param)> {
        self.list.iter().enumerate().find(|(_, p)| p.name == name)
    }

    /// The value of `name`, or `default` when the table has no such parameter.
    pub fn get_or(&self, name: &str, default: f32) -> f32 {
        self.by_name(name).map_or(default, |(_, p)| p.value)
    }

    /// This table as `profile` keeps it for `kind`: `profile`'s parameters (defaults), each
    /// carrying the value set here when this table has it too.
    pub fn rebuilt_for(&self, kind: VehicleKind, profile: Profile) -> Self {
        let sysid = self.get_or("SYSID_THISMAV", 1.0).clamp(0.0, 255.0) as u8;
        let mut fresh = Self::defaults(kind, sysid, profile);
        for old in &self.list {
            if let Some(new) = fresh.list.iter_mut().find(|p| p.name == old.name) {
                new.value = old.value;
            }
        }
        fresh
    }

    /// Sets `name`, rounding integer types; returns the index, or `None` when unknown.
    pub fn set(&mut self, name: &str, value: f32) -> Option<usize> {
        let (index, _) = self.by_name(name)?;
        let param = &mut self.list[index];
        param.value = if param.kind == F32 || !value.is_finite() {
            value
        } else {
            value.round()
        };
        Some(index)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rover_defaults_and_set() {
        let mut params = Params::defaults(VehicleKind::Rover, 7, Profile::ArduPilot);
        assert_eq!(params.get_or("SYSID_THISMAV", 0.0), 7.0);
        assert_eq!(params.get_or("WP_RADIUS", 0.0), 2.0);
        assert_eq!(
            params.set("CRUISE_SPEED", 3.5),
            params.by_name("CRUISE_SPEED").map(|p| p.0)
        );
        assert_eq!(params.get_or("CRUISE_SPEED", 0.0), 3.5);
        params.set("CRUISE_THROTTLE", 41.6);
        assert_eq!(
            params.get_or("CRUISE_THROTTLE", 0.0),
            42.0,
            "integers are rounded"
        );
        assert_eq!(params.set("NO_SUCH_PARAM", 1.0), None);
        assert!(params.list.iter().all(|p| p.name.len() <= 16));
    }

    #[test]
    fn the_geofence_params_follow_the_profile() {
        let ardupilot_fence = ["FENCE_ENABLE", "FENCE_TYPE", "FENCE_ACTION", "FENCE_RADIUS"];
        let px4_fence = ["GF_ACTION", "GF_MAX_HOR_DIST", "GF_MAX_VER_DIST"];
        for profile in [
            Profile::ArduPilot,
            Profile::Generic,
            Profile::ArduPilotResetting,
        ] {
            let params = Params::defaults(VehicleKind::Rover, 1, profile);
            assert!(
                ardupilot_fence.iter().all(|n| params.by_name(n).is_some()),
                "{profile:?}"
            );
            assert!(
                px4_fence.iter().all(|n| params.by_name(n).is_none()),
                "{profile:?}"
            );
        }
        let px4 = Params::defaults(VehicleKind::Copter, 1, Profile::Px4);
        assert!(ardupilot_fence.iter().all(|n| px4.by_name(n).is_none()));
        assert_eq!(
            px4_fence.map(|n| px4.get_or(n, -1.0)),
            [2.0, 0.0, 0.0],
            "GF_ACTION hold, no distance limits"
        );
        assert_eq!(
            px4.by_name("GF_ACTION").map(|(_, p)| p.kind),
            Some(MavParamType::MAV_PARAM_TYPE_INT32)
        );
        assert_eq!(px4.get_or("WPNAV_SPEED", 0.0), 500.0, "the kind's own stay");
    }

    #[test]
    fn a_rebuilt_table_keeps_the_values_both_profiles_share() {
        let mut params = Params::defaults(VehicleKind::Rover, 3, Profile::ArduPilot);
        params.set("CRUISE_SPEED", 4.0);
        params.set("FENCE_RADIUS", 50.0);
        let mut px4 = params.rebuilt_for(VehicleKind::Rover, Profile::Px4);
        assert_eq!(px4.get_or("CRUISE_SPEED", 0.0), 4.0);
        assert_eq!(px4.get_or("SYSID_THISMAV", 0.0), 3.0);
        assert!(px4.by_name("FENCE_RADIUS").is_none());
        px4.set("GF_MAX_HOR_DIST", 120.0);
        let back = px4.rebuilt_for(VehicleKind::Rover, Profile::ArduPilot);
        assert_eq!(
            back.get_or("FENCE_RADIUS", 0.0),
            300.0,
            "ArduPilot's default again"
        );
        assert!(back.by_name("GF_MAX_HOR_DIST").is_none());
        assert_eq!(back.get_or("CRUISE_SPEED", 0.0), 4.0);
    }
}

//! The simulated vehicle's outgoing side: wall-clock duties (heartbeat, telemetry streams at their requested rates,
//! mission request retries, RC override expiry) and the messages it builds.

use super::*;

impl Vehicle {
    /// Wall-clock duties: heartbeat, telemetry streams, mission request retries,
    /// RC override expiry.
    pub fn poll(&mut self, now: Instant) -> Vec<MavMessage> {
        let mut out = self.mission.poll(now);
        if now >= self.next_heartbeat {
            out.push(self.heartbeat());
            self.next_heartbeat = now + HEARTBEAT_PERIOD;
        }
        if self
            .sticks
            .is_some_and(|(_, at)| now.duration_since(at) > RC_OVERRIDE_TIMEOUT)
        {
            self.sticks = None;
        }
        let due: Vec<u32> = self
            .streams
            .iter_mut()
            .filter(|(_, (_, next))| now >= *next)
            .map(|(id, (period, next))| {
                // Catch up without bursts after a stall.
                *next = (*next + *period).max(now);
                *id
            })
            .collect();
        for id in due {
            if let Some(msg) = self.telemetry(id) {
                out.push(msg);
            }
        }
        out
    }

    pub(super) fn set_rate(&mut self, id: u32, hz: f64, now: Instant) {
        if hz <= 0.0 || !hz.is_finite() {
            self.streams.remove(&id);
        } else {
            let period = Duration::from_secs_f64(1.0 / hz.min(1000.0));
            self.streams.insert(id, (period, now));
        }
    }

    // ---------------------------------------------------------------- messages out

    /// The HEARTBEAT describing the current mode and arming state.
    pub fn heartbeat(&self) -> MavMessage {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        match self.behaviour() {
            Behaviour::Manual => base |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,
            Behaviour::Hold => base |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED,
            Behaviour::Auto
            | Behaviour::Rtl
            | Behaviour::Guided
            | Behaviour::Land
            | Behaviour::Takeoff => {
                base |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED
            }
        }
        if self.armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: self.profile.encode_mode(self.cfg.kind, self.mode),
            mavtype: match self.cfg.kind {
                VehicleKind::Rover => MavType::MAV_TYPE_GROUND_ROVER,
                VehicleKind::Copter => MavType::MAV_TYPE_QUADROTOR,
                VehicleKind::Plane => MavType::MAV_TYPE_FIXED_WING,
            },
            autopilot: match self.profile {
                Profile::ArduPilot | Profile::ArduPilotResetting => {
                    MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA
                }
                Profile::Px4 => MavAutopilot::MAV_AUTOPILOT_PX4,
                Profile::Generic => MavAutopilot::MAV_AUTOPILOT_GENERIC,
            },
            base_mode: base,
            system_status: if self.armed {
                MavState::MAV_STATE_ACTIVE
            } else {
                MavState::MAV_STATE_STANDBY
            },
            mavlink_version: 3,
        })
    }

    pub(super) fn mission_current(&self) -> MavMessage {
        MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA {
            seq: self.current,
            ..Default::default()
        })
    }

    pub(super) fn telemetry(&self, id: u32) -> Option<MavMessage> {
        let time_boot_ms = (self.sim_time * 1000.0) as u32;
        let geo = self.frame.to_geo(self.state.pos);
        let heading_deg = self.state.yaw.to_degrees().rem_euclid(360.0);
        Some(match id {
            GLOBAL_POSITION_INT_ID => MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms,
                lat: (geo.lat_deg * 1e7).round() as i32,
                lon: (geo.lon_deg * 1e7).round() as i32,
                alt: (geo.alt_m * 1000.0).round() as i32,
                relative_alt: (self.state.pos.up * 1000.0).round() as i32,
                vx: (self.state.vel_north * 100.0).round() as i16,
                vy: (self.state.vel_east * 100.0).round() as i16,
                vz: (-self.state.climb * 100.0).round() as i16,
                hdg: (heading_deg * 100.0).round() as u16 % 36000,
            }),
            ATTITUDE_ID => MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms,
                roll: self.state.roll as f32,
                pitch: 0.0,
                yaw: crate::kinematics::wrap_pi(self.state.yaw) as f32,
                rollspeed: 0.0,
                pitchspeed: 0.0,
                yawspeed: self.state.yaw_rate as f32,
            }),
            VFR_HUD_ID => MavMessage::VFR_HUD(VFR_HUD_DATA {
                // The plane's `speed` is its airspeed; over the ground the wind adds to it.
                airspeed: self.state.speed as f32,
                groundspeed: self.state.vel_north.hypot(self.state.vel_east) as f32,
                alt: geo.alt_m as f32,
                climb: self.state.climb as f32,
                heading: heading_deg.round() as i16 % 360,
                throttle: if self.armed {
                    (self.state.speed.abs() / self.limits().cruise_speed * 50.0).min(100.0) as u16
                } else {
                    0
                },
            }),
            SYS_STATUS_ID => {
                let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
                    | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL
                    | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_MAG
                    | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS;
                MavMessage::SYS_STATUS(SYS_STATUS_DATA {
                    onboard_control_sensors_present: sensors,
                    onboard_control_sensors_enabled: sensors,
                    onboard_control_sensors_health: sensors,
                    load: 120,
                    voltage_battery: (self.battery.voltage() * 1000.0).round() as u16,
                    // cA, at least the avionics' 0.5 A (a disarmed vehicle still draws that).
                    current_battery: (self.battery.current().max(0.5) * 100.0)
                        .round()
                        .min(f64::from(i16::MAX)) as i16,
                    battery_remaining: self.battery.remaining_pct(),
                    ..SYS_STATUS_DATA::default()
                })
            }
            HOME_POSITION_ID => MavMessage::HOME_POSITION(HOME_POSITION_DATA {
                latitude: (self.cfg.home.lat_deg * 1e7).round() as i32,
                longitude: (self.cfg.home.lon_deg * 1e7).round() as i32,
                altitude: (self.cfg.home.alt_m * 1000.0).round() as i32,
                q: [1.0, 0.0, 0.0, 0.0],
                ..HOME_POSITION_DATA::default()
            }),
            AUTOPILOT_VERSION_ID => MavMessage::AUTOPILOT_VERSION(AUTOPILOT_VERSION_DATA {
                capabilities: MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_INT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MAVLINK2,
                ..AUTOPILOT_VERSION_DATA::default()
            }),
            MISSION_CURRENT_ID
                if !self.quiet_progress && !self.profile.mission_current_on_change_only() =>
            {
                self.mission_current()
            }
            _ => return None,
        })
    }

    pub(super) fn param_value(&self, index: usize) -> Option<MavMessage> {
        let p = self.params.by_index(index)?;
        Some(MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: p.value,
            param_count: self.params.len() as u16,
            param_index: index as u16,
            param_id: p.name.into(),
            param_type: p.kind,
        }))
    }
}

//! The simulated vehicle's incoming side: one handler per MAVLink message it understands, commands, takeoff
//! and mission items.

use mavlink::dialects::ardupilotmega::{
    MavMissionResult, MavMissionType, MISSION_ACK_DATA, MISSION_CLEAR_ALL_DATA, MISSION_COUNT_DATA,
    MISSION_REQUEST_LIST_DATA,
};

use super::*;

impl Vehicle {
    // ---------------------------------------------------------------- messages in

    /// Handles one message from `from` (system, component); returns the replies.
    pub fn handle(&mut self, from: (u8, u8), msg: &MavMessage, now: Instant) -> Vec<MavMessage> {
        let mut out = Vec::new();
        match msg {
            MavMessage::COMMAND_LONG(c) if self.for_us(c.target_system) => {
                let result = self.command(c, now, &mut out);
                out.push(command_ack(c.command, result));
            }
            // PX4 takes DO_REPOSITION as COMMAND_INT (lat/lon in 1e-7 degrees); nothing else
            // arrives that way here.
            MavMessage::COMMAND_INT(c) if self.for_us(c.target_system) => {
                let result = match c.command {
                    MavCmd::MAV_CMD_DO_REPOSITION if self.profile == Profile::Px4 => self
                        .px4_reposition(
                            [c.param1, c.param2, c.param4],
                            // INT32_MAX: unchanged (where it is), as in PX4.
                            if c.x == i32::MAX || c.y == i32::MAX {
                                (f64::NAN, f64::NAN)
                            } else {
                                (f64::from(c.x) / 1e7, f64::from(c.y) / 1e7)
                            },
                            c.z,
                            &mut out,
                        ),
                    _ => MavResult::MAV_RESULT_UNSUPPORTED,
                };
                out.push(command_ack(c.command, result));
            }
            MavMessage::SET_MODE(m) if self.for_us(m.target_system) => {
                let result = match self.profile.decode_mode(self.cfg.kind, m.custom_mode) {
                    Some(_) if self.not_ready() => MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
                    Some(mode) => self.change_mode(mode, &mut out),
                    None => MavResult::MAV_RESULT_DENIED,
                };
                out.push(command_ack(MavCmd::MAV_CMD_DO_SET_MODE, result));
            }
            MavMessage::REQUEST_DATA_STREAM(r) if self.for_us(r.target_system) => {
                let ids: &[u32] = match r.req_stream_id {
                    MavDataStream::MAV_DATA_STREAM_ALL => &STREAMABLE,
                    MavDataStream::MAV_DATA_STREAM_EXTENDED_STATUS => {
                        &[SYS_STATUS_ID, MISSION_CURRENT_ID]
                    }
                    MavDataStream::MAV_DATA_STREAM_POSITION => &[GLOBAL_POSITION_INT_ID],
                    MavDataStream::MAV_DATA_STREAM_EXTRA1 => &[ATTITUDE_ID],
                    MavDataStream::MAV_DATA_STREAM_EXTRA2 => &[VFR_HUD_ID],
                    _ => &[],
                };
                let hz = if r.start_stop == 0 {
                    0.0
                } else {
                    f64::from(r.req_message_rate)
                };
                for &id in ids {
                    self.set_rate(id, hz, now);
                }
            }
            MavMessage::RC_CHANNELS_OVERRIDE(rc) if self.for_us(rc.target_system) => {
                let prev = self.sticks.map(|(s, _)| s).unwrap_or_default();
                let steer = pwm_to_unit(rc.chan1_raw).unwrap_or(prev.steer);
                let throttle = pwm_to_unit(rc.chan3_raw).unwrap_or(prev.throttle);
                self.sticks = Some((Sticks { steer, throttle }, now));
            }
            MavMessage::PARAM_REQUEST_LIST(r) if self.for_us(r.target_system) => {
                out.extend((0..self.params.len()).filter_map(|i| self.param_value(i)));
            }
            MavMessage::PARAM_REQUEST_READ(r) if self.for_us(r.target_system) => {
                let index = if r.param_index >= 0 {
                    Some(r.param_index as usize)
                } else {
                    r.param_id
                        .to_str()
                        .ok()
                        .and_then(|name| self.params.by_name(name).map(|(i, _)| i))
                };
                out.extend(index.and_then(|i| self.param_value(i)));
            }
            MavMessage::PARAM_SET(s) if self.for_us(s.target_system) => {
                // Unknown names get no answer, as in ArduPilot.
                if let Some(index) = s
                    .param_id
                    .to_str()
                    .ok()
                    .and_then(|n| self.params.set(n, s.param_value))
                {
                    out.extend(self.param_value(index));
                }
            }
            // The fence (`fence.rs`): its own transfer, beside the mission.
            MavMessage::MISSION_COUNT(c)
                if self.for_us(c.target_system)
                    && c.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE =>
            {
                out.extend(self.fence.on_count(from, c.count));
                if c.count == 0 {
                    self.record(LogEvent::FenceUploaded {
                        vertices: 0,
                        circle_m: None,
                    });
                }
            }
            MavMessage::MISSION_ITEM_INT(item)
                if self.for_us(item.target_system)
                    && item.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE =>
            {
                let (replies, done) = self.fence.on_item(from, item.clone(), &self.frame);
                out.extend(replies);
                if let Some(vertices) = done {
                    let circle_m = self.fence.circle_m();
                    self.record(LogEvent::FenceUploaded { vertices, circle_m });
                }
            }
            MavMessage::MISSION_CLEAR_ALL(c)
                if self.for_us(c.target_system)
                    && c.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE =>
            {
                out.extend(self.fence.on_clear(from));
                self.record(LogEvent::FenceUploaded {
                    vertices: 0,
                    circle_m: None,
                });
            }
            MavMessage::MISSION_ACK(a)
                if self.for_us(a.target_system)
                    && a.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE =>
            {
                self.fence.on_ack();
            }
            // Rally points (and fence downloads) are not simulated: refused, so a ground
            // station does not take them for the mission.
            MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                target_system,
                mission_type,
                ..
            })
            | MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
                target_system,
                mission_type,
                ..
            })
            | MavMessage::MISSION_CLEAR_ALL(MISSION_CLEAR_ALL_DATA {
                target_system,
                mission_type,
                ..
            }) if self.for_us(*target_system)
                && *mission_type != MavMissionType::MAV_MISSION_TYPE_MISSION =>
            {
                out.push(MavMessage::MISSION_ACK(MISSION_ACK_DATA {
                    target_system: from.0,
                    target_component: from.1,
                    mavtype: MavMissionResult::MAV_MISSION_UNSUPPORTED,
                    mission_type: *mission_type,
                    ..Default::default()
                }));
            }
            MavMessage::MISSION_COUNT(c) if self.for_us(c.target_system) => {
                out.extend(self.mission.on_count(from, c.count, now));
            }
            // Without partial writes (PX4, generic): unanswered, as the autopilots that lack it.
            MavMessage::MISSION_WRITE_PARTIAL_LIST(p)
                if self.for_us(p.target_system) && self.profile.partial_writes() =>
            {
                out.extend(
                    self.mission
                        .on_partial(from, p.start_index, p.end_index, now),
                );
            }
            MavMessage::MISSION_ITEM_INT(item)
                if self.for_us(item.target_system)
                    && item.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
            {
                self.mission_item(from, item.clone(), now, &mut out);
            }
            MavMessage::MISSION_ITEM(item)
                if self.for_us(item.target_system)
                    && item.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
            {
                self.mission_item(from, mission::item_from_float(item), now, &mut out);
            }
            MavMessage::MISSION_REQUEST_LIST(r) if self.for_us(r.target_system) => {
                out.push(self.mission.on_request_list(from));
            }
            MavMessage::MISSION_REQUEST_INT(r) if self.for_us(r.target_system) => {
                out.push(self.mission.on_request(from, r.seq, true));
            }
            MavMessage::MISSION_REQUEST(r) if self.for_us(r.target_system) => {
                out.push(self.mission.on_request(from, r.seq, false));
            }
            MavMessage::MISSION_ACK(a) if self.for_us(a.target_system) => {
                self.mission.on_ack(from);
            }
            MavMessage::MISSION_CLEAR_ALL(c) if self.for_us(c.target_system) => {
                let (replies, change) = self.mission.on_clear(from);
                out.extend(replies);
                self.mission_changed(change, &mut out);
            }
            MavMessage::MISSION_SET_CURRENT(s) if self.for_us(s.target_system) => {
                let changed = self.set_current(s.seq, &mut out);
                if !changed {
                    // Refused: tell the client what is current instead.
                    out.push(self.mission_current());
                }
            }
            _ => {}
        }
        out
    }

    /// MAV_CMD_NAV_TAKEOFF as a command: as ArduCopter, only armed, in GUIDED, on the ground;
    /// climbs straight up to `alt` metres above home, then holds there.
    fn takeoff(&mut self, alt: f32) -> MavResult {
        if self.cfg.kind != VehicleKind::Copter {
            return MavResult::MAV_RESULT_UNSUPPORTED;
        }
        if !alt.is_finite() || alt <= 0.0 {
            return MavResult::MAV_RESULT_DENIED;
        }
        if !self.armed || self.behaviour() != Behaviour::Guided || self.state.pos.up > 1.0 {
            return MavResult::MAV_RESULT_FAILED;
        }
        self.takeoff_to = Some(Ned {
            up: f64::from(alt),
            ..self.state.pos
        });
        MavResult::MAV_RESULT_ACCEPTED
    }

    /// MAV_CMD_DO_REPOSITION as a COMMAND_LONG (no frame: the altitude is MSL): in GUIDED,
    /// fly to the point (at param1 m/s when positive), then hold there.
    fn guided_reposition(&mut self, c: &COMMAND_LONG_DATA) -> MavResult {
        let (lat, lon, alt) = (
            f64::from(c.param5),
            f64::from(c.param6),
            f64::from(c.param7),
        );
        if !(lat.is_finite() && lon.is_finite() && alt.is_finite())
            || lat.abs() > 90.0
            || lon.abs() > 180.0
        {
            return MavResult::MAV_RESULT_DENIED;
        }
        if self.behaviour() != Behaviour::Guided || !self.armed {
            return MavResult::MAV_RESULT_FAILED;
        }
        let mut to = self.frame.to_local(GeoPoint {
            lat_deg: lat,
            lon_deg: lon,
            alt_m: 0.0,
        });
        to.up = if self.cfg.kind == VehicleKind::Rover {
            0.0
        } else {
            alt - self.cfg.home.alt_m
        };
        if c.param1.is_finite() && c.param1 > 0.0 {
            self.change_speed(c.param1);
        }
        self.guided_to = Some(to);
        self.record(LogEvent::Repositioned {
            lat,
            lon,
            alt: to.up,
        });
        MavResult::MAV_RESULT_ACCEPTED
    }

    /// MAV_CMD_DO_REPOSITION as PX4 does it: with the CHANGE_MODE flag (param2 bit 0), or
    /// already holding, the vehicle switches to its hold mode (AUTO.LOITER), goes to
    /// (lat, lon) at the ground speed `param1` (when positive) and holds there. A NaN or zero
    /// position means where it is; a NaN altitude its own (above home).
    /// `params` are param1 (speed), param2 (flags) and param4 (yaw, ignored).
    fn px4_reposition(
        &mut self,
        params: [f32; 3],
        (lat, lon): (f64, f64),
        alt: f32,
        out: &mut Vec<MavMessage>,
    ) -> MavResult {
        let [speed, flags, _yaw] = params;
        let change_mode = flags.is_finite() && (flags as u32) & 1 == 1;
        if !change_mode && self.behaviour() != Behaviour::Hold {
            return MavResult::MAV_RESULT_DENIED;
        }
        if !self.armed {
            // PX4 refuses to move a disarmed vehicle.
            return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
        }
        let here = !lat.is_finite() || !lon.is_finite() || (lat == 0.0 && lon == 0.0);
        if !here && (lat.abs() > 90.0 || lon.abs() > 180.0) {
            return MavResult::MAV_RESULT_DENIED;
        }
        // PX4's AUTO.LOITER: the first mode of the table with that encoding.
        let Some(hold) = self.profile.decode_mode(self.cfg.kind, 4 << 16 | 3 << 24) else {
            return MavResult::MAV_RESULT_UNSUPPORTED;
        };
        if self.behaviour() != Behaviour::Hold {
            let r = self.change_mode(hold, out);
            if r != MavResult::MAV_RESULT_ACCEPTED {
                return r;
            }
        }
        let geo = if here {
            self.frame.to_geo(self.state.pos)
        } else {
            GeoPoint {
                lat_deg: lat,
                lon_deg: lon,
                alt_m: 0.0,
            }
        };
        let mut pos = if here {
            self.state.pos
        } else {
            self.frame.to_local(geo)
        };
        pos.up = match self.cfg.kind {
            VehicleKind::Rover => 0.0,
            _ if alt.is_finite() => f64::from(alt),
            _ => self.state.pos.up,
        };
        if speed.is_finite() && speed > 0.0 {
            self.change_speed(speed);
        }
        self.hold_point = pos;
        self.reposition = Some((pos, geo));
        self.record(LogEvent::Repositioned {
            lat: geo.lat_deg,
            lon: geo.lon_deg,
            alt: pos.up,
        });
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn mission_item(
        &mut self,
        from: (u8, u8),
        item: Item,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        let (replies, change) = self.mission.on_item(from, item, self.cfg.home, now);
        out.extend(replies);
        if let Some(change) = change {
            self.mission_changed(change, out);
        }
    }

    /// On ArduPilot a committed mission change never moves the memorised target (003
    /// §2.5.4); PX4 and generic autopilots reset the current item to 0 after a whole upload
    /// (and drive to it in a mission).
    fn mission_changed(&mut self, change: Change, out: &mut Vec<MavMessage>) {
        let uploaded = matches!(change, Change::Uploaded { .. });
        let event = match change {
            Change::Uploaded { count } => LogEvent::MissionUploaded { count },
            Change::PartialWrite { start, end } => LogEvent::MissionPartialWrite { start, end },
            Change::Cleared => LogEvent::MissionCleared,
        };
        self.record(event);
        if uploaded && self.profile.resets_current_on_upload() {
            if self.behaviour() == Behaviour::Auto {
                self.target = None;
                self.go_to_index(0, "upload_reset", out);
            } else if self.current != 0 {
                self.current = 0;
                out.push(self.mission_current());
                self.record(LogEvent::CurrentChanged {
                    seq: 0,
                    cause: "upload_reset".to_owned(),
                });
            }
        }
    }

    fn command(
        &mut self,
        c: &COMMAND_LONG_DATA,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) -> MavResult {
        match c.command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM | MavCmd::MAV_CMD_DO_SET_MODE
                if self.not_ready() =>
            {
                MavResult::MAV_RESULT_TEMPORARILY_REJECTED
            }
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                if c.param1 == 1.0 && self.behaviour() == Behaviour::Land {
                    // As ArduCopter: LAND is not a mode to arm in.
                    out.push(statustext(
                        MavSeverity::MAV_SEVERITY_CRITICAL,
                        "Arm: Mode not armable",
                    ));
                    return MavResult::MAV_RESULT_FAILED;
                }
                if c.param1 == 1.0 {
                    self.set_armed(true, out);
                } else if c.param1 == 0.0 {
                    self.set_armed(false, out);
                } else {
                    return MavResult::MAV_RESULT_DENIED;
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_DO_SET_MODE => {
                if c.param2 < 0.0 || !c.param2.is_finite() {
                    return MavResult::MAV_RESULT_DENIED;
                }
                // PX4 takes (main, sub) in param2 and param3.
                let custom = if self.profile == Profile::Px4 {
                    let sub = if c.param3.is_finite() && c.param3 >= 0.0 {
                        c.param3 as u32
                    } else {
                        0
                    };
                    (c.param2 as u32) << 16 | sub << 24
                } else {
                    c.param2 as u32
                };
                match self.profile.decode_mode(self.cfg.kind, custom) {
                    Some(mode) => self.change_mode(mode, out),
                    None => MavResult::MAV_RESULT_DENIED,
                }
            }
            MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT => {
                if c.param1 < 0.0 || !c.param1.is_finite() || c.param1 > f32::from(u16::MAX) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                if self.set_current(c.param1 as u16, out) {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                let id = c.param1 as u32;
                if id == 0 {
                    // HEARTBEAT stays at 1 Hz.
                    return MavResult::MAV_RESULT_ACCEPTED;
                }
                if !STREAMABLE.contains(&id) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                let hz = match c.param2 {
                    x if x < 0.0 => 0.0,
                    0.0 => 1.0,
                    us => 1e6 / f64::from(us),
                };
                self.set_rate(id, hz, now);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_NAV_TAKEOFF => self.takeoff(c.param7),
            // PX4 also takes DO_REPOSITION as COMMAND_LONG (degrees as floats).
            MavCmd::MAV_CMD_DO_REPOSITION if self.profile == Profile::Px4 => self.px4_reposition(
                [c.param1, c.param2, c.param4],
                (f64::from(c.param5), f64::from(c.param6)),
                c.param7,
                out,
            ),
            // ArduPilot: a guided target, in GUIDED.
            MavCmd::MAV_CMD_DO_REPOSITION => self.guided_reposition(c),
            // PX4: into the mission (AUTO.MISSION), from item param1 when given.
            MavCmd::MAV_CMD_MISSION_START if self.profile == Profile::Px4 => {
                let Some(auto) = modes::table(self.cfg.kind)
                    .iter()
                    .find(|m| m.2 == Behaviour::Auto)
                    .map(|m| m.0)
                else {
                    return MavResult::MAV_RESULT_UNSUPPORTED;
                };
                if c.param1.is_finite() && c.param1 >= 1.0 && c.param1 < f32::from(u16::MAX) {
                    self.current = c.param1 as u16;
                }
                self.change_mode(auto, out)
            }
            MavCmd::MAV_CMD_GET_HOME_POSITION => {
                out.extend(self.telemetry(HOME_POSITION_ID));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES => {
                out.extend(self.telemetry(AUTOPILOT_VERSION_ID));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_DO_CHANGE_SPEED => {
                if self.change_speed(c.param2) {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_REQUEST_MESSAGE => match c.param1 as u32 {
                0 => {
                    out.push(self.heartbeat());
                    MavResult::MAV_RESULT_ACCEPTED
                }
                id => match self.telemetry(id) {
                    Some(m) => {
                        out.push(m);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    None => MavResult::MAV_RESULT_UNSUPPORTED,
                },
            },
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
    }
}

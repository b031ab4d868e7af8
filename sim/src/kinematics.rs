//! Flat-earth local tangent plane and the rover / copter / plane motion models.
//!
//! Positions live in metres north/east of home and metres up; the conversion to
//! latitude/longitude is the equirectangular approximation, which is well under
//! a centimetre off over the few kilometres a test mission spans.

use std::f64::consts::PI;

/// WGS-84 equatorial radius, metres.
const EARTH_RADIUS_M: f64 = 6_378_137.0;

/// A geographic position: degrees and metres above mean sea level.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeoPoint {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_m: f64,
}

/// A point in the local frame: metres north and east of home, metres above home.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Ned {
    /// Metres north of home.
    pub north: f64,
    /// Metres east of home.
    pub east: f64,
    /// Metres above home (positive up, unlike a true NED down axis).
    pub up: f64,
}

impl Ned {
    /// Horizontal distance to `other`, metres.
    pub fn horizontal_distance(&self, other: &Ned) -> f64 {
        (other.north - self.north).hypot(other.east - self.east)
    }
}

/// The tangent plane at home.
#[derive(Clone, Copy, Debug)]
pub struct LocalFrame {
    home: GeoPoint,
    cos_lat: f64,
}

impl LocalFrame {
    /// A tangent plane centred on `home`.
    pub fn new(home: GeoPoint) -> Self {
        Self {
            home,
            cos_lat: home.lat_deg.to_radians().cos().max(1e-6),
        }
    }

    /// The home position this frame is centred on.
    pub fn home(&self) -> GeoPoint {
        self.home
    }

    /// Geographic position to local metres.
    pub fn to_local(&self, p: GeoPoint) -> Ned {
        Ned {
            north: (p.lat_deg - self.home.lat_deg).to_radians() * EARTH_RADIUS_M,
            east: (p.lon_deg - self.home.lon_deg).to_radians() * EARTH_RADIUS_M * self.cos_lat,
            up: p.alt_m - self.home.alt_m,
        }
    }

    /// Local metres to a geographic position.
    pub fn to_geo(&self, p: Ned) -> GeoPoint {
        GeoPoint {
            lat_deg: self.home.lat_deg + (p.north / EARTH_RADIUS_M).to_degrees(),
            lon_deg: self.home.lon_deg + (p.east / (EARTH_RADIUS_M * self.cos_lat)).to_degrees(),
            alt_m: self.home.alt_m + p.up,
        }
    }
}

/// Which motion model the vehicle follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum VehicleKind {
    /// Ground rover: speed along the heading, turn-rate limited, can stop.
    Rover,
    /// Multicopter: moves straight toward its target in 3D, can hover.
    Copter,
    /// Fixed wing: constant airspeed, turn-rate limited, loiters instead of stopping.
    Plane,
}

/// Performance limits of the motion model, from the vehicle's parameters.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Cruise speed, m/s.
    pub cruise_speed: f64,
    /// Maximum yaw rate, rad/s.
    pub max_yaw_rate: f64,
    /// Maximum longitudinal acceleration, m/s².
    pub max_accel: f64,
    /// Maximum climb/descent rate, m/s (copter and plane).
    pub max_climb: f64,
    /// Loiter radius, metres (plane).
    pub loiter_radius: f64,
    /// The air mass's velocity, metres per second north and east (a steady wind blowing
    /// *toward* that direction): a plane flies through the air and drifts with it, crabbing
    /// into it to hold its track; a copter leans into it, its ground speed what its top speed
    /// leaves. A rover feels none.
    pub wind: (f64, f64),
    /// The slowest airspeed a plane flies, m/s: asked to go slower, it flies this fast.
    pub stall_speed: f64,
}

impl Limits {
    /// Limits of no particular vehicle: no wind, no stall.
    pub fn calm(cruise_speed: f64, max_yaw_rate: f64, max_accel: f64, max_climb: f64) -> Self {
        Self {
            cruise_speed,
            max_yaw_rate,
            max_accel,
            max_climb,
            loiter_radius: 0.0,
            wind: (0.0, 0.0),
            stall_speed: 0.0,
        }
    }
}

/// A steady wind of `speed` m/s blowing *from* `from_deg` (degrees clockwise from north, as a
/// forecast gives it) as the air's velocity north and east.
pub fn wind_from(speed: f64, from_deg: f64) -> (f64, f64) {
    let to = (from_deg + 180.0).to_radians();
    (speed * to.cos(), speed * to.sin())
}

/// What the vehicle is asked to do during one step.
#[derive(Clone, Copy, Debug)]
pub enum Command {
    /// Go toward this point.
    GoTo(Ned),
    /// Stop (rover, copter) or circle around this point (plane).
    Hold(Ned),
    /// Normalised stick inputs: steering/roll in -1..1, throttle in -1..1
    /// (rover: signed speed; copter: climb; plane: ignored, it keeps cruise speed).
    Sticks {
        /// Steering (rover) or roll (aircraft), -1 left .. 1 right.
        steer: f64,
        /// Throttle, -1 .. 1.
        throttle: f64,
    },
}

/// The fastest a plane rolls on the ground under the sticks, m/s: a brisk taxi, well under any
/// take-off speed.
pub const TAXI_SPEED_MAX: f64 = 8.0;

/// The kinematic state of the vehicle.
#[derive(Clone, Copy, Debug, Default)]
pub struct State {
    /// Position in the local frame.
    pub pos: Ned,
    /// Heading, radians clockwise from north, in [0, 2π).
    pub yaw: f64,
    /// Ground speed along the heading (rover, plane) or along the velocity (copter), m/s.
    pub speed: f64,
    /// Velocity north, m/s.
    pub vel_north: f64,
    /// Velocity east, m/s.
    pub vel_east: f64,
    /// Climb rate, m/s (positive up).
    pub climb: f64,
    /// Yaw rate of the last step, rad/s.
    pub yaw_rate: f64,
    /// Bank angle of the last step, radians (plane and copter, cosmetic).
    pub roll: f64,
}

/// Wraps an angle to (-π, π].
pub fn wrap_pi(a: f64) -> f64 {
    let mut a = a % (2.0 * PI);
    if a > PI {
        a -= 2.0 * PI;
    } else if a <= -PI {
        a += 2.0 * PI;
    }
    a
}

/// The heading correction (radians, to add to `course`) that holds a ground track along
/// `course` at `airspeed` in `wind`: the plane points into the crosswind. A crosswind stronger
/// than the airspeed cannot be crabbed: the plane points straight into it and drifts.
fn crab(course: f64, airspeed: f64, wind: (f64, f64)) -> f64 {
    // The wind's component across the course, positive from the left (pushing right).
    let cross = -wind.0 * course.sin() + wind.1 * course.cos();
    -(cross / airspeed.max(0.1)).clamp(-1.0, 1.0).asin()
}

/// The ground velocity a copter makes good when it wants `ground` (north, east) in the wind
/// of `limits`: the air velocity that needs, cut to its top speed, plus the wind.
fn against_wind(ground: (f64, f64), limits: &Limits) -> (f64, f64) {
    let (wn, we) = limits.wind;
    let (an, ae) = (ground.0 - wn, ground.1 - we);
    let air = an.hypot(ae);
    let top = limits.cruise_speed.max(0.1);
    let scale = if air > top { top / air } else { 1.0 };
    (an * scale + wn, ae * scale + we)
}

/// Bearing from `from` to `to`, radians clockwise from north.
pub fn bearing(from: &Ned, to: &Ned) -> f64 {
    (to.east - from.east).atan2(to.north - from.north)
}

fn approach(value: f64, target: f64, max_delta: f64) -> f64 {
    value + (target - value).clamp(-max_delta, max_delta)
}

impl State {
    /// A vehicle at rest at `pos`, heading north.
    pub fn at(pos: Ned) -> Self {
        Self {
            pos,
            ..Self::default()
        }
    }

    /// Integrates one fixed step of `dt` seconds.
    pub fn step(&mut self, kind: VehicleKind, cmd: Command, limits: &Limits, dt: f64) {
        match kind {
            VehicleKind::Rover => self.step_rover(cmd, limits, dt),
            VehicleKind::Copter => self.step_copter(cmd, limits, dt),
            VehicleKind::Plane => self.step_plane(cmd, limits, dt),
        }
        self.yaw = self.yaw.rem_euclid(2.0 * PI);
    }

    /// Turns toward `desired` heading at most at the yaw-rate limit; returns the
    /// heading error left after the turn.
    fn turn_toward(&mut self, desired: f64, limits: &Limits, dt: f64) -> f64 {
        let err = wrap_pi(desired - self.yaw);
        let turn = err.clamp(-limits.max_yaw_rate * dt, limits.max_yaw_rate * dt);
        self.yaw += turn;
        self.yaw_rate = turn / dt;
        wrap_pi(desired - self.yaw)
    }

    fn advance_along_heading(&mut self, dt: f64) {
        self.vel_north = self.speed * self.yaw.cos();
        self.vel_east = self.speed * self.yaw.sin();
        self.pos.north += self.vel_north * dt;
        self.pos.east += self.vel_east * dt;
    }

    fn step_rover(&mut self, cmd: Command, limits: &Limits, dt: f64) {
        let target_speed = match cmd {
            Command::GoTo(target) => {
                let dist = self.pos.horizontal_distance(&target);
                let err = self.turn_toward(bearing(&self.pos, &target), limits, dt);
                // Slow down while pointing away so the turn radius shrinks and the
                // rover cannot orbit a waypoint; slow on the final metres so it
                // does not overshoot by more than a step.
                let align = err.cos().max(0.1);
                (limits.cruise_speed * align).min(dist / dt)
            }
            Command::Hold(_) => {
                self.yaw_rate = 0.0;
                0.0
            }
            Command::Sticks { steer, throttle } => {
                let steer = steer.clamp(-1.0, 1.0);
                let turn = steer * limits.max_yaw_rate * dt;
                // Ackermann steering: no turning in place.
                let turn = if self.speed.abs() > 0.05 { turn } else { 0.0 };
                self.yaw += turn;
                self.yaw_rate = turn / dt;
                throttle.clamp(-1.0, 1.0) * limits.cruise_speed
            }
        };
        self.speed = approach(self.speed, target_speed, limits.max_accel * dt);
        self.climb = 0.0;
        self.roll = 0.0;
        self.advance_along_heading(dt);
    }

    /// A plane on its wheels under the sticks: the throttle (from its bottom, -1, idle) sets
    /// the ground speed, up to [`TAXI_SPEED_MAX`], the steering turns it as a rover's does; it
    /// never leaves the ground (taking off is the TAKEOFF mode's) and the wind does not push
    /// it.
    fn taxi(&mut self, steer: f64, throttle: f64, limits: &Limits, dt: f64) {
        let open = (throttle.clamp(-1.0, 1.0) + 1.0) / 2.0;
        let target = (open * limits.cruise_speed).min(TAXI_SPEED_MAX);
        if self.speed.abs() > 0.05 {
            let turn = steer.clamp(-1.0, 1.0) * limits.max_yaw_rate * dt;
            self.yaw += turn;
            self.yaw_rate = turn / dt;
        } else {
            self.yaw_rate = 0.0;
        }
        self.speed = approach(self.speed, target, limits.max_accel * dt);
        self.climb = 0.0;
        self.roll = 0.0;
        self.pos.up = 0.0;
        self.advance_along_heading(dt);
    }

    fn step_copter(&mut self, cmd: Command, limits: &Limits, dt: f64) {
        let (vn, ve, vu) = match cmd {
            Command::GoTo(target) => {
                let dn = target.north - self.pos.north;
                let de = target.east - self.pos.east;
                let du = target.up - self.pos.up;
                let horizontal = dn.hypot(de);
                if horizontal > 0.5 {
                    self.turn_toward(de.atan2(dn), limits, dt);
                } else {
                    self.yaw_rate = 0.0;
                }
                // Never step past the target.
                let h_speed = limits.cruise_speed.min(horizontal / dt);
                let (vn, ve) = if horizontal > 1e-9 {
                    (dn / horizontal * h_speed, de / horizontal * h_speed)
                } else {
                    (0.0, 0.0)
                };
                let (vn, ve) = against_wind((vn, ve), limits);
                (
                    vn,
                    ve,
                    du.clamp(-limits.max_climb, limits.max_climb)
                        .clamp(-du.abs() / dt, du.abs() / dt),
                )
            }
            Command::Hold(_) => {
                self.yaw_rate = 0.0;
                let (vn, ve) = against_wind((0.0, 0.0), limits);
                (vn, ve, 0.0)
            }
            Command::Sticks { steer, throttle } => {
                let turn = steer.clamp(-1.0, 1.0) * limits.max_yaw_rate * dt;
                self.yaw += turn;
                self.yaw_rate = turn / dt;
                let (vn, ve) = against_wind((0.0, 0.0), limits);
                (vn, ve, throttle.clamp(-1.0, 1.0) * limits.max_climb)
            }
        };
        let max_dv = limits.max_accel * dt;
        self.vel_north = approach(self.vel_north, vn, max_dv);
        self.vel_east = approach(self.vel_east, ve, max_dv);
        self.climb = approach(self.climb, vu, max_dv);
        self.pos.north += self.vel_north * dt;
        self.pos.east += self.vel_east * dt;
        self.pos.up = (self.pos.up + self.climb * dt).max(0.0);
        self.speed = self.vel_north.hypot(self.vel_east);
        self.roll = 0.0;
    }

    fn step_plane(&mut self, cmd: Command, limits: &Limits, dt: f64) {
        if let (Command::Sticks { steer, throttle }, true) = (cmd, self.pos.up <= 0.0) {
            self.taxi(steer, throttle, limits, dt);
            return;
        }
        let airspeed = limits.cruise_speed.max(limits.stall_speed);
        let target_up = match cmd {
            Command::GoTo(target) => {
                let course = bearing(&self.pos, &target);
                self.turn_toward(course + crab(course, airspeed, limits.wind), limits, dt);
                target.up
            }
            Command::Hold(centre) => {
                // Circle clockwise: aim at the tangent point of the loiter circle.
                let dist = self.pos.horizontal_distance(&centre);
                let to_centre = bearing(&self.pos, &centre);
                let offset = if dist > limits.loiter_radius {
                    (limits.loiter_radius / dist).asin()
                } else {
                    PI / 2.0 * (dist / limits.loiter_radius.max(1.0)).max(0.5)
                };
                let course = to_centre - offset;
                self.turn_toward(course + crab(course, airspeed, limits.wind), limits, dt);
                centre.up
            }
            Command::Sticks { steer, .. } => {
                let turn = steer.clamp(-1.0, 1.0) * limits.max_yaw_rate * dt;
                self.yaw += turn;
                self.yaw_rate = turn / dt;
                self.pos.up
            }
        };
        // `speed` is the airspeed along the heading; the ground velocity adds the wind.
        self.speed = approach(self.speed, airspeed, limits.max_accel * dt);
        let du = target_up - self.pos.up;
        self.climb = du
            .clamp(-limits.max_climb, limits.max_climb)
            .clamp(-du.abs() / dt, du.abs() / dt);
        self.pos.up += self.climb * dt;
        // Coordinated turn: tan(roll) = v * yaw_rate / g.
        self.roll = (self.speed * self.yaw_rate / 9.81).atan();
        self.vel_north = self.speed * self.yaw.cos() + limits.wind.0;
        self.vel_east = self.speed * self.yaw.sin() + limits.wind.1;
        self.pos.north += self.vel_north * dt;
        self.pos.east += self.vel_east * dt;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOME: GeoPoint = GeoPoint {
        lat_deg: 41.2757,
        lon_deg: 1.9881,
        alt_m: 10.0,
    };

    fn limits() -> Limits {
        Limits {
            loiter_radius: 30.0,
            ..Limits::calm(2.0, 90f64.to_radians(), 2.0, 2.0)
        }
    }

    #[test]
    fn local_frame_round_trips() {
        let frame = LocalFrame::new(HOME);
        let p = Ned {
            north: 123.4,
            east: -56.7,
            up: 8.0,
        };
        let back = frame.to_local(frame.to_geo(p));
        assert!((back.north - p.north).abs() < 1e-6);
        assert!((back.east - p.east).abs() < 1e-6);
        assert!((back.up - p.up).abs() < 1e-9);
        // One degree of latitude is about 111 km.
        let north = frame.to_local(GeoPoint {
            lat_deg: HOME.lat_deg + 1.0,
            ..HOME
        });
        assert!((north.north - 111_319.0).abs() < 50.0, "{north:?}");
    }

    #[test]
    fn a_plane_on_its_wheels_taxis_under_the_sticks_and_never_takes_off() {
        let limits = Limits {
            stall_speed: 9.0,
            wind: (0.0, 5.0),
            ..Limits::calm(18.0, 30f64.to_radians(), 3.0, 4.0)
        };
        let mut s = State::at(Ned::default());
        let sticks = |steer, throttle| Command::Sticks { steer, throttle };
        // Idle: stands still, the wind does not push it.
        for _ in 0..50 {
            s.step(VehicleKind::Plane, sticks(0.0, -1.0), &limits, 0.1);
        }
        assert!(
            s.pos.north.abs() < 1e-9 && s.pos.east.abs() < 1e-9,
            "{:?}",
            s.pos
        );
        // Full throttle on the ground: a taxi, capped, never airborne; steering turns it.
        for _ in 0..200 {
            s.step(VehicleKind::Plane, sticks(0.5, 1.0), &limits, 0.1);
        }
        assert!((s.speed - TAXI_SPEED_MAX).abs() < 1e-9, "{}", s.speed);
        assert_eq!(s.pos.up, 0.0);
        assert!(s.yaw.abs() > 1.0, "it turned: {}", s.yaw);
        // A third of the throttle's travel: a third of cruise, under the cap.
        let mut s = State::at(Ned::default());
        for _ in 0..100 {
            s.step(
                VehicleKind::Plane,
                sticks(0.0, -1.0 + 2.0 / 3.0),
                &limits,
                0.1,
            );
        }
        assert!((s.speed - 6.0).abs() < 1e-6, "{}", s.speed);
    }

    #[test]
    fn wrap_pi_stays_in_range() {
        for a in [-10.0, -PI, -0.1, 0.0, PI, 3.5, 12.0] {
            let w = wrap_pi(a);
            assert!(w > -PI - 1e-12 && w <= PI + 1e-12, "{a} -> {w}");
        }
    }

    fn drive_to(kind: VehicleKind, target: Ned, radius: f64, max_steps: usize) -> (State, usize) {
        let mut s = State::at(Ned::default());
        for i in 0..max_steps {
            if s.pos.horizontal_distance(&target) <= radius {
                return (s, i);
            }
            s.step(kind, Command::GoTo(target), &limits(), 0.02);
        }
        panic!("{kind:?} never reached {target:?}, ended at {:?}", s.pos);
    }

    #[test]
    fn rover_reaches_a_target_behind_it() {
        let target = Ned {
            north: -30.0,
            east: 10.0,
            up: 0.0,
        };
        let (s, steps) = drive_to(VehicleKind::Rover, target, 2.0, 10_000);
        // ~32 m at 2 m/s plus the turn: well under a minute of simulated time.
        assert!(steps < 50 * 40, "took {steps} steps");
        assert!(s.speed <= 2.0 + 1e-9);
    }

    #[test]
    fn rover_stops_on_hold() {
        let mut s = State::at(Ned::default());
        s.speed = 2.0;
        for _ in 0..100 {
            s.step(VehicleKind::Rover, Command::Hold(s.pos), &limits(), 0.02);
        }
        assert_eq!(s.speed, 0.0);
    }

    #[test]
    fn rover_sticks_drive_and_steer() {
        let mut s = State::at(Ned::default());
        for _ in 0..200 {
            s.step(
                VehicleKind::Rover,
                Command::Sticks {
                    steer: 0.5,
                    throttle: 1.0,
                },
                &limits(),
                0.02,
            );
        }
        assert!(s.speed > 1.9);
        assert!(s.yaw > 0.1, "steering right turns clockwise");
    }

    #[test]
    fn copter_climbs_and_reaches_3d_target() {
        let target = Ned {
            north: 20.0,
            east: 20.0,
            up: 15.0,
        };
        let mut s = State::at(Ned::default());
        for _ in 0..5_000 {
            s.step(VehicleKind::Copter, Command::GoTo(target), &limits(), 0.02);
        }
        assert!(s.pos.horizontal_distance(&target) < 0.1, "{:?}", s.pos);
        assert!((s.pos.up - 15.0).abs() < 0.1);
    }

    fn plane_limits(wind: (f64, f64)) -> Limits {
        Limits {
            loiter_radius: 60.0,
            wind,
            stall_speed: 9.0,
            ..Limits::calm(15.0, 9.81 / 15.0, 3.0, 5.0)
        }
    }

    #[test]
    fn a_plane_crabs_into_a_crosswind_and_holds_its_track() {
        // 6 m/s from the west (blowing east) across a track due north.
        let l = plane_limits(wind_from(6.0, 270.0));
        let mut s = State::at(Ned::default());
        s.speed = 15.0;
        let target = Ned {
            north: 2_000.0,
            east: 0.0,
            up: 0.0,
        };
        let mut worst_off_track: f64 = 0.0;
        while s.pos.north < 1_900.0 {
            s.step(VehicleKind::Plane, Command::GoTo(target), &l, 0.02);
            if s.pos.north > 300.0 {
                worst_off_track = worst_off_track.max(s.pos.east.abs());
            }
        }
        assert!(
            worst_off_track < 5.0,
            "blown {worst_off_track} m off the track"
        );
        // Pointing into the wind (left of north) by asin(6/15), about 23.6 degrees.
        let heading = wrap_pi(s.yaw).to_degrees();
        assert!((heading + 23.6).abs() < 1.0, "heading {heading}");
        // Over the ground it goes slower than through the air: sqrt(15² - 6²).
        let ground = s.vel_north.hypot(s.vel_east);
        assert!((ground - 13.75).abs() < 0.1, "ground speed {ground}");
    }

    #[test]
    fn a_plane_cannot_fly_against_a_wind_faster_than_itself_and_a_copter_holds_in_its_own() {
        // 20 m/s from the north against a 15 m/s plane heading for a point north of it.
        let l = plane_limits(wind_from(20.0, 0.0));
        let mut s = State::at(Ned::default());
        s.speed = 15.0;
        let target = Ned {
            north: 1_000.0,
            east: 0.0,
            up: 0.0,
        };
        for _ in 0..3_000 {
            s.step(VehicleKind::Plane, Command::GoTo(target), &l, 0.02);
        }
        assert!(s.pos.north < -100.0, "it should be blown back: {:?}", s.pos);
        // A copter with a 5 m/s top speed holds its place in a 4 m/s wind, and drifts in 8.
        for (wind, holds) in [(4.0, true), (8.0, false)] {
            let l = Limits {
                wind: wind_from(wind, 90.0),
                ..Limits::calm(5.0, 1.0, 2.5, 2.5)
            };
            let mut c = State::at(Ned::default());
            for _ in 0..3_000 {
                c.step(VehicleKind::Copter, Command::Hold(Ned::default()), &l, 0.02);
            }
            let drift = c.pos.horizontal_distance(&Ned::default());
            assert_eq!(drift < 1.0, holds, "{wind} m/s: drifted {drift} m");
        }
    }

    #[test]
    fn a_plane_asked_to_fly_below_its_stall_speed_flies_at_it() {
        let mut l = plane_limits((0.0, 0.0));
        l.cruise_speed = 4.0;
        let mut s = State::at(Ned::default());
        s.speed = 15.0;
        for _ in 0..1_000 {
            s.step(VehicleKind::Plane, Command::Hold(Ned::default()), &l, 0.02);
        }
        assert!((s.speed - 9.0).abs() < 1e-6, "{}", s.speed);
    }

    #[test]
    fn plane_keeps_speed_and_circles_on_hold() {
        let mut l = limits();
        l.cruise_speed = 15.0;
        l.max_yaw_rate = 20f64.to_radians();
        let mut s = State::at(Ned::default());
        s.speed = 15.0;
        let centre = Ned::default();
        let mut max_dist: f64 = 0.0;
        for i in 0..20_000 {
            s.step(VehicleKind::Plane, Command::Hold(centre), &l, 0.02);
            if i > 10_000 {
                max_dist = max_dist.max(s.pos.horizontal_distance(&centre));
            }
        }
        assert!((s.speed - 15.0).abs() < 1e-9);
        assert!(
            max_dist < 3.0 * l.loiter_radius,
            "drifted {max_dist} m away"
        );
    }
}

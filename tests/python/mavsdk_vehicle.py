#!/usr/bin/env python3
"""A rover built from MAVSDK's server plugins: a MAVLink implementation not written here.

The MAVLink side is entirely MAVSDK's (the `mavsdk` package's native library): its
mission_raw_server receives missions, answers MISSION_SET_CURRENT and reports reached items;
action_server takes arming and mode changes; param_server answers parameters;
telemetry_server sends positions. Only the motion is ours: a small kinematic rover that
drives in straight lines toward the current mission item at a fixed speed.

Used by the VAS's conformance suite (services/vas/tests/vas_vs_mavsdk.rs); also by hand:

    .venv-test/bin/python tests/python/mavsdk_vehicle.py --port 14570 --speedup 10

Speaks MAVLink on udpin 127.0.0.1:PORT (a ground station sends there; replies go back to
it). Prints JSON lines on stdout, one per event, flushed at once:

    {"event": "ready", "port": 14570}
    {"event": "mission", "count": 6}
    {"event": "mode", "mode": "MISSION"}
    {"event": "armed", "armed": true}
    {"event": "current", "seq": 2, "lat": 41.27, "lon": 1.98}
    {"event": "reached", "seq": 2, "lat": 41.27, "lon": 1.98, "t": 12.3}
    {"event": "mission_end"}

Ends on SIGTERM/SIGINT, or when stdin closes (the parent died).
"""

import argparse
import json
import math
import signal
import sys
import threading
import time

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action_server import ActionServer, AllowableFlightModes, FlightMode
from mavsdk.plugins.mission_raw_server import MissionRawServer
from mavsdk.plugins.param_server import ParamServer
from mavsdk.plugins.telemetry_server import (
    Heading,
    Position,
    TelemetryServer,
    VelocityNed,
)

M_PER_DEG = 111_319.49
NAV_COMMANDS = {16, 21, 22}  # NAV_WAYPOINT, NAV_LAND, NAV_TAKEOFF


def emit(**fields):
    sys.stdout.write(json.dumps(fields) + "\n")
    sys.stdout.flush()


class Rover:
    """The kinematic model and the state the plugins' callbacks change."""

    def __init__(self, lat, lon, speed, radius):
        self.lock = threading.Lock()
        self.lat = lat
        self.lon = lon
        self.home = (lat, lon)
        self.speed = speed
        self.radius = radius
        self.armed = False
        self.mode = FlightMode.HOLD
        self.items = []
        self.current = None  # (seq, lat, lon)
        # The current item was reported reached: once per time it becomes current (a new
        # mission or a new current item), even where two items share a position.
        self.current_reported = False
        self.vn = 0.0
        self.ve = 0.0
        self.heading = 0.0

    def distance_to(self, lat, lon):
        dn = (lat - self.lat) * M_PER_DEG
        de = (lon - self.lon) * M_PER_DEG * math.cos(math.radians(self.lat))
        return dn, de, math.hypot(dn, de)

    def step(self, dt):
        """Moves for `dt` simulated seconds; returns the seq of an item reached, if any."""
        with self.lock:
            self.vn = self.ve = 0.0
            if not (self.armed and self.mode == FlightMode.MISSION and self.current):
                return None
            seq, lat, lon = self.current
            dn, de, dist = self.distance_to(lat, lon)
            if dist <= self.radius:
                return seq
            move = min(self.speed * dt, dist)
            self.vn = self.speed * dn / dist
            self.ve = self.speed * de / dist
            self.heading = math.degrees(math.atan2(de, dn)) % 360.0
            self.lat += move * dn / dist / M_PER_DEG
            self.lon += move * de / dist / (M_PER_DEG * math.cos(math.radians(self.lat)))
            return None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, required=True, help="UDP port to listen on")
    ap.add_argument("--speedup", type=float, default=1.0, help="simulated s per wall s")
    ap.add_argument("--speed", type=float, default=5.0, help="cruise speed, m/s")
    ap.add_argument("--radius", type=float, default=2.0, help="acceptance radius, m")
    ap.add_argument("--home", default="41.2757,1.9881", help="LAT,LON")
    ap.add_argument("--sysid", type=int, default=1)
    args = ap.parse_args()
    lat, lon = (float(v) for v in args.home.split(","))
    rover = Rover(lat, lon, args.speed, args.radius)

    cfg = Configuration.create_with_component_type(ComponentType.AUTOPILOT)
    cfg.system_id = args.sysid
    cfg.component_id = 1
    mavsdk = Mavsdk(cfg)
    result = mavsdk.add_any_connection(f"udpin://127.0.0.1:{args.port}")
    if int(result) != 0 and str(result).split(".")[-1] != "SUCCESS":
        emit(event="error", what=f"connection: {result}")
        return 2
    server = mavsdk.server_component()
    mission = MissionRawServer(server)
    action = ActionServer(server)
    params = ParamServer(server)
    telemetry = TelemetryServer(server)

    params.provide_param_float("WP_RADIUS", float(args.radius))
    params.provide_param_float("CRUISE_SPEED", float(args.speed))
    action.set_armable(True, True)
    action.set_disarmable(True, True)
    action.set_allowable_flight_modes(
        AllowableFlightModes(
            can_auto_mode=True,
            can_guided_mode=True,
            can_stabilize_mode=True,
            can_auto_rtl_mode=True,
            can_auto_loiter_mode=True,
        )
    )
    action.set_flight_mode(FlightMode.HOLD)

    def on_mission(result, plan, _):
        with rover.lock:
            rover.items = list(plan.mission_items)
            rover.current_reported = False
        emit(event="mission", result=str(result).split(".")[-1], count=len(plan.mission_items))

    def on_current(item, _):
        lat, lon = item.x / 1e7, item.y / 1e7
        with rover.lock:
            # The same item said current again is not a new visit.
            if rover.current is None or rover.current[0] != item.seq:
                rover.current_reported = False
            rover.current = (item.seq, lat, lon)
        emit(event="current", seq=item.seq, lat=lat, lon=lon)

    # Setting the server's state calls these callbacks again with the state just set: only a
    # change is applied (else they would call each other forever, millions of times a minute).
    def on_arm(result, arm, _):
        armed = bool(arm.arm)
        with rover.lock:
            changed = rover.armed != armed
            rover.armed = armed
        if changed:
            action.set_armed_state(armed)
            emit(event="armed", armed=armed)

    def on_mode(result, mode, _):
        mode = FlightMode(int(mode))
        with rover.lock:
            changed = rover.mode != mode
            rover.mode = mode
        if changed:
            action.set_flight_mode(mode)
            emit(event="mode", mode=mode.name)

    mission.subscribe_incoming_mission(on_mission)
    mission.subscribe_current_item_changed(on_current)
    action.subscribe_arm_disarm(on_arm)
    action.subscribe_flight_mode_change(on_mode)

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())

    def watch_stdin():
        # The parent closes our stdin (or dies): stop.
        try:
            while sys.stdin.read(1):
                pass
        except (OSError, ValueError):
            pass
        stop.set()

    threading.Thread(target=watch_stdin, daemon=True).start()
    emit(event="ready", port=args.port)

    tick = 0.02
    sim_t = 0.0
    last_pub = 0.0
    while not stop.is_set():
        time.sleep(tick)
        dt = tick * args.speedup
        sim_t += dt
        reached = rover.step(dt)
        if reached is not None:
            with rover.lock:
                seq, rlat, rlon = rover.current
                last = len(rover.items) - 1
                first = not rover.current_reported
                rover.current_reported = True
            if first:
                emit(event="reached", seq=seq, lat=rlat, lon=rlon, t=round(sim_t, 3))
                if seq >= last:
                    # The end of the mission: hold there, as autopilots do.
                    mission.set_current_item_complete()
                    with rover.lock:
                        rover.mode = FlightMode.HOLD
                    action.set_flight_mode(FlightMode.HOLD)
                    emit(event="mission_end")
                else:
                    mission.set_current_item_complete()
        now = time.monotonic()
        if now - last_pub >= 0.1:
            last_pub = now
            with rover.lock:
                pos = Position(rover.lat, rover.lon, 10.0, 0.0)
                vel = VelocityNed(rover.vn, rover.ve, 0.0)
                hdg = Heading(rover.heading)
            try:
                telemetry.publish_position(pos, vel, hdg)
            except Exception as e:  # a refusal must not stop the vehicle
                emit(event="error", what=f"publish_position: {e}")
    mavsdk.destroy()
    return 0


if __name__ == "__main__":
    sys.exit(main())

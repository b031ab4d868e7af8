#!/usr/bin/env python3
"""A second ground station (pymavlink) beside the VAS: it listens where the VAS forwards
MAVLink (`vas --forward udpout:127.0.0.1:PORT`), waits for the autopilot's heartbeat, and on a
line `upload LAT,LON;LAT,LON;...` on stdin uploads that mission (item 0 first) through the VAS's
link, as QGroundControl or MAVProxy would. JSON lines on stdout:

    {"event": "heartbeat", "system": 1, "autopilot": 3}
    {"event": "uploaded", "result": 0, "count": 4}
    {"event": "error", "what": "..."}

Ends when stdin closes.
"""

import argparse
import json
import os
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402


def emit(**fields):
    sys.stdout.write(json.dumps(fields) + "\n")
    sys.stdout.flush()


def upload(m, target, points, timeout=10.0):
    mav = m.mav
    n = len(points)
    mav.mission_count_send(target[0], target[1], n)
    deadline = time.time() + timeout
    while time.time() < deadline:
        msg = m.recv_match(
            type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"],
            blocking=True,
            timeout=0.5,
        )
        if msg is None or msg.get_srcSystem() != target[0]:
            continue
        if msg.target_system not in (0, m.source_system):
            continue
        if msg.get_type() == "MISSION_ACK":
            return msg.type
        seq = msg.seq
        if seq >= n:
            continue
        lat, lon = points[seq]
        mav.mission_item_int_send(
            target[0], target[1], seq,
            mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            mavutil.mavlink.MAV_CMD_NAV_WAYPOINT,
            0, 1, 0, 0, 0, 0,
            int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0,
        )
    return None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--sysid", type=int, default=250)
    args = ap.parse_args()
    m = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{args.port}",
        source_system=args.sysid,
        source_component=190,
        dialect="ardupilotmega",
    )
    hb = None
    deadline = time.time() + 30
    while hb is None and time.time() < deadline:
        msg = m.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
        if msg is not None and msg.type != mavutil.mavlink.MAV_TYPE_GCS:
            hb = msg
    if hb is None:
        emit(event="error", what="no autopilot heartbeat forwarded")
        return 1
    target = (hb.get_srcSystem(), hb.get_srcComponent())
    emit(event="heartbeat", system=target[0], autopilot=hb.autopilot)
    for line in sys.stdin:
        words = line.split(maxsplit=1)
        if not words:
            continue
        if words[0] == "upload" and len(words) == 2:
            points = [tuple(float(v) for v in p.split(",")) for p in words[1].split(";") if p.strip()]
            # The autopilot takes one mission transfer at a time: items of ours that met the
            # VAS's own write are refused (MAV_MISSION_DENIED, or OPERATION_CANCELLED, or
            # MAV_MISSION_ERROR once the VAS's write replaced our transfer), and a station
            # tries again.
            busy = (
                mavutil.mavlink.MAV_MISSION_DENIED,
                mavutil.mavlink.MAV_MISSION_OPERATION_CANCELLED,
                mavutil.mavlink.MAV_MISSION_ERROR,
            )
            result = upload(m, target, points)
            for _ in range(3):
                if result not in busy:
                    break
                result = upload(m, target, points)
            if result is None:
                emit(event="error", what="mission upload unanswered")
            else:
                emit(event="uploaded", result=int(result), count=len(points))
    return 0


if __name__ == "__main__":
    sys.exit(main())

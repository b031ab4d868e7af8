"""A plain Zenoh client (the official `eclipse-zenoh` package) using a USAL system through its
public contract (docs/zenoh.md): no marea, no USAL code.

    zenoh_client.py ENDPOINT DOMAIN

Connects to the router at ENDPOINT and prints one JSON line per finding:
  {"nodes": [...]}                  the liveliness tokens usal/DOMAIN/@node/*
  {"position": {...}, "encoding": ..}  the first sample of usal/DOMAIN/air/vas/position
  {"last": {...}}                   a get of the same key (the variable's last value)
  {"double": 42}                    a get on usal/DOMAIN/air/vas/double with 21 as argument
  {"change_state": {...}}           the error reply of a call an <access> rule refuses
  {"done": true}
"""

import json
import sys
import time

import zenoh


def out(**kv):
    print(json.dumps(kv), flush=True)


def call(session, key, arg):
    """(True, result) or (False, error) of the first reply to a get carrying `arg` as JSON."""
    for reply in session.get(key, payload=json.dumps(arg), timeout=15.0):
        if reply.ok is not None:
            return True, json.loads(reply.ok.payload.to_string())
        return False, json.loads(reply.err.payload.to_string())
    return False, {"error": "no reply"}


def main():
    endpoint, domain = sys.argv[1], sys.argv[2]
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    prefix = f"usal/{domain}"
    with zenoh.open(conf) as session:
        position = f"{prefix}/air/vas/position"
        sub = session.declare_subscriber(position)
        out(ready=True)
        # The nodes of the domain, once the ones the test started are all there.
        deadline = time.monotonic() + 20
        nodes = []
        while time.monotonic() < deadline:
            nodes = sorted(
                {
                    str(r.ok.key_expr).rsplit("/", 1)[-1]
                    for r in session.liveliness().get(f"{prefix}/@node/*", timeout=5.0)
                    if r.ok is not None
                }
            )
            if {"air", "airdbl", "airfn", "bridge"} <= set(nodes):
                break
            time.sleep(0.2)
        out(nodes=nodes)
        sample = sub.recv()
        out(position=json.loads(sample.payload.to_string()), encoding=str(sample.encoding))
        last = [
            json.loads(r.ok.payload.to_string())
            for r in session.get(position, timeout=10.0)
            if r.ok is not None
        ]
        out(last=last[0] if last else None)
        ok, value = call(session, f"{prefix}/air/vas/double", 21)
        out(double=value if ok else {"refused": value})
        ok, value = call(session, f"{prefix}/airfn/vas/change_state", 1)
        out(change_state=value if not ok else {"served": value})
        out(done=True)


if __name__ == "__main__":
    main()

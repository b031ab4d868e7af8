"""A plain Zenoh client (the official `eclipse-zenoh` package) using a USAL system through its
public contract (docs/zenoh.md): no marea, no USAL code.

    zenoh_client.py ENDPOINT DOMAIN USER:PASSWORD OTHER:PASSWORD

Logs in to the router at ENDPOINT as USER and prints one JSON line per finding:
  {"nodes": [...]}                  the liveliness tokens usal/DOMAIN/@node/*
  {"position": {...}, "encoding": ..}  the first sample of usal/DOMAIN/air/vas/position
  {"last": {...}}                   a get of the same key (the variable's last value)
  {"double": 42}                    a get on usal/DOMAIN/air/vas/double with 21 as argument
  {"change_state": {...}}           airfn/vas/change_state called on its plain key (anonymous)
  {"as_self": {...}}                the same called as USER (usal/DOMAIN/@as/USER/...)
then as OTHER:
  {"other_as_self": {...}}          the same called as OTHER
  {"impersonation": {...}}          OTHER calling under USER's key: the router lets nothing through
  {"done": true}
A call's line holds its result, or {"refused": error} / the error reply.
"""

import json
import sys
import time

import zenoh


def out(**kv):
    print(json.dumps(kv), flush=True)


def call(session, key, arg, timeout=15.0):
    """(True, result) or (False, error) of the first reply to a get carrying `arg` as JSON."""
    for reply in session.get(key, payload=json.dumps(arg), timeout=timeout):
        if reply.ok is not None:
            return True, json.loads(reply.ok.payload.to_string())
        return False, json.loads(reply.err.payload.to_string())
    return False, {"error": "no reply"}


def open_as(endpoint, credentials):
    """A session with the router at `endpoint`, logged in with USER:PASSWORD."""
    user, password = credentials.split(":", 1)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return user, zenoh.open(conf)


def main():
    endpoint, domain, me, other = sys.argv[1:5]
    prefix = f"usal/{domain}"
    guarded = "airfn/vas/change_state"
    user, session = open_as(endpoint, me)
    with session:
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
        ok, value = call(session, f"{prefix}/{guarded}", 1)
        out(change_state=value if not ok else {"served": value})
        ok, value = call(session, f"{prefix}/@as/{user}/{guarded}", 1)
        out(as_self={"served": value} if ok else {"refused": value})
    other_user, session = open_as(endpoint, other)
    with session:
        ok, value = call(session, f"{prefix}/@as/{other_user}/{guarded}", 1)
        out(other_as_self={"served": value} if ok else {"refused": value})
        # Nothing answers: the router drops the query (the bound is how long we listen).
        ok, value = call(session, f"{prefix}/@as/{user}/{guarded}", 1, timeout=3.0)
        out(impersonation={"served": value} if ok else {"refused": value})
    out(done=True)


if __name__ == "__main__":
    main()

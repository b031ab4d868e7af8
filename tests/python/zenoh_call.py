"""Calls one function of a USAL domain through the bridge, as any Zenoh client would: the
official `eclipse-zenoh` package, a Zenoh configuration file (e.g. one `usal router
--tls-client` made: the client's certificate), the public contract of docs/zenoh.md.

    zenoh_call.py CONFIG ENDPOINT KEY ARG [LISTEN_S]

Prints one JSON line: {"ok": result}, {"err": error reply}, or {"none": true} when nothing
answered within LISTEN_S seconds (default 15). While the bridge does not know the function yet
(`no_provider`) it asks again, for up to 20 s.
"""

import json
import sys
import time

import zenoh


def main():
    config, endpoint, key, arg = sys.argv[1:5]
    listen = float(sys.argv[5]) if len(sys.argv) > 5 else 15.0
    conf = zenoh.Config.from_file(config)
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    deadline = time.monotonic() + 20
    with zenoh.open(conf) as session:
        while True:
            found = {"none": True}
            for reply in session.get(key, payload=arg, timeout=listen):
                if reply.ok is not None:
                    found = {"ok": json.loads(reply.ok.payload.to_string())}
                else:
                    found = {"err": json.loads(reply.err.payload.to_string())}
                break
            waiting = found.get("err", {}).get("error") == "no_provider"
            if not waiting or time.monotonic() > deadline:
                break
            time.sleep(0.2)
    print(json.dumps(found), flush=True)


if __name__ == "__main__":
    main()

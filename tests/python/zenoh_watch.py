"""Watches a running USAL mission through its router's bridge, as any Zenoh client would: the
official `eclipse-zenoh` package, the run's client configuration, the public contract of
docs/zenoh.md, no USAL code.

    zenoh_watch.py ENDPOINT CONFIG DOMAIN ITEM NODE...

Connects to the router at ENDPOINT with the Zenoh configuration CONFIG (the run's
client.json5: it trusts the run's authority) and prints one JSON line per finding:
  {"sample": {...}, "encoding": ..}   the first sample of usal/DOMAIN/ITEM
  {"nodes": [...]}                    the liveliness tokens usal/DOMAIN/@node/*, once every
                                      NODE is among them (or after 20 s)
  {"done": true}
"""

import json
import sys
import time

import zenoh


def out(**kv):
    print(json.dumps(kv), flush=True)


def main():
    endpoint, config, domain, item = sys.argv[1:5]
    expected = set(sys.argv[5:])
    conf = zenoh.Config.from_file(config)
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    prefix = f"usal/{domain}"
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(f"{prefix}/{item}")
        out(ready=True)
        sample = sub.recv()
        out(sample=json.loads(sample.payload.to_string()), encoding=str(sample.encoding))
        # The bridge declares a token once it knows the node: ask until all are there.
        deadline = time.monotonic() + 20
        while True:
            nodes = sorted(
                {
                    str(r.ok.key_expr).rsplit("/", 1)[-1]
                    for r in session.liveliness().get(f"{prefix}/@node/*", timeout=5.0)
                    if r.ok is not None
                }
            )
            if expected <= set(nodes) or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        out(nodes=nodes)
    out(done=True)


if __name__ == "__main__":
    main()

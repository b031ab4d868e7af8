"""Watches a running USAL mission through its router's bridge, as any Zenoh client would: the
official `eclipse-zenoh` package, the run's client configuration, the public contract of
docs/zenoh.md, no USAL code.

    zenoh_watch.py ENDPOINT CONFIG DOMAIN ITEM

Connects to the router at ENDPOINT with the Zenoh configuration CONFIG (the run's
client.json5: it trusts the run's authority) and prints one JSON line per finding:
  {"sample": {...}, "encoding": ..}   the first sample of usal/DOMAIN/ITEM
  {"nodes": [...]}                    the liveliness tokens usal/DOMAIN/@node/*
  {"done": true}
"""

import json
import sys

import zenoh


def out(**kv):
    print(json.dumps(kv), flush=True)


def main():
    endpoint, config, domain, item = sys.argv[1:5]
    conf = zenoh.Config.from_file(config)
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    prefix = f"usal/{domain}"
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(f"{prefix}/{item}")
        out(ready=True)
        sample = sub.recv()
        out(sample=json.loads(sample.payload.to_string()), encoding=str(sample.encoding))
        nodes = sorted(
            {
                str(r.ok.key_expr).rsplit("/", 1)[-1]
                for r in session.liveliness().get(f"{prefix}/@node/*", timeout=5.0)
                if r.ok is not None
            }
        )
        out(nodes=nodes)
    out(done=True)


if __name__ == "__main__":
    main()

"""An outsider against a lungdyn room, with the eclipse-zenoh Python client (not lungdyn's code).

usage: zenoh_outsider.py ENDPOINT_PORT OURS_DIR THEIRS_DIR ROOM

Tries to connect to tls/127.0.0.1:PORT as a client (1) over plain TCP, (2) over TLS with no
certificate of its own, (3) with a certificate of another room's authority, (4) with this room's
observer certificate; with (4) it puts 5 unsealed probes on the time relay's key. Prints one JSON
object: for each attempt whether it connected and Zenoh's error.
"""
import json
import sys
import time

import zenoh


def attempt(endpoint, tls=None):
    conf = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
    }
    if tls is not None:
        conf["transport"] = {"link": {"tls": tls}}
    try:
        s = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
        return s, None
    except Exception as e:  # Zenoh's ZError
        return None, str(e)[:300]


def main():
    port, ours, theirs, room = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
    tls_ep = f"tls/127.0.0.1:{port}"
    out = {"zenoh": getattr(zenoh, "__version__", "unknown")}

    def as_(folder, name):
        return {
            "root_ca_certificate": f"{ours}/authority.crt",
            "connect_certificate": f"{folder}/{name}.crt",
            "connect_private_key": f"{folder}/{name}.key",
            "enable_mtls": True,
            "verify_name_on_connect": False,
        }

    for label, ep, tls in [
        ("plain_tcp", f"tcp/127.0.0.1:{port}", None),
        ("tls_without_certificate", tls_ep, {"root_ca_certificate": f"{ours}/authority.crt",
                                              "verify_name_on_connect": False}),
        ("another_rooms_certificate", tls_ep, as_(theirs, "site")),
        ("this_rooms_observer", tls_ep, as_(ours, "observer")),
    ]:
        s, err = attempt(ep, tls)
        out[label] = {"connected": s is not None, "error": err}
        if s is not None and label == "this_rooms_observer":
            for _ in range(5):
                s.put(f"lungdyn/{room}/relay/probe", b"LDCS forged probe")
            time.sleep(1.0)
            out[label]["put"] = 5
        if s is not None:
            s.close()
    print(json.dumps(out))


main()

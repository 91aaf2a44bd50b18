#!/usr/bin/env python3
"""A respiratory amplitude over OpenIGTLink from pyigtl, as an outsider sends it (the bridge's
`--breathing igtl:Resp` test): connects to 127.0.0.1:PORT and at 30 Hz sends

  - STRING "Resp" `mm=VALUE`, VALUE = k / 10 for k = 1..N (the values the test expects, in order),
  - every 10th frame a STRING "Other" `mm=99` (another device: never the signal),
  - a TRANSFORM "Patient" (the tracker's own pose),

then one STRING "Resp" `mm=` (a sample its sender marks invalid) and stops.

    python amplitude_sender.py PORT N
"""
import socket
import sys
import time

import numpy as np
import pyigtl


def main():
    if len(sys.argv) != 3:
        sys.exit("usage: amplitude_sender.py PORT N")
    port, n = int(sys.argv[1]), int(sys.argv[2])
    waited = time.time()
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            if time.time() - waited > 120:
                sys.exit(f"nothing listens on 127.0.0.1:{port}")
            time.sleep(0.1)
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port, start_now=True)
    for _ in range(300):
        if client.is_connected():
            break
        time.sleep(0.05)
    if not client.is_connected():
        sys.exit(f"could not connect to 127.0.0.1:{port}")
    pose = np.eye(4)
    pose[2, 3] = -1000.0
    start = time.time()
    for k in range(1, n + 1):
        client.send_message(pyigtl.TransformMessage(pose, device_name="Patient"), wait=False)
        client.send_message(pyigtl.StringMessage(f"mm={k / 10:.1f}", device_name="Resp"), wait=False)
        if k % 10 == 0:
            client.send_message(pyigtl.StringMessage("mm=99", device_name="Other"), wait=False)
        time.sleep(max(0.0, start + k / 30.0 - time.time()))
    client.send_message(pyigtl.StringMessage("mm=", device_name="Resp"), wait=True)
    time.sleep(0.5)
    client.stop()
    print(f"sent {n} amplitudes and one invalid")


if __name__ == "__main__":
    main()

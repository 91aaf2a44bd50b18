#!/usr/bin/env python3
"""A breathing chest tool over OpenIGTLink, for `lungdyn demo --breathing tool:Chest` (or
`--breathing igtl:Resp`) without a tracker.

Streams three TRANSFORMs at 60 Hz with pyigtl (as PLUS or 3D Slicer would): `Patient` (the patient
reference, turned 30 degrees about the camera's Y and tilted 10, drifting along X), `HMD`, and `Chest`,
5 mm anterior of the reference plus a breath: 12 a minute, inspiration 1.67 s, 8 mm rise whose size
changes +-15 % from breath to breath. Beside them, at 30 Hz, the same rise as a belt would send it:
a STRING `mm=VALUE` from the device `Resp`. Connects when the server listens (the bridge's igtl-server).

    target/pyenv/bin/python bench/chest_sender.py 18944 60 &
    lungdyn demo --tracker igtl-server:127.0.0.1:18944 --breathing tool:Chest --seconds 40
    lungdyn demo --tracker igtl-server:127.0.0.1:18944 --breathing igtl:Resp --seconds 40

A third argument, `--mount DEG`, mounts the reference off the patient's frame: the chest then rises
along the reference's anterior axis turned DEG degrees about its X axis (towards its superior axis),
as a marker block taped at an angle sees it — what `--breathing tool:Chest:auto` learns.

(target/pyenv is made by `./run setup test`; any Python with pyigtl and numpy will do.)
"""
import math
import socket
import sys
import time

import numpy as np
import pyigtl


def rotation(axis, degrees):
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rise_mm(t):
    """The chest's rise above its end-expiration, mm, at `t` seconds."""
    cycle, phase = divmod(t, 5.0)
    amplitude = 8.0 * (1.0 + 0.15 * math.sin(1.7 * cycle))
    if phase < 1.67:
        return amplitude * math.sin(math.pi * phase / 1.67 / 2) ** 2
    return amplitude * math.cos(math.pi * (phase - 1.67) / 3.33 / 2) ** 2


def matrix(r, p):
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = p
    return m


def main():
    if len(sys.argv) not in (3, 5) or (len(sys.argv) == 5 and sys.argv[3] != "--mount"):
        sys.exit("usage: chest_sender.py PORT SECONDS [--mount DEG]")
    port, seconds = int(sys.argv[1]), float(sys.argv[2])
    mount = 0.0
    if len(sys.argv) == 5:
        try:
            mount = float(sys.argv[4])
        except ValueError:
            sys.exit(f"--mount {sys.argv[4]!r}: not a number of degrees")
        if not -180.0 <= mount <= 180.0:
            sys.exit(f"--mount {sys.argv[4]}: degrees from -180 to 180")
        mount = math.radians(mount)
    # The breath's direction in the reference's frame: anterior, turned by the mount.
    up = np.array([0.0, math.cos(mount), math.sin(mount)])
    waited = time.time()
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            if time.time() - waited > 300:
                sys.exit(f"nothing listens on 127.0.0.1:{port}")
            time.sleep(0.2)
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port, start_now=True)
    for _ in range(300):
        if client.is_connected():
            break
        time.sleep(0.1)
    if not client.is_connected():
        sys.exit(f"could not connect to 127.0.0.1:{port}")
    turn = rotation("y", 30) @ rotation("z", 10)
    start, k = time.time(), 0
    while time.time() - start < seconds:
        t = time.time() - start
        at = np.array([(0.05 * k) % 40.0, 0.0, -1200.0])
        chest = at + turn @ (np.array([-20.0, 5.0, 60.0]) + rise_mm(t) * up)
        for name, m in (("Patient", matrix(turn, at)),
                        ("HMD", matrix(np.eye(3), [0.0, 100.0, -700.0])),
                        ("Chest", matrix(turn, chest))):
            client.send_message(pyigtl.TransformMessage(m, device_name=name), wait=False)
        if k % 2 == 0:
            belt = pyigtl.StringMessage(f"mm={rise_mm(t):.3f}", device_name="Resp")
            client.send_message(belt, wait=False)
        k += 1
        time.sleep(max(0.0, start + k / 60.0 - time.time()))
    client.stop()


if __name__ == "__main__":
    main()

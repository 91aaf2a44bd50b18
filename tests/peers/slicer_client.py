"""A client of `lungdyn demo --igtl-serve`, as 3D Slicer's OpenIGTLinkIF would be, with pyigtl (not
lungdyn's code).

usage: slicer_client.py PORT FRAMES OUT_JSON

pyigtl 0.3.4 does not register POLYDATA for receiving and its `_unpack_content` for it cannot run
(it indexes a `struct.Struct` instead of unpacking, and reads no attributes). Both are mended here,
in test code, from the OpenIGTLink protocol text (POLYDATA: ten big-endian u32 counts, the points
as f32 triples, the cells as u32 runs, per attribute a u8 type, u8 components, u32 count, then the
NUL-terminated names padded to an even length, then each attribute's f32 data).

1. pyigtl's own client (its receive thread, as a Slicer-like peer) connects and waits for
   "BreathState" and "RightLung": pyigtl's loop reads lungdyn's stream.
2. A plain socket reads FRAMES frames in order; each message's header is parsed by pyigtl
   (`MessageBase.parse_header`), its CRC-64 checked with pyigtl's own CRC function, its body
   unpacked by pyigtl's message classes (POLYDATA by the mended one). A frame ends at "BreathState".

Prints nothing on success; writes one JSON object to OUT_JSON: pyigtl's version, phase 1's result,
every frame's tick, message order and timestamps, and three frames (first, middle, last) whole:
points, polygons (first frame only), attributes, the state.
"""
import json
import socket
import struct
import sys
import time

import numpy as np
import pyigtl
from pyigtl import messages as M


class MendedPolyData(pyigtl.PolyDataMessage):
    def _unpack_content(self, content):
        counts = struct.unpack_from(">10I", content, 0)
        npts, _nv, sv, _nl, sl, npoly, sp, _ns, ss, nattr = counts
        at = 40
        self.points = np.frombuffer(content, dtype=">f4", count=npts * 3, offset=at).reshape(-1, 3)
        at += npts * 12
        cells = []
        for size in (sv, sl, sp, ss):
            cells.append(np.frombuffer(content, dtype=">u4", count=size // 4, offset=at))
            at += size
        self.vertices, self.lines, self.polygons, self.triangle_strips = cells
        self.polygon_count = npoly
        heads = []
        for _ in range(nattr):
            kind, comps, n = struct.unpack_from(">BBI", content, at)
            heads.append((kind, comps, n))
            at += 6
        names = []
        start = at
        for _ in range(nattr):
            end = content.index(b"\0", at)
            names.append(content[at:end].decode("ascii"))
            at = end + 1
        if (at - start) % 2 == 1:
            at += 1
        self.attributes = []
        for (kind, comps, n), name in zip(heads, names):
            data = np.frombuffer(content, dtype=">f4", count=n * comps, offset=at)
            at += n * comps * 4
            self.attributes.append({"type": kind, "components": comps, "name": name, "data": data})
        self.consumed = at
        self.content_length = len(content)


M.message_type_to_class_constructor["POLYDATA"] = MendedPolyData


def pyigtl_client_phase(port):
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    got = {}
    try:
        # The port is open before the demo has baked its lungs and started its processes: the first
        # frame may be a minute away on a loaded machine.
        for device, timeout in (("BreathState", 180), ("RightLung", 30)):
            m = client.wait_for_message(device, timeout=timeout)
            got[device] = None if m is None else m._message_type
            if m is not None and m._message_type == "POLYDATA":
                got["RightLung_points"] = int(len(m.points))
            if m is not None and m._message_type == "STRING":
                got["BreathState_tick"] = json.loads(m.string)["tick"]
    finally:
        client.stop()
    return got


def read_exact(sock, n):
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            raise EOFError("the server closed the connection")
        out += chunk
    return bytes(out)


def connect(port, timeout_s):
    deadline = time.time() + timeout_s
    while True:
        try:
            return socket.create_connection(("127.0.0.1", port), timeout=10)
        except OSError:
            if time.time() > deadline:
                raise
            time.sleep(0.2)


def whole(msg):
    if isinstance(msg, MendedPolyData):
        return {
            "type": "POLYDATA",
            "points": [float(v) for v in msg.points.reshape(-1)],
            "polygon_count": int(msg.polygon_count),
            "vertices_bytes": int(msg.vertices.size * 4),
            "consumed": msg.consumed,
            "content_length": msg.content_length,
            "attributes": [
                {"type": a["type"], "components": a["components"], "name": a["name"],
                 "data": [float(v) for v in a["data"]]}
                for a in msg.attributes
            ],
        }
    if msg._message_type == "TRANSFORM":
        return {"type": "TRANSFORM", "matrix": [float(v) for v in np.asarray(msg.matrix).reshape(-1)]}
    if msg._message_type == "STRING":
        return {"type": "STRING", "string": msg.string}
    return {"type": msg._message_type}


def main():
    port, frames, out_path = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    # The demo bakes and starts its processes before it listens: wait for the port first.
    connect(port, 120).close()
    from importlib.metadata import version
    out = {"pyigtl": version("pyigtl"), "pyigtl_client": pyigtl_client_phase(port)}
    sock = connect(port, 10)
    captured, current, crc_errors = [], [], 0
    while len(captured) < frames:
        header = read_exact(sock, M.MessageBase.IGTL_HEADER_SIZE)
        fields = M.MessageBase.parse_header(header)
        crc_sent = struct.unpack(">Q", header[50:58])[0]
        body = read_exact(sock, fields["body_size"])
        if M.CRC64(body) != crc_sent:
            crc_errors += 1
        msg = M.MessageBase.create_message(fields["message_type"])
        if msg is None:
            raise SystemExit(f"pyigtl knows no {fields['message_type']!r} message")
        msg.unpack(fields, body)
        current.append((fields["device_name"], fields["timestamp"], msg))
        if fields["device_name"] == "BreathState":
            captured.append(current)
            current = []
    sock.close()
    keep = {0, len(captured) // 2, len(captured) - 1}
    out["crc_errors"] = crc_errors
    out["frames"] = []
    for i, frame in enumerate(captured):
        state = json.loads(frame[-1][2].string)
        entry = {
            "tick": state["tick"],
            "order": [d for d, _, _ in frame],
            "types": [m._message_type for _, _, m in frame],
            "timestamps": [t for _, t, _ in frame],
        }
        if i in keep:
            entry["messages"] = {d: whole(m) for d, _, m in frame}
            if i != 0:
                for m in entry["messages"].values():
                    m.pop("polygons", None)
            else:
                for d, _, m in frame:
                    if isinstance(m, MendedPolyData):
                        entry["messages"][d]["polygons"] = [int(v) for v in m.polygons]
        out["frames"].append(entry)
    with open(out_path, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()

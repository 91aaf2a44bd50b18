#!/usr/bin/env bash
# What the link to 3D Slicer costs the frame (issue 38, docs/SLICER.md): `lungdyn latency` back to back,
# without and with `--igtl-serve`, a client reading every byte as Slicer would (Python's socket, no
# parsing), on the built-in default scene (2 × ~10k vertices).
#
# usage: bench/slicer_latency.sh [SECONDS] [OUT]     (default 30 s measured per run, out/slicer_latency)
# Prints both summaries; the JSON of each run is in OUT/{without,with}.json. READER_NICE=10 runs the
# reader at nice 10 (to tell its cost from the link's when both share the cores); SCENE=FILE measures
# that scene instead (its [slicer] rate_hz is the link's rate).
set -euo pipefail
seconds=${1:-30}
out=${2:-out/slicer_latency}
root=$(cd "$(dirname "$0")/.." && pwd)
lungdyn=${LUNGDYN:-$root/target/release/lungdyn}
port=${PORT:-18965}
mkdir -p "$out"
scene=(${SCENE:+--scene "$SCENE"})
"$lungdyn" latency --seconds "$seconds" --out "$out/without" --json "${scene[@]}" > "$out/without.json"
# The reader connects when the port opens and reads until the demo closes it.
nice -n "${READER_NICE:-0}" python3 - "$port" "$((seconds + 120))" > "$out/reader.txt" <<'PY' &
import socket, sys, time
port, limit = int(sys.argv[1]), float(sys.argv[2])
t0, total = time.time(), 0
while time.time() - t0 < limit:
    try:
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
    except OSError:
        time.sleep(0.2)
        continue
    s.settimeout(None)
    while True:
        b = s.recv(1 << 20)
        if not b:
            break
        total += len(b)
    break
print(f"reader: {total} bytes in {time.time() - t0:.1f} s")
PY
reader=$!
"$lungdyn" latency --seconds "$seconds" --out "$out/with" --json --igtl-serve "$port" "${scene[@]}" > "$out/with.json"
wait "$reader" || true
python3 - "$out" <<'PY'
import json, sys
out = sys.argv[1]
for name in ("without", "with"):
    r = json.load(open(f"{out}/{name}.json"))
    line = (f"{name:8s} frames {r['frames']}, deadline misses {r['deadline_misses']}, capture->submit p99 "
            f"{r['capture_to_submit_p99_ms']:.2f} ms, capture->GPU done p99 {r['capture_to_gpu_done_p99_ms']:.2f} ms")
    s = r.get("slicer")
    if s:
        mbs = s["bytes"] / 1e6 / s["seconds"] if s["seconds"] else 0
        line += (f"; Slicer: {s['frames']} frames to {s['clients']} client(s), {s['dropped']} missed, "
                 f"{mbs:.1f} MB/s, {s['frame_bytes'] / 1e6:.2f} MB a frame, make p50 {s['make_ms_p50']} ms "
                 f"p99 {s['make_ms_p99']} ms max {s['make_ms_max']} ms")
    print(line)
PY
cat "$out/reader.txt"

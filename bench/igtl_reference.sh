#!/usr/bin/env bash
# lungdyn's OpenIGTLink stream (`lungdyn demo --igtl-serve`) decoded by the OpenIGTLink C++ library —
# the library 3D Slicer's OpenIGTLinkIF links — instead of pyigtl: builds the library at a pinned
# commit, builds bench/igtl_reference/receive.cxx against it, and runs the Slicer test
# (tests/tests/trackers.rs, slicer_receives_the_breathing_lungs_and_the_tumour_over_openigtlink) with
# that client (LUNGDYN_IGTL_REFERENCE_CLIENT): every frame's CRC-64 checked by the library, the
# points of three frames held against the renderer's CPU reference to 1 µm, the triangles, the lobe
# attribute, the tumour's transform and the state as the pyigtl run holds them. Then the other way
# round: the client listens as Slicer's Server connector (`receive --listen`) and
# `lungdyn demo --igtl-connect` connects to it; its capture is summarised (frames, CRC errors, the
# first frame's messages).
#
#   bench/igtl_reference.sh                 clone https://github.com/openigtlink/OpenIGTLink
#   OPENIGTLINK_SRC=/path bench/igtl_reference.sh   use a clone already there
#
# Needs git, a C++ compiler, make and CMake ≥ 3.5 (`pip install cmake` gives one), a Vulkan adapter
# (lavapipe will do) as the test suite does. Not in CI: the library is a C++ build from GitHub; the
# run's figures are in docs/SLICER.md.
set -euo pipefail
cd "$(dirname "$0")/.."
COMMIT=94244fed7051e00cbcd4c341a7d7656be8ac404a
work="${LUNGDYN_IGTL_WORK:-target/igtl-reference}"
mkdir -p "$work"
src="$work/OpenIGTLink"
if [ ! -d "$src/.git" ]; then
  git clone -q "${OPENIGTLINK_SRC:-https://github.com/openigtlink/OpenIGTLink}" "$src"
fi
git -C "$src" checkout -q "${OPENIGTLINK_COMMIT:-$COMMIT}"
echo "igtl_reference: OpenIGTLink at $(git -C "$src" log -1 --format='%h %s')" >&2
cmake_bin="$(command -v cmake || true)"
[ -n "$cmake_bin" ] || { echo "igtl_reference: needs cmake (pip install cmake)" >&2; exit 1; }
"$cmake_bin" -S "$src" -B "$work/build" -DBUILD_TESTING=OFF -DBUILD_EXAMPLES=OFF \
  -DBUILD_SHARED_LIBS=OFF -DCMAKE_BUILD_TYPE=Release >/dev/null
make -C "$work/build" -j"$(nproc)" >/dev/null
c++ -O2 -std=c++17 -I "$src/Source" -I "$src/Source/igtlutil" -I "$work/build" \
  -I "$work/build/Source" -I "$work/build/Source/igtlutil" \
  bench/igtl_reference/receive.cxx "$work/build/lib/libOpenIGTLink.a" -lpthread -o "$work/receive"
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}" XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
LUNGDYN_IGTL_REFERENCE_CLIENT="$PWD/$work/receive" \
  cargo test --release -p lungdyn-tests --test trackers slicer_receives -- --nocapture 2>&1 |
  grep -E "slicer test|Slicer link|test result|panicked|assert" 
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
scene="$work/connect.toml"
printf '[lungs]\nvertices = 1500\n[disease]\nkind = "tumour"\nside = "right"\n[disease.tumour]\nlobe = "right lower"\nradii_mm = [12.0, 10.0, 15.0]\n[render]\nwidth = 160\nheight = 120\n' > "$scene"
"$work/receive" --listen "$port" 30 "$work/listen.json" & listener=$!
sleep 1
target/release/lungdyn demo --seconds 8 --snapshots 0 --out "$work/connect-out" --scene "$scene" \
  --igtl-connect "127.0.0.1:$port" 2>&1 | grep -E "Slicer" || true
wait "$listener"
python3 - "$work/listen.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
f = next(x for x in d["frames"] if "messages" in x)
m = f["messages"]
print(f"--igtl-connect, read by the library as Slicer's server: {len(d['frames'])} frames, "
      f"{d['crc_errors']} CRC errors; the first frame {list(zip(f['types'], f['order']))}; "
      f"RightLung {len(m['RightLung']['points']) // 3} points, {m['RightLung']['polygon_count']} "
      f"polygons, attributes {[a['name'] for a in m['RightLung']['attributes']]}")
sys.exit(1 if d["crc_errors"] or len(d["frames"]) < 30 else 0)
PY

#!/bin/bash
# The GPU check (issues 20 and 21) on a machine with a real GPU: `lungdyn bench tradeoff --gpu
# require`, `lungdyn latency` at 2 x 400k vertices in stereo, a demo's breath strip, a sweep for the
# largest stereo mesh that holds 60 Hz, and the governor on and off back to back (issue 36). Run from the repository root:
#
#   BIN=target/release OUT=/tmp/gpu-check bench/gpu_check.sh
#
# BIN holds lungdyn, engine, renderer and tracker-bridge (or .dev/bin.tar.xz holds them, for a machine
# without Rust). Every step has its own timeout; everything small lands in $W/res and is tarred into
# $OUT/results.tar.gz after each step, so a run cut short keeps what finished. Results and what they
# mean: docs/gpu/.
set -u
OUT=${OUT:-/tmp/devout}; mkdir -p "$OUT"
W=${W:-/tmp/w}; mkdir -p $W/res $W/bin
LOG=$OUT/log.txt
SIZES=${SIZES:-10000,100000,400000}; MESH=${MESH:-400000}; SMIN=${SMIN:-400000}; SMAX=${SMAX:-2000000}
T_TR=${T_TR:-120}; T_LAT=${T_LAT:-110}; T_DEMO=${T_DEMO:-60}; T_SW=${T_SW:-200}; LSEC=${LSEC:-30}
SCENE=$W/stereo.toml; printf '[render]\nstereo = true\n' > $SCENE
exec > >(tee -a "$LOG") 2>&1
pack() { tar -C $W -czf "$OUT/results.tar.gz" --exclude='*.kernel' --exclude='kernels' res; }
step() { local t=$1; shift; echo "=== $(date +%T) [$t s] $*"; local s=$(date +%s); timeout -k 5 "$t" "$@"; local rc=$?; echo "=== rc=$rc in $(( $(date +%s) - s )) s"; pack; }
# A bare machine without the Vulkan loader: .gl/ may hold its .deb files (libvulkan1 and the GL/EGL
# dispatch libraries), unpacked over / here; and NVIDIA's ICD is named when the driver lives outside
# the loader's search path.
if [ -d .gl ] && ! ldconfig -p | grep -q libvulkan.so.1; then for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig; fi
if [ -z "${VK_DRIVER_FILES:-}" ]; then for f in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json; do
  [ -f "$f" ] && export VK_DRIVER_FILES=$f; done; fi
export WGPU_BACKEND=vulkan XDG_RUNTIME_DIR=$(mktemp -d) RUST_BACKTRACE=1
if [ -f .dev/bin.tar.xz ]; then tar -C $W/bin -xJf .dev/bin.tar.xz; else cp "${BIN:-target/release}"/{lungdyn,engine,renderer,tracker-bridge} $W/bin/; fi
L=$W/bin/lungdyn
echo "VK_DRIVER_FILES=${VK_DRIVER_FILES:-unset}"; nproc; free -g | head -2; uname -r
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv 2>&1 | tee $W/res/gpu.csv
ldconfig -p | grep -E 'libvulkan|libEGL' | head
step 30 sh -c "$L doctor --json > $W/res/doctor.json"; head -c 3000 $W/res/doctor.json; echo
step $T_TR $L bench tradeoff --gpu require --sizes $SIZES --out $W/res/tradeoff
step $T_LAT $L latency --scene $SCENE --mesh $MESH --seconds $LSEC --realtime --out $W/lat400s --trace $W/lat400s.trace.json
mkdir -p $W/res/lat400s; cp $W/lat400s/latency.* $W/res/lat400s/ 2>/dev/null; gzip -c $W/lat400s.trace.json > $W/res/lat400s/trace.json.gz 2>/dev/null; pack
step $T_DEMO $L demo --out $W/demo
mkdir -p $W/res/demo; cp $W/demo/*.png $W/res/demo/ 2>/dev/null; pack
step $T_SW $L latency --scene $SCENE --sweep --sweep-min $SMIN --sweep-max $SMAX --sweep-seconds 3 --realtime --out $W/sweep
mkdir -p $W/res/sweep; cp $W/sweep/latency.* $W/res/sweep/ 2>/dev/null; pack
# Issue 36's GPU goal: where the governor has nothing to do, the frame (renderer wake -> GPU done) p50
# within 5 % of the governor off: the default scene back to back, the governor from full quality.
for g in hold-deadline off; do
  step ${T_GOV:-60} $L latency --seconds $LSEC --governor $g --governor-start full --json --out $W/gov-$g
  mkdir -p $W/res/gov-$g; cp $W/gov-$g/latency.* $W/res/gov-$g/ 2>/dev/null; pack
done
python3 - "$W/res" > $W/res/governor.txt <<'PY' || true
import json, sys
p50 = {}
for g in ("hold-deadline", "off"):
    r = json.load(open(f"{sys.argv[1]}/gov-{g}/latency.json"))
    r = r.get("run", r)
    row = next(x for x in r["rows"] if x["hop"] == "renderer wake -> GPU done")
    p50[g] = row["p50_ms"]
    print(f"governor {g}: renderer wake -> GPU done p50 {row['p50_ms']:.3f} ms, p99 {row['p99_ms']:.3f} ms, "
          f"{r['deadline_misses']} misses, quality at the end {r['final_quality']}, changes {r['quality_changes']}")
print(f"on / off: {p50['hold-deadline'] / p50['off']:.3f} (goal: within 0.95..1.05)")
PY
cat $W/res/governor.txt; pack
# Draw levels of detail (docs/lod.md): frame time per level and stereo/mono with LOD off and auto, 2 x 400k
# drawn small; a cargo bench, so only where cargo is on PATH.
if command -v cargo >/dev/null; then step ${T_LOD:-240} sh -c "cargo bench -p lungdyn-bench --bench render_looks -- --lod --vertices $MESH --size 320x240 --frames 30 > $W/res/lod.txt"; fi
ls -la $W/res $W/res/*; echo ALL DONE

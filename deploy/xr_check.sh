#!/usr/bin/env bash
# The OpenXR check: build Monado (pinned commit, minimal: its null compositor and simulated headset,
# no hardware drivers) outside the repository, then run `lungdyn demo --xr` through it headless
# and the test that requires it (tests/tests/openxr.rs with LUNGDYN_REQUIRE_XR=1). Run from the
# repository root:
#
#   deploy/xr_check.sh            # MONADO_DIR=~/.cache/lungdyn/monado, 10 s demo
#
# Needs (Debian 12 / Ubuntu): cmake ninja-build g++ pkg-config git libeigen3-dev glslang-tools
# libvulkan-dev libx11-xcb-dev libxcb-randr0-dev libudev-dev libopenxr-loader1, and a Vulkan driver
# (mesa-vulkan-drivers: lavapipe on a machine without a GPU). The script says which are missing and
# installs nothing. CI does not run it (more packages and a C/C++ build); docs/DEPLOY.md "OpenXR" says
# what it verified and what it cannot.
#
# Variables: MONADO_DIR (checkout and build, outside the repository), MONADO_GIT (where to clone
# from), MONADO_COMMIT (the pinned commit), JOBS (build jobs, default 2), XR_SECONDS (demo length),
# OUT (the demo's output folder).
set -euo pipefail
cd "$(dirname "$0")/.."
say() { printf 'xr_check: %s\n' "$*" >&2; }
die() { printf 'xr_check: %s\n' "$*" >&2; exit 1; }

MONADO_DIR=${MONADO_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/lungdyn/monado}
# The commit the check was verified with (Monado 21.0.0+, Nov 2022; it lives in this mirror of
# upstream's history — upstream is https://gitlab.freedesktop.org/monado/monado).
MONADO_GIT=${MONADO_GIT:-https://github.com/shinyquagsire23/monado.git}
MONADO_COMMIT=${MONADO_COMMIT:-f8e58ef6a16dc2717a764fa1f36fe801f0c7f43a}
JOBS=${JOBS:-2}
XR_SECONDS=${XR_SECONDS:-10}
OUT=${OUT:-$(mktemp -d)}
mkdir -p "$OUT"

# --- what the build needs -------------------------------------------------------------------------
missing=()
for tool in cmake ninja c++ pkg-config git glslangValidator python3 cargo; do
  command -v "$tool" >/dev/null || missing+=("$tool")
done
# libudev although Monado is configured with XRT_HAVE_LIBUDEV=OFF below: its CMakeLists asks
# `find_package(udev REQUIRED)` on Linux whatever the option says.
for pc in eigen3 vulkan x11-xcb xcb-randr libudev; do
  pkg-config --exists "$pc" 2>/dev/null || missing+=("$pc (pkg-config)")
done
# ldconfig lives in /sbin (not on a Debian user's PATH); read its list whole (grep -q stopping early
# would SIGPIPE ldconfig and, under pipefail, read as "missing").
libs=$(PATH=$PATH:/sbin:/usr/sbin ldconfig -p 2>/dev/null || true)
grep -q 'libopenxr_loader.so.1' <<<"$libs" || missing+=("libopenxr_loader.so.1")
if [ ${#missing[@]} -gt 0 ]; then
  die "missing: ${missing[*]}. Install (Debian/Ubuntu, as root): apt-get install cmake ninja-build g++ \
pkg-config git libeigen3-dev glslang-tools libvulkan-dev libx11-xcb-dev libxcb-randr0-dev libudev-dev \
libopenxr-loader1 mesa-vulkan-drivers"
fi

# --- Monado, pinned and minimal ------------------------------------------------------------------
if [ ! -d "$MONADO_DIR/.git" ]; then
  say "cloning Monado from $MONADO_GIT into $MONADO_DIR"
  mkdir -p "$(dirname "$MONADO_DIR")"
  git clone --quiet "$MONADO_GIT" "$MONADO_DIR"
elif ! git -C "$MONADO_DIR" cat-file -e "$MONADO_COMMIT^{commit}" 2>/dev/null; then
  say "fetching $MONADO_COMMIT from $MONADO_GIT into $MONADO_DIR"
  git -C "$MONADO_DIR" fetch --quiet "$MONADO_GIT" || true
fi
git -C "$MONADO_DIR" checkout --quiet "$MONADO_COMMIT" ||
  die "commit $MONADO_COMMIT is not in $MONADO_DIR (clone of $MONADO_GIT): set MONADO_GIT to a clone that has it"
# Every hardware driver off but the simulated headset; only the null compositor is used (the main
# one is built because this Monado's runtime target links it unconditionally; it needs xcb).
drivers=$(grep -o 'XRT_BUILD_DRIVER_[A-Z0-9_]*' "$MONADO_DIR/CMakeLists.txt" | sort -u | grep -v SIMULATED |
  sed 's/^/-D/; s/$/=OFF/')
# shellcheck disable=SC2086
cmake -S "$MONADO_DIR" -B "$MONADO_DIR/build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DBUILD_TESTING=OFF -DXRT_BUILD_SAMPLES=OFF \
  -DXRT_FEATURE_COMPOSITOR_MAIN=ON -DXRT_FEATURE_COMPOSITOR_NULL=ON -DXRT_HAVE_XCB=ON \
  -DXRT_FEATURE_IPC=OFF -DXRT_FEATURE_SERVICE=OFF -DXRT_FEATURE_STEAMVR_PLUGIN=OFF \
  -DXRT_FEATURE_CLIENT_DEBUG_GUI=OFF -DXRT_FEATURE_WINDOW_PEEK=OFF -DXRT_FEATURE_RENDERDOC=OFF \
  -DXRT_HAVE_OPENGL=OFF -DXRT_HAVE_OPENGL_GLX=OFF -DXRT_HAVE_OPENGLES=OFF -DXRT_HAVE_EGL=OFF \
  -DXRT_HAVE_SDL2=OFF -DXRT_HAVE_WAYLAND=OFF -DXRT_HAVE_XLIB=OFF -DXRT_HAVE_XRANDR=OFF \
  -DXRT_HAVE_DBUS=OFF -DXRT_HAVE_LIBUDEV=OFF -DXRT_HAVE_LIBBSD=OFF -DXRT_HAVE_SYSTEMD=OFF \
  -DXRT_HAVE_OPENCV=OFF -DXRT_HAVE_LIBUSB=OFF -DXRT_HAVE_HIDAPI=OFF -DXRT_HAVE_JPEG=OFF \
  -DXRT_HAVE_FFMPEG=OFF -DXRT_HAVE_GST=OFF -DXRT_HAVE_BLUETOOTH=OFF $drivers >"$MONADO_DIR/cmake.log" ||
  die "configuring Monado failed: see $MONADO_DIR/cmake.log"
say "building Monado's in-process runtime ($JOBS jobs)"
nice -n 10 ninja -C "$MONADO_DIR/build" -j "$JOBS" openxr_monado >"$MONADO_DIR/build.log" ||
  die "building Monado failed: see $MONADO_DIR/build.log"
MANIFEST=$MONADO_DIR/build/openxr_monado-dev.json
[ -f "$MANIFEST" ] || die "Monado built no manifest at $MANIFEST"

# --- the launcher with OpenXR, run through the runtime ----------------------------------------------
say "building lungdyn with --features openxr"
cargo build --release -p lungdyn --features openxr
export XR_RUNTIME_JSON=$MANIFEST LUNGDYN_XR_RUNTIME=$MANIFEST XRT_COMPOSITOR_NULL=1 WGPU_BACKEND=${WGPU_BACKEND:-vulkan}
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-$(mktemp -d)}
say "lungdyn demo --xr --seconds $XR_SECONDS through $MANIFEST (null compositor, simulated HMD)"
target/release/lungdyn demo --xr --seconds "$XR_SECONDS" --json --out "$OUT" >"$OUT/report.json" 2>"$OUT/stderr.txt" ||
  { tail -40 "$OUT/stderr.txt" >&2; die "the demo through OpenXR failed (all of its stderr: $OUT/stderr.txt)"; }
xr_line=$(grep "frames waited for" "$OUT/stderr.txt") || die "the renderer did not say what it gave the runtime"
python3 - "$OUT/report.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
assert r["present_mode"] == "openxr" and r["ended"] == "completed" and r["restarts"] == 0, r
print(f"xr_check: verified: {r['frames_rendered']} frames in {r['seconds']:.1f} s ({r['fps']:.1f} fps), "
      f"{r['presented_frames']} presented through OpenXR, run {r['ended']}, no restarts; "
      f"submit -> xrEndFrame returned p50 {r['submit_to_present_p50_ms']:.1f} ms, p99 "
      f"{r['submit_to_present_p99_ms']:.1f} ms", file=sys.stderr)
PY
say "verified: ${xr_line#*: openxr: }"
say "the test that requires a runtime (LUNGDYN_REQUIRE_XR=1)"
LUNGDYN_REQUIRE_XR=1 cargo test --release -p lungdyn-tests --test openxr
say "done: Monado $MONADO_COMMIT, null compositor, simulated HMD; the demo's output is in $OUT"

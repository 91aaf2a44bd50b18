#!/bin/bash
# The systemd watchdog check (issue 23): boots a Debian/Ubuntu root file system with systemd as PID 1
# in a container (systemd-nspawn), installs the service there with `lungdyn install`, starts
# lungdyn.target on a virtual X display, then hangs each process in turn with SIGSTOP and times how
# long systemd's watchdog takes to abort it and have a new process running and READY. The goal:
# restarted within WatchdogSec + 1 s. Works on a host without a running systemd (a container or a
# VM like our development machine): nspawn is told not to register with machined or make a scope.
#
#   sudo deploy/watchdog_check.sh ROOTFS [LUNGDYN] [OUT]
#
# ROOTFS: a root file system with systemd, Xvfb and a Vulkan driver (lavapipe will do), e.g.
#   sudo debootstrap --variant=minbase bookworm ROOTFS && sudo chroot ROOTFS apt-get install -y \
#     systemd systemd-sysv dbus xvfb xauth mesa-vulkan-drivers libvulkan1 libx11-6 \
#     libxkbcommon-x11-0 libxcursor1 libxrandr2 libxi6
# LUNGDYN: the lungdyn binary (default target/release/lungdyn); copied into ROOTFS/opt/lungdyn-check.
# OUT: a folder for the report (default out/watchdog): watchdog.md and the container's journal.
# The host needs systemd-nspawn (Debian/Ubuntu: apt-get install systemd-container) and root.
# The container is powered off at the end (or on any failure); ROOTFS keeps /usr/local's install.
set -euo pipefail
ROOTFS=${1:?usage: deploy/watchdog_check.sh ROOTFS [LUNGDYN] [OUT]}
BIN=${2:-target/release/lungdyn}
OUT=${3:-out/watchdog}
WD=${WATCHDOG_SEC:-2}
NAME=lungdyn-wd-$$
die() { echo "watchdog_check: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "needs root (systemd-nspawn): sudo $0 $*"
command -v systemd-nspawn >/dev/null || die "no systemd-nspawn: apt-get install systemd-container"
command -v nsenter >/dev/null || die "no nsenter: apt-get install util-linux"
command -v pgrep >/dev/null || die "no pgrep: apt-get install procps"
[ -x "$ROOTFS/lib/systemd/systemd" ] || [ -x "$ROOTFS/usr/lib/systemd/systemd" ] ||
  die "$ROOTFS has no systemd (install systemd systemd-sysv in it; see the header of this script)"
[ -x "$ROOTFS/usr/bin/Xvfb" ] || die "$ROOTFS has no Xvfb (the renderer unit draws on DISPLAY=:0): install xvfb in it"
[ -x "$BIN" ] || die "no lungdyn binary at $BIN: cargo build --release --bin lungdyn, or name it"
mkdir -p "$OUT" "$ROOTFS/opt/lungdyn-check"
cp "$BIN" "$ROOTFS/opt/lungdyn-check/lungdyn"
# The units run the thin role binaries, which install takes from beside lungdyn.
for role in engine renderer tracker-bridge; do
  [ -x "$(dirname "$BIN")/$role" ] ||
    die "no $role binary beside $BIN: cargo build --release -p engine -p renderer -p tracker-bridge"
  cp "$(dirname "$BIN")/$role" "$ROOTFS/opt/lungdyn-check/$role"
done
# A binary built against a newer C library than ROOTFS's would only fail inside the container.
chroot "$ROOTFS" /opt/lungdyn-check/lungdyn --version >/dev/null 2>"$OUT/version.err" ||
  die "$BIN does not run in $ROOTFS: $(head -3 "$OUT/version.err") (build it on a system no newer than ROOTFS)"

systemd-nspawn -D "$ROOTFS" --boot --register=no --keep-unit -M "$NAME" --console=passive \
  >"$OUT/nspawn.log" 2>&1 &
NSPAWN=$!
PID1=""
inside() { nsenter -t "$PID1" -m -u -i -n -p -C -- /bin/bash -c "$1"; }
cleanup() {
  if [ -n "$PID1" ]; then inside 'journalctl --no-pager -o short-precise' >"$OUT/journal.txt" 2>&1 || true
    inside 'systemctl poweroff' >/dev/null 2>&1 || true; fi
  for _ in $(seq 100); do kill -0 "$NSPAWN" 2>/dev/null || break; sleep 0.1; done
  kill "$NSPAWN" 2>/dev/null || true
}
trap cleanup EXIT
# The container's PID 1: nspawn's descendant that is PID 1 in its own namespace and runs systemd
# (nspawn forks an intermediate child first, so its first child is not it).
container_pid1() {
  local p
  for p in $(pgrep -P "$NSPAWN" 2>/dev/null) $(for c in $(pgrep -P "$NSPAWN" 2>/dev/null); do pgrep -P "$c"; done); do
    if awk '/^NSpid:/ {exit !($NF == 1 && NF > 2)}' "/proc/$p/status" 2>/dev/null &&
      [ "$(cat "/proc/$p/comm" 2>/dev/null)" = systemd ]; then echo "$p"; return; fi
  done
}
for _ in $(seq 300); do PID1=$(container_pid1); [ -n "$PID1" ] && break; sleep 0.1; done
[ -n "$PID1" ] || die "the container did not start: $(tail -5 "$OUT/nspawn.log")"
st=""
for _ in $(seq 600); do
  st=$(inside 'systemctl is-system-running' 2>/dev/null || true)
  case "$st" in running|degraded) break ;; esac; sleep 0.1; done
case "$st" in running|degraded) ;; *) die "the container's systemd did not come up (is-system-running: '$st')" ;; esac
echo "container $NAME: systemd $(inside 'systemctl --version | head -1 | cut -d" " -f2') is $st"

inside "set -e
  /opt/lungdyn-check/lungdyn install --prefix /usr/local --watchdog-sec $WD >/root/install.log 2>&1
  groupadd -f -r lungdyn
  for g in video render dialout; do getent group \$g >/dev/null || groupadd -r \$g; done
  id lungdyn >/dev/null 2>&1 || useradd -r -g lungdyn -G video,render,dialout lungdyn
  systemd-run --quiet --unit=lungdyn-check-xvfb /usr/bin/Xvfb :0 -screen 0 1280x720x24 -ac -nolisten tcp
  for _ in \$(seq 100); do [ -S /tmp/.X11-unix/X0 ] && break; sleep 0.1; done
  systemctl daemon-reload
  systemctl start lungdyn.target" ||
  die "setting up the service in the container failed: $(tail -5 "$ROOTFS/root/install.log" 2>/dev/null)"

now() { date +%s.%N; }
report="$OUT/watchdog.md"
restart=$(inside "systemctl show -p RestartUSec --value lungdyn-engine")
{
  echo "# The systemd watchdog restarting a hung process"
  echo
  echo "$(date -u +%F) on $(uname -n) ($(nproc) cores), container \`$ROOTFS\` booted with systemd-nspawn, systemd"
  echo "$(inside 'systemctl --version | head -1'), WatchdogSec=$WD, RestartSec=$restart; each unit's main process stopped with"
  echo "SIGSTOP while the three ran together under lungdyn.target (the renderer on Xvfb :0, lavapipe)."
  echo "Goal: a new process running and READY within WatchdogSec + 1 s = $((WD + 1)) s of the SIGSTOP."
  echo
  echo "| unit | stopped pid | watchdog fired after | new pid READY after | restarts | within goal |"
  echo "|---|---:|---:|---:|---:|---|"
} >"$report"
fail=0
for unit in lungdyn-tracker-bridge lungdyn-engine lungdyn-renderer; do
  for _ in $(seq 300); do
    [ "$(inside "systemctl show -p SubState --value $unit")" = running ] && break; sleep 0.1; done
  sleep 3  # let it settle into its loop (pings every WatchdogSec/2)
  old=$(inside "systemctl show -p MainPID --value $unit")
  [ "$old" != 0 ] || die "$unit is not running: $(inside "systemctl status $unit --no-pager | tail -5")"
  t0=$(now); inside "kill -STOP $old"
  new=""
  for _ in $(seq 200); do  # up to 10 s
    cur=$(inside "systemctl show -p MainPID --value $unit"); sub=$(inside "systemctl show -p SubState --value $unit")
    if [ "$cur" != "$old" ] && [ "$cur" != 0 ] && [ "$sub" = running ]; then new=$cur; break; fi
    sleep 0.05
  done
  restarts=$(inside "systemctl show -p NRestarts --value $unit")
  # The journal's own times (-o short-unix): the watchdog's abort, and "Started" (Type=notify: READY=1).
  j=$(inside "journalctl -u $unit.service --no-pager -q -o short-unix --since=@${t0%.*}")
  fired=$(echo "$j" | awk -v t="$t0" '/Watchdog timeout/ && $1 >= t {print $1; exit}')
  ready=$(echo "$j" | awk -v t="$t0" '/Started lungdyn/ && $1 >= t {print $1; exit}')
  if [ -z "$new" ] || [ -z "$ready" ]; then
    echo "| $unit | $old | ${fired:+$(awk -v a="$t0" -v b="$fired" 'BEGIN{printf "%.2f s", b-a}')} | not restarted in 10 s | $restarts | **no** |" >>"$report"
    fail=1; continue; fi
  f="(no watchdog line)"; [ -z "$fired" ] || f=$(awk -v a="$t0" -v b="$fired" 'BEGIN{printf "%.2f s", b-a}')
  r=$(awk -v a="$t0" -v b="$ready" 'BEGIN{printf "%.2f", b-a}')
  ok=$(awk -v r="$r" -v g="$((WD + 1))" 'BEGIN{print (r <= g) ? "yes" : "**no**"}')
  [ -n "$fired" ] || ok="**no** (not the watchdog)"
  [ "$ok" = yes ] || fail=1
  echo "| $unit | $old | $f | $r s | $restarts | $ok |" >>"$report"
done
{
  echo
  echo "Journal lines of the watchdog's actions (all units):"
  echo
  echo '```'
  inside "journalctl -b --no-pager -o short-precise -u 'lungdyn-*' | grep -E 'Watchdog timeout|Killing process|Scheduled restart|Started lungdyn'"
  echo '```'
} >>"$report"
# A process that fails at every start (a drop-in makes the engine's ExecStart /bin/false): systemd
# restarts it RestartSec apart until StartLimitBurst starts within StartLimitIntervalSec, then leaves
# it failed ("Start request repeated too quickly"; systemd 252 keeps Result=exit-code, newer ones say
# start-limit-hit) — it must not spin for ever, nor give up at once.
burst=$(inside "systemctl show -p StartLimitBurst --value lungdyn-engine")
t0=$(now)
inside "mkdir -p /run/systemd/system/lungdyn-engine.service.d &&
  printf '[Service]\nExecStart=\nExecStart=/bin/false\n' >/run/systemd/system/lungdyn-engine.service.d/crash.conf &&
  systemctl daemon-reload && systemctl reset-failed lungdyn-engine; systemctl restart lungdyn-engine" || true
limit=""
for _ in $(seq 900); do  # up to 90 s
  j=$(inside "journalctl -b -u lungdyn-engine.service --no-pager -q -o short-unix --since=@${t0%.*}")
  limit=$(echo "$j" | awk -v t="$t0" '/Start request repeated too quickly/ && $1 >= t {print $1; exit}')
  [ -n "$limit" ] && [ "$(inside "systemctl show -p ActiveState --value lungdyn-engine")" = failed ] && break
  sleep 0.1
done
result=$(inside "systemctl show -p Result --value lungdyn-engine")
starts=$(echo "$j" | awk -v t="$t0" '/Starting lungdyn-engine/ && $1 >= t' | wc -l)
gave_up=$(awk -v a="$t0" -v b="${limit:-$t0}" 'BEGIN{printf "%.1f", b-a}')
inside "rm -rf /run/systemd/system/lungdyn-engine.service.d && systemctl daemon-reload &&
  systemctl reset-failed lungdyn-engine && systemctl start lungdyn-engine" || true
{
  echo
  echo "A crash loop (the engine's ExecStart replaced by /bin/false in a drop-in): systemd started it"
  if [ -n "$limit" ]; then
    echo "$starts times and gave up after $gave_up s (\"Start request repeated too quickly\", Result=$result;"
  else
    echo "$starts times and had **not** given up after 90 s (Result=$result;"
  fi
  echo "StartLimitBurst=$burst in StartLimitIntervalSec=60, RestartSec=$restart)."
} >>"$report"
if [ -z "$limit" ]; then
  echo "the crash loop was not stopped by the start limit" >&2; fail=1
fi
cat "$report"
[ "$fail" = 0 ] || die "a unit was not restarted within WatchdogSec + 1 s, or a crash loop was not stopped (see $report)"

#!/usr/bin/env python3
"""Every latency and frame-rate figure the README and docs quote, measured again in one command,
with the date and the machine (issue 36 item 3).

    python3 bench/figures.py [--out docs/latency/figures-DATE] [--seconds 60] [--quick]

Runs, one after another on the built release binaries (build them first:
`cargo build --release -p lungdyn -p engine -p renderer -p tracker-bridge`), with nothing else
meant to run beside them:
  1. `lungdyn latency --seconds S` with the quality governor, then `--governor off` (back to back);
  2. `lungdyn demo --seconds 12` with and without the governor (frames per second, misses);
  3. the time to the first frame, `demo --seconds 3` into a new folder and again (cold, warm);
  4. a heavy scene's start (`lungdyn latency --mesh 100000 --seconds 30`): a first run that keeps
     where the governor settled, then `--governor-start full` and `--governor-start remembered`;
  5. unless --quick: `cargo bench -p lungdyn-bench --bench render_looks -- --frames 40` (each look's
     frame) and `-- --lod --vertices 10000 --size 800x600` (each draw level).
Writes figures.json (every number, with the commands) and figures.md (the tables the docs quote)
into --out, and prints figures.md. Each step's own output (latency.md and its plot and trace, the
demo's pictures and kernels: tens of MB) goes under --runs (default out/figures-runs-DATE, not in the
repository). Every run keeps its cache (draw levels, where the governor settled) in a folder of
this run's own (LUNGDYN_CACHE_DIR), so no earlier run changes where these start. Exits non-zero,
naming the step, when a command fails.
"""

import argparse
import datetime
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LUNGDYN = os.path.join(ROOT, "target", "release", "lungdyn")


def run(cmd, what, env=None):
    """Run cmd (a list); return (stdout, stderr); exit naming `what` when it fails."""
    print(f"figures: {what}: {' '.join(cmd)}", file=sys.stderr, flush=True)
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    if p.returncode != 0:
        sys.exit(f"figures: {what} failed (exit {p.returncode}):\n{p.stderr[-3000:]}")
    return p.stdout, p.stderr


def machine():
    cpu = platform.processor() or "?"
    try:
        with open("/proc/cpuinfo") as f:
            m = re.search(r"model name\s*:\s*(.+)", f.read())
            cpu = m.group(1).strip() if m else cpu
    except OSError:
        pass
    return {
        "host": platform.node(),
        "cores": os.cpu_count(),
        "cpu": cpu,
        "kernel": platform.release(),
        "load_average": os.getloadavg(),
    }


def latency(runs, seconds, governor, extra=(), tag=""):
    d = os.path.join(runs, f"latency-{governor}{tag}")
    stdout, stderr = run(
        [LUNGDYN, "latency", "--seconds", str(seconds), "--governor", governor, "--json",
         "--out", d] + list(extra),
        f"latency, governor {governor} {' '.join(extra)}",
    )
    r = json.loads(stdout)
    r = r.get("run", r)
    adapter = re.search(r"GPU adapter (.+)", stderr)
    return {
        "command": f"lungdyn latency --seconds {seconds} --governor {governor} {' '.join(extra)}".strip(),
        "adapter": adapter.group(1).strip() if adapter else None,
        "frames": r["frames"],
        "fps": r["frames"] / r["seconds"] if r["seconds"] else 0.0,
        "deadline_misses": r["deadline_misses"],
        "late_frames": r["late_frames"],
        "missed_frame_slots": r["missed_frame_slots"],
        "capture_to_submit_p99_ms": r["capture_to_submit_p99_ms"],
        "capture_to_gpu_done_p99_ms": r["capture_to_gpu_done_p99_ms"],
        "final_quality": r["final_quality"],
        "first_quality": r.get("first_quality"),
        "quality_frames": r["quality_frames"],
        "governor_floor_frames": r["governor_floor_frames"],
    }


def demo(name, out, args):
    """`lungdyn demo ARGS --json --out OUT`."""
    stdout, _ = run([LUNGDYN, "demo", "--json", "--out", out] + args, f"demo ({name})")
    v = json.loads(stdout)
    return {
        "command": "lungdyn demo " + " ".join(args),
        "frames": v["frames_rendered"],
        "fps": v["fps"],
        "deadline_misses": v["deadline_misses"],
        "end_to_end_p99_ms": v["end_to_end_p99_ms"],
        "first_frame_s": v["first_frame_s"],
        "final_quality": v["final_quality"],
    }


def render_looks(extra):
    stdout, stderr = run(
        ["cargo", "bench", "-p", "lungdyn-bench", "--bench", "render_looks", "--"] + extra,
        "render_looks " + " ".join(extra),
    )
    # The bench's table and its header lines, without cargo's own.
    noise = ("Compiling", "Finished", "Running", "warning", "Blocking", "Updating")
    rows = [line.rstrip() for line in (stderr + "\n" + stdout).splitlines()
            if line.strip() and not line.strip().startswith(noise)]
    return {"command": "cargo bench -p lungdyn-bench --bench render_looks -- " + " ".join(extra),
            "lines": rows}


def markdown(f):
    m = f["machine"]
    s = [f"# Figures measured {f['date']}\n",
         f"Machine: `{m['host']}`, {m['cores']} cores ({m['cpu']}), Linux {m['kernel']}, "
         f"load average at the start {m['load_average'][0]:.2f}; GPU adapter: "
         f"{f['latency']['hold-deadline']['adapter']}. Command: `python3 bench/figures.py`"
         f"{' --quick' if f['quick'] else ''}.\n",
         "## `lungdyn latency`, default scene, back to back\n",
         "| governor | frames | fps | deadline misses (late + empty slots) | capture → submit p99 | "
         "capture → GPU done p99 | quality at the end | frames at the floor |",
         "|---|---:|---:|---:|---:|---:|---|---:|"]
    for g, r in f["latency"].items():
        s.append(f"| {g} | {r['frames']} | {r['fps']:.1f} | {r['deadline_misses']} "
                 f"({r['late_frames']} + {r['missed_frame_slots']}) | "
                 f"{r['capture_to_submit_p99_ms']:.1f} ms | {r['capture_to_gpu_done_p99_ms']:.1f} ms | "
                 f"{r['final_quality']} | {r['governor_floor_frames']} |")
    s += ["\n## `lungdyn demo`, default scene\n",
          "| run | frames | fps | deadline misses (capture → submit) | end to end p99 | "
          "first frame after the command's start | quality at the end |",
          "|---|---:|---:|---:|---:|---:|---|"]
    for name, r in f["demo"].items():
        s.append(f"| {name} (`{r['command']}`) | {r['frames']} | {r['fps']:.1f} | "
                 f"{r['deadline_misses']} | {r['end_to_end_p99_ms']:.1f} ms | "
                 f"{r['first_frame_s']:.2f} s | {r['final_quality']} |")
    if f.get("heavy_start"):
        s += ["\n## A heavy scene's start: `lungdyn latency --mesh 100000 --seconds 30`\n",
              "| run | frames | deadline misses | capture → GPU done p99 | first frame at | "
              "last frame at |",
              "|---|---:|---:|---:|---|---|"]
        for name, r in f["heavy_start"].items():
            s.append(f"| {name} | {r['frames']} | {r['deadline_misses']} | "
                     f"{r['capture_to_gpu_done_p99_ms']:.1f} ms | {r['first_quality']} | "
                     f"{r['final_quality']} |")
    for k, b in f.get("render_looks", {}).items():
        s += [f"\n## `{b['command']}`\n", "```"] + b["lines"] + ["```"]
    return "\n".join(s) + "\n"


def main():
    today = datetime.date.today().isoformat()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "latency", f"figures-{today}"))
    ap.add_argument("--runs", default=os.path.join(ROOT, "out", f"figures-runs-{today}"))
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--quick", action="store_true", help="leave out the render_looks benches")
    a = ap.parse_args()
    if not (a.seconds > 0 and a.seconds <= 3600):
        sys.exit(f"figures: --seconds {a.seconds}: give 1..3600")
    if not os.access(LUNGDYN, os.X_OK):
        sys.exit(f"figures: {LUNGDYN} is not built: cargo build --release -p lungdyn -p engine "
                 "-p renderer -p tracker-bridge")
    os.makedirs(a.out, exist_ok=True)
    os.makedirs(a.runs, exist_ok=True)
    cache = os.path.join(a.runs, "cache")
    shutil.rmtree(cache, ignore_errors=True)
    os.environ["LUNGDYN_CACHE_DIR"] = cache
    f = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
         "machine": machine(), "quick": a.quick, "latency": {}, "demo": {}}
    for g in ["hold-deadline", "off"]:
        f["latency"][g] = latency(a.runs, a.seconds, g)
    for g in ["hold-deadline", "off"]:
        f["demo"][f"governor {g}"] = demo(
            f"governor {g}", os.path.join(a.runs, f"demo-{g}"),
            ["--seconds", "12", "--governor", g])
    fresh = tempfile.mkdtemp(prefix="lungdyn-figures-")
    try:
        for when in ["cold", "warm"]:
            f["demo"][f"first frame, {when}"] = demo(
                f"first frame, {when}", fresh, ["--seconds", "3", "--snapshots", "0"])
    finally:
        shutil.rmtree(fresh, ignore_errors=True)
    f["heavy_start"] = {}
    for name, start in [("first run (nothing kept)", "remembered"), ("from full quality", "full"),
                        ("where the first run settled", "remembered")]:
        f["heavy_start"][name] = latency(
            a.runs, 30, "hold-deadline", ["--mesh", "100000", "--governor-start", start],
            tag=f"-100k-{len(f['heavy_start'])}")
    if not a.quick:
        f["render_looks"] = {"looks": render_looks(["--frames", "40"]),
                             "levels": render_looks(["--lod", "--vertices", "10000", "--size",
                                                     "800x600", "--frames", "40"])}
    with open(os.path.join(a.out, "figures.json"), "w") as w:
        json.dump(f, w, indent=1)
    md = markdown(f)
    with open(os.path.join(a.out, "figures.md"), "w") as w:
        w.write(md)
    print(md)


if __name__ == "__main__":
    main()

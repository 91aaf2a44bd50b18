#!/usr/bin/env python3
"""A real chest belt's respiration signal as a lungdyn trace: BioSPPy's example `examples/resp.txt`
(github.com/PIA-Group/BioSPPy, BSD-3-Clause, (c) 2015 Instituto de Telecomunicacoes; 60 s at 1 kHz,
12-bit, the sensor not stated) averaged to 25 Hz and written as `time_s,amplitude_au`.

    python3 bench/belt_trace.py PATH/TO/BioSPPy/examples/resp.txt belt_25hz.csv [--rate-hz 25]

then `lungdyn breathing check belt_25hz.csv` (docs/BREATHING.md "A chest belt") or
the README's animation of the lungs following it (docs/images/breath_follow.gif):

    lungdyn demo --scene docs/images/readme_scene.toml --breathing trace:belt_25hz.csv \
        --record docs/images/breath_follow.gif --record-frames 36 --snapshot-at-s 40 --seconds 50

The signal is not in the repository: get it from BioSPPy's
repository. The header is checked (its sampling rate and one `Resp` column); the values are the
converter's counts, + = inspiration as recorded (the belt stretches on inspiration).
"""
import argparse, os, sys


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("resp", help="BioSPPy's examples/resp.txt")
    ap.add_argument("out", help="the trace CSV to write")
    ap.add_argument("--rate-hz", type=float, default=25.0, help="rate of the trace written (divides 1000)")
    a = ap.parse_args()
    rate, values = None, []
    with open(a.resp) as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if line.startswith("#"):
                if "Sampling Rate" in line:
                    rate = float(line.split("=")[-1])
                elif "Labels" in line and line.split("=")[-1].strip() != "Resp":
                    sys.exit(f"{a.resp}: line {n}: labels {line!r}: expected one Resp column")
                continue
            if line:
                try:
                    values.append(float(line))
                except ValueError:
                    sys.exit(f"{a.resp}: line {n}: {line!r} is not a number")
    if rate is None:
        sys.exit(f"{a.resp}: no '# Sampling Rate (Hz):= ...' header line: is this BioSPPy's resp.txt?")
    if not (a.rate_hz > 0 and a.rate_hz < float("inf")):
        sys.exit(f"--rate-hz {a.rate_hz}: give a rate above 0 that divides the file's {rate:g} Hz")
    block = rate / a.rate_hz
    if block < 1 or abs(block - round(block)) > 1e-9:
        sys.exit(f"--rate-hz {a.rate_hz}: give a divisor of the file's {rate:g} Hz")
    block = int(round(block))
    if len(values) < block * a.rate_hz * 10:
        sys.exit(f"{a.resp}: {len(values)} samples: under 10 s at {rate:g} Hz")
    tmp = a.out + ".tmp"
    try:
        with open(tmp, "w") as f:
            f.write("time_s,amplitude_au\n")
            # Each block's mean at the block's centre.
            for i in range(0, len(values) - block + 1, block):
                f.write(f"{(i + (block - 1) / 2) / rate:.4f},{sum(values[i:i + block]) / block:.2f}\n")
        os.replace(tmp, a.out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    print(f"wrote {a.out}: {len(values) // block} samples at {a.rate_hz:g} Hz ({len(values) / rate:.1f} s)",
          file=sys.stderr)


if __name__ == "__main__":
    main()

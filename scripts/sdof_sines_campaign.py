#!/usr/bin/env python3
"""A 1-DOF campaign on data nobody here simulated (ACCURACY.md, forty-sixth session).

A 2 kg mass on a spring (8,000 N/m) and a damper (4 N·s/m), driven by a sum of 20 sines of
1–15 Hz (frequencies and phases drawn from the seed) — a force smooth between samples, not
the simulator's piecewise-linear one — integrated by RK4 at 20 steps per sample, sampled at
1 kHz for 3,000 samples, displacement and velocity measured with Gaussian noise of NOISE
times each channel's RMS. Each record goes through `jointid import` (CSV) and `jointid
replay --json` (the defaults unless EXTRA arguments are given); the script prints each
seed's estimates in standard errors off the truth and the coverage of the 95 % intervals.

    python3 scripts/sdof_sines_campaign.py FROM COUNT NOISE [--motion] [--bin PATH] [-- EXTRA...]

`--motion` starts the mass at 4 mm and −0.2 m/s instead of at rest. Pure Python (no NumPy):
~0.5 s per record besides jointid's time.
"""
import argparse
import json
import math
import os
import random
import subprocess
import tempfile

SETUP = """title = "sdof: mass on a spring and a damper"
[model]
nodes = [{ id = 1, x = 0.0 }]
masses = [{ node = 1, mass = 2.0 }]
supports = [{ node = 1, fix = ["rz"] }]
[[excitation]]
name = "force"
dof = { node = 1, dir = "w" }
[[sensors]]
name = "disp"
dof = { node = 1, dir = "w" }
quantity = "displacement"
[[sensors]]
name = "vel"
dof = { node = 1, dir = "w" }
quantity = "velocity"
[[connections]]
name = "j"
dof = { node = 1, dir = "w" }
basis = ["u", "v"]
initial = [0.0, 0.0]
truth = [8000.0, 4.0]
[integrator]
dt_s = 1.0e-3
"""
M, K, C, DT, N, SUB = 2.0, 8000.0, 4.0, 1e-3, 3000, 20
TRUTH = [K, C]


def record(seed, noise, motion):
    """Rows (t, force, disp, vel) of one test, the noise added."""
    rng = random.Random(seed)
    sines = [(1.0 + 14.0 * rng.random(), 2 * math.pi * rng.random()) for _ in range(20)]

    def force(t):
        return sum(10.0 * math.sin(2 * math.pi * f * t + p) for f, p in sines)

    def acc(t, x, v):
        return (force(t) - K * x - C * v) / M

    x, v = (0.004, -0.2) if motion else (0.0, 0.0)
    rows = []
    h = DT / SUB
    for i in range(N):
        t = i * DT
        rows.append((t, force(t), x, v))
        for s in range(SUB):
            tt = t + s * h
            k1x, k1v = v, acc(tt, x, v)
            k2x, k2v = v + h / 2 * k1v, acc(tt + h / 2, x + h / 2 * k1x, v + h / 2 * k1v)
            k3x, k3v = v + h / 2 * k2v, acc(tt + h / 2, x + h / 2 * k2x, v + h / 2 * k2v)
            k4x, k4v = v + h * k3v, acc(tt + h, x + h * k3x, v + h * k3v)
            x += h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
            v += h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    rms_d = math.sqrt(sum(r[2] ** 2 for r in rows) / N)
    rms_v = math.sqrt(sum(r[3] ** 2 for r in rows) / N)
    return [
        (t, f, d + noise * rms_d * rng.gauss(0, 1), u + noise * rms_v * rng.gauss(0, 1))
        for t, f, d, u in rows
    ]


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("first", type=int)
    ap.add_argument("count", type=int)
    ap.add_argument("noise", type=float)
    ap.add_argument("--motion", action="store_true")
    ap.add_argument("--bin", default=os.path.join(here, "..", "target", "release", "jointid"))
    ap.add_argument("extra", nargs="*")
    a = ap.parse_args()
    inside, worst, answered = [0, 0], [0.0, 0.0], 0
    with tempfile.TemporaryDirectory() as d:
        setup = os.path.join(d, "sdof.toml")
        with open(setup, "w") as fh:
            fh.write(SETUP)
        for seed in range(a.first, a.first + a.count):
            csv = os.path.join(d, f"s{seed}.csv")
            with open(csv, "w") as fh:
                fh.write("t,force,disp,vel\n")
                for r in record(seed, a.noise, a.motion):
                    fh.write("%.9e,%.9e,%.9e,%.9e\n" % r)
            rec = os.path.join(d, f"s{seed}.mcap")
            subprocess.run(
                [a.bin, "import", csv, "--setup", setup, "--out", rec],
                check=True,
                capture_output=True,
            )
            out = subprocess.run(
                [a.bin, "replay", rec, "--json"] + a.extra, capture_output=True, text=True
            )
            if out.returncode != 0:
                print(f"seed {seed}: exit {out.returncode}: {out.stderr.strip()[-300:]}")
                continue
            answered += 1
            fit = json.loads(out.stdout)
            line = []
            for i, (p, truth) in enumerate(zip(fit["parameters"], TRUTH)):
                z = (p["value"] - truth) / p["std_error"]
                inside[i] += abs(z) <= 1.96
                worst[i] = max(worst[i], abs(z))
                line.append(f"{p['basis']} {p['value']:.6g} ± {p['std_error']:.3g} ({z:+.2f} se)")
            print(f"seed {seed}: " + "; ".join(line), flush=True)
    start = "in motion" if a.motion else "at rest"
    print(
        f"noise {a.noise:g}, {start}: {answered} of {a.count} answered; coverage u {inside[0]}/{answered}, "
        f"v {inside[1]}/{answered}; worst u {worst[0]:.1f} se, v {worst[1]:.1f} se"
    )


main()

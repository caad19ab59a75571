#!/usr/bin/env python3
"""The paper's two-beam problem on data nobody here simulated (ACCURACY.md, fifty-eighth session).

The condensed 11-DOF component matrices of `recordings/two-beam-mm/` (what `jointid
export-mm` writes for the shipped two-beam setups) with the connection at node 6 carrying
the truth of a shipped setup — `friction`: 3,000 N `sign(u)` + 3e5 N/m; `spring`: 3e5 N/m
alone — driven at node 1 by a sum of 40 sines of 10–1,000 Hz (frequencies and phases drawn
from the seed, 20,000 N RMS: a force smooth between samples, not the simulator's piecewise
linear one; raised from 0 over ONSET s, 5 ms by default, as a shaker starts: a step of
20 kN rings the structure's undamped modes above the sampling rate for the whole record), integrated by classical RK4 at SUB steps per 0.1 ms sample (1,000 by default:
the friction's switch is not located, so each crossing costs an error of order the step;
the joint's force is `−Lc f` as in DESIGN.md), sampled for 2,000 samples, every displacement
and velocity channel given Gaussian noise of NOISE times its RMS. Each record goes through
`jointid import` (CSV) and `jointid replay --json` with the shipped setup and the defaults
(unless EXTRA arguments are given); the script prints each seed's estimates in standard
errors off the truth, the coverage of the 95 % intervals and the worst.

    python3 scripts/two_beam_campaign.py {friction,spring} FROM COUNT NOISE[,NOISE...] \
        [--motion] [--sub 1000] [--bin PATH] [-- EXTRA...]

`--motion` cuts every record 20 ms (LEAD samples) after the force started (a record cut from
a running test). Needs NumPy; the seeds of one
call are integrated together (vectorised), about 1–3 minutes for 30 records at `--sub 1000`.
"""
import argparse
import json
import math
import os
import subprocess
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.join(HERE, "..")
MM = os.path.join(REPO, "recordings", "two-beam-mm")
DT, N, RMS, SINES, BAND = 1.0e-4, 2000, 20_000.0, 40, (10.0, 1000.0)
FORCE_NODE, JOINT_NODE = 1, 6
LEAD = 200
SENSOR_NODES = [1, 3, 5, 7, 9, 11]
CASES = {
    # setup file, the truth's friction level (N) and stiffness (N/m)
    "friction": ("two-beam-friction.toml", 3000.0, 3.0e5),
    "spring": ("two-beam-spring.toml", 0.0, 3.0e5),
}


def read_mtx(path):
    """A symmetric Matrix Market coordinate file as a dense array."""
    with open(path) as fh:
        lines = [l for l in fh if not l.startswith("%")]
    n, _, _ = (int(x) for x in lines[0].split())
    a = np.zeros((n, n))
    for l in lines[1:]:
        i, j, v = l.split()
        i, j = int(i) - 1, int(j) - 1
        a[i, j] = a[j, i] = float(v)
    return a


def rows_of():
    """Node id → matrix row (0-based) from the DOF map."""
    rows = {}
    with open(os.path.join(MM, "dofs.csv")) as fh:
        next(fh)
        for l in fh:
            node, direction, row = l.strip().split(",")
            if direction == "w":
                rows[int(node)] = int(row) - 1
    return rows


def integrate(seeds, friction, stiffness, sub, motion, onset):
    """Sampled force (N × S) and displacements, velocities (N × 11 × S) of every seed."""
    M, K = read_mtx(os.path.join(MM, "mass.mtx")), read_mtx(os.path.join(MM, "stiffness.mtx"))
    minv = 1.0 / np.diag(M)
    assert np.allclose(M, np.diag(np.diag(M))), "lumped mass expected"
    rows = rows_of()
    ip, ic = rows[FORCE_NODE], rows[JOINT_NODE]
    S = len(seeds)
    draws = [np.random.default_rng(s) for s in seeds]
    freq = np.stack([r.uniform(*BAND, SINES) for r in draws], axis=1)  # (SINES, S)
    phase = np.stack([r.uniform(0, 2 * math.pi, SINES) for r in draws], axis=1)
    # Σ sin has mean square SINES / 2: scale each seed's sum to RMS.
    amp = RMS / math.sqrt(SINES / 2)

    # A record in motion: the test ran for LEAD samples before the record was cut.
    begin = -LEAD * DT if motion else 0.0

    def force(t, ph):
        since = t - begin
        ramp = 1.0 if since >= onset else 0.5 - 0.5 * math.cos(math.pi * since / onset)
        return ramp * amp * np.sin(2 * math.pi * freq * t + ph).sum(axis=0)

    def acc(t, x, v, ph):
        f = friction * np.sign(x[ic]) + stiffness * x[ic]
        r = -(K @ x)
        r[ip] += force(t, ph)
        r[ic] -= f
        return minv[:, None] * r

    h = DT / sub

    def run(samples, x, v, ph, keep, t0):
        out_f, out_x, out_v = [], [], []
        for i in range(samples):
            t = t0 + i * DT
            if keep:
                out_f.append(force(t, ph))
                out_x.append(x.copy())
                out_v.append(v.copy())
            for s in range(sub):
                tt = t + s * h
                k1x, k1v = v, acc(tt, x, v, ph)
                k2x, k2v = v + h / 2 * k1v, acc(tt + h / 2, x + h / 2 * k1x, v + h / 2 * k1v, ph)
                k3x, k3v = v + h / 2 * k2v, acc(tt + h / 2, x + h / 2 * k2x, v + h / 2 * k2v, ph)
                k4x, k4v = v + h * k3v, acc(tt + h, x + h * k3x, v + h * k3v, ph)
                x = x + h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
                v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        return x, v, out_f, out_x, out_v

    x = np.zeros((M.shape[0], S))
    v = np.zeros_like(x)
    if motion:
        x, v, *_ = run(LEAD, x, v, phase, False, begin)
    _, _, f, xs, vs = run(N, x, v, phase, True, 0.0)
    return np.array(f), np.array(xs), np.array(vs), rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=sorted(CASES))
    ap.add_argument("first", type=int)
    ap.add_argument("count", type=int)
    ap.add_argument("noise", help="comma-separated noise levels, fractions of each channel's RMS")
    ap.add_argument("--motion", action="store_true")
    ap.add_argument("--sub", type=int, default=1000)
    ap.add_argument("--onset", type=float, default=0.005, help="s of a raised-cosine ramp of the force from 0 (0: a step)")
    ap.add_argument("--bin", default=os.path.join(REPO, "target", "release", "jointid"))
    ap.add_argument("--keep", help="a directory to keep the CSV files in")
    ap.add_argument("extra", nargs="*")
    a = ap.parse_args()
    setup_file, friction, stiffness = CASES[a.case]
    setup = os.path.join(REPO, "recordings", setup_file)
    seeds = list(range(a.first, a.first + a.count))
    f, xs, vs, rows = integrate(seeds, friction, stiffness, a.sub, a.motion, a.onset)
    names = []
    cols = []
    for node in SENSOR_NODES:
        names += [f"node{node}.disp", f"node{node}.vel"]
        cols += [xs[:, rows[node], :], vs[:, rows[node], :]]
    truth = {"sign(u)": friction, "u": stiffness, "const(100)": 0.0, "v": 0.0}
    for level in (float(x) for x in a.noise.split(",")):
        stats = {}
        answered = 0
        with tempfile.TemporaryDirectory() as d:
            where = a.keep or d
            os.makedirs(where, exist_ok=True)
            for k, seed in enumerate(seeds):
                rng = np.random.default_rng([seed, int(round(level * 1e6))])
                data = [c[:, k] + level * math.sqrt(np.mean(c[:, k] ** 2)) * rng.standard_normal(N) for c in cols]
                csv = os.path.join(where, f"{a.case}_{seed}_{level:g}.csv")
                with open(csv, "w") as fh:
                    fh.write(",".join(["t", "node1.force"] + names) + "\n")
                    for i in range(N):
                        fh.write(",".join("%.12e" % x for x in [i * DT, f[i, k]] + [c[i] for c in data]) + "\n")
                rec = os.path.join(d, f"s{seed}.mcap")
                subprocess.run([a.bin, "import", csv, "--setup", setup, "--out", rec], check=True, capture_output=True)
                out = subprocess.run([a.bin, "replay", rec, "--json"] + a.extra, capture_output=True, text=True)
                if out.returncode != 0:
                    print(f"seed {seed}: exit {out.returncode}: {out.stderr.strip()[-300:]}", flush=True)
                    continue
                answered += 1
                fit = json.loads(out.stdout)
                line = []
                for p in fit["parameters"]:
                    z = (p["value"] - truth[p["basis"]]) / p["std_error"]
                    s = stats.setdefault(p["basis"], [0, 0.0])
                    s[0] += abs(z) <= 1.96
                    s[1] = max(s[1], abs(z))
                    line.append(f"{p['basis']} {p['value']:.6g} ± {p['std_error']:.3g} ({z:+.2f})")
                print(f"seed {seed}: " + "; ".join(line), flush=True)
        start = "in motion" if a.motion else "at rest"
        cover = sum(s[0] for s in stats.values()) / max(1, answered * len(stats))
        parts = ", ".join(f"{b} {s[0]}/{answered} (worst {s[1]:.1f})" for b, s in stats.items())
        print(f"{a.case}, noise {level:g}, {start}: {answered} of {a.count} answered; "
              f"coverage {100 * cover:.0f} %; {parts}", flush=True)


if __name__ == "__main__":
    main()

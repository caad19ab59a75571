"""Arrays in Python -> a jointid recording, by way of `jointid import`.

Your acquisition code holds the excitation and the responses as arrays (NumPy or lists);
write them as CSV with one column per setup channel, named as in the setup, and a time
column `t` in seconds, then let `jointid import` check and convert them (it attaches the
setup, checks the sampling is even and every value finite, and names the line and column
of anything wrong).

    python3 examples/python/arrays_to_recording.py recordings/two-beam-spring.toml test.mcap

The arrays here are a stand-in (a random force and zero responses): replace `arrays()`
with your own data. Standard library only; NumPy arrays work as they are (any sequence of
numbers does).
"""

import csv
import random
import subprocess
import sys
import tomllib


def arrays(setup, n=2000):
    """t (s), then {channel name: samples}. Replace with your measured arrays."""
    dt = setup["integrator"]["dt_s"]
    t = [i * dt for i in range(n)]
    rng = random.Random(1)
    data = {e["name"]: [rng.gauss(0.0, 1000.0) for _ in t] for e in setup["excitation"]}
    data.update({s["name"]: [0.0] * n for s in setup["sensors"]})
    return t, data


def write_csv(path, t, data):
    names = list(data)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t"] + names)
        for i, ti in enumerate(t):
            # repr() round-trips a float exactly.
            w.writerow([repr(float(ti))] + [repr(float(data[n][i])) for n in names])


def main():
    if len(sys.argv) != 3:
        sys.exit("usage: arrays_to_recording.py SETUP.toml OUT.mcap")
    setup_path, out = sys.argv[1], sys.argv[2]
    with open(setup_path, "rb") as f:
        setup = tomllib.load(f)
    t, data = arrays(setup)
    csv_path = out + ".csv"
    write_csv(csv_path, t, data)
    jointid = "jointid"  # or target/release/jointid
    subprocess.run([jointid, "import", csv_path, "--setup", setup_path, "--out", out], check=True)


if __name__ == "__main__":
    main()

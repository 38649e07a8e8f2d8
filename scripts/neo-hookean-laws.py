#!/usr/bin/env python3
"""Runs every built-in scene (scenes/*.toml) under both neo-Hookean laws and prints a
Markdown table of how far the trajectories move apart: per scene, the largest centre-of-mass
difference over the steps relative to the scene's characteristic length L, the final one,
each law's smallest min_j, steps that ended inverted and Newton iterations.

    scripts/neo-hookean-laws.py [--bin target/release/stickslip] [--steps N] [--size S]

The classical law (`model = "neo-hookean"`) is each scene as shipped; the stable law is the
same file with `model = "stable-neo-hookean"`. Mass-spring scenes have nothing to change.
"""
import argparse
import csv
import json
import math
import pathlib
import subprocess
import tempfile
import time


def run(binary, scene, out, steps, size):
    cmd = [binary, "run", str(scene), "--out", str(out), "--quiet", "--overwrite"]
    if steps:
        cmd += ["--steps", str(steps)]
    if size:
        cmd += ["--size", str(size)]
    t = time.time()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.time() - t
    summary = json.loads((out / "summary.json").read_text())
    with open(out / "steps.csv") as f:
        rows = list(csv.DictReader(f))
    return p.returncode, p.stderr.strip(), summary, rows, wall


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="target/release/stickslip")
    ap.add_argument("--steps", type=int, default=0)
    ap.add_argument("--size", type=float, default=0)
    a = ap.parse_args()
    root = pathlib.Path(__file__).resolve().parent.parent
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="nh-laws-"))
    print("| scene | steps | max ‖Δcom‖/L | final ‖Δcom‖/L | min_j classical | min_j stable | "
          "inverted steps (stable) | Newton its classical / stable |")
    print("|---|---|---|---|---|---|---|---|")
    for f in sorted((root / "scenes").glob("*.toml")):
        text = f.read_text()
        name = f.stem
        if 'model = "neo-hookean"' not in text:
            print(f"| {name} | | (no neo-Hookean body) | | | | | |")
            continue
        stable = tmp / f"{name}.toml"
        stable.write_text(text.replace('model = "neo-hookean"', 'model = "stable-neo-hookean"'))
        res = {}
        for law, path in [("classical", f), ("stable", stable)]:
            res[law] = run(a.bin, path, tmp / f"{name}-{law}", a.steps, a.size)
        (rc_c, err_c, s_c, rows_c, _), (rc_s, err_s, s_s, rows_s, _) = res["classical"], res["stable"]
        L = s_c["characteristic_length"]
        axes = [k for k in rows_c[0] if k.startswith("com_")]
        worst = 0.0
        last = 0.0
        for rc, rs in zip(rows_c, rows_s):
            d = math.sqrt(sum((float(rc[k]) - float(rs[k])) ** 2 for k in axes)) / L
            worst = max(worst, d)
            last = d
        mj = lambda rows: min(float(r["min_j"]) for r in rows)
        n = min(len(rows_c), len(rows_s)) - 1
        note = ""
        if rc_c or rc_s:
            note = f" (classical rc {rc_c}: {err_c}; stable rc {rc_s}: {err_s})"
        inv = s_s.get("inverted_steps", {}).get("stable-neo-hookean", 0)
        print(f"| {name} | {n} | {worst:.2e} | {last:.2e} | {mj(rows_c):.3f} | {mj(rows_s):.3f} | "
              f"{inv} | {s_c['newton_iterations']} / {s_s['newton_iterations']}{note} |")


if __name__ == "__main__":
    main()

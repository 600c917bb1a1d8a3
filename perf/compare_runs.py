"""Two runs of the folder flow on the same Mitsuba captures, by light count and material class (session 37).

Reads JSON lines with a capture name (``cap`` or ``capture``) and a MAEN (``default`` or ``maen``; the rows of
perf/model_threshold_eval.py, perf/dev_held_dark_eval.py and perf/many_images_eval.py) and prints, for each light
count and class (dielectric, metal: the rough conductors, diffuse, non-diffuse: the first two), the number of
captures in both runs, the two means, how many captures got better or worse by more than 0.05 deg, the largest loss,
and the captures that moved by more than ``--show`` deg.  Several files may make up one run (comma-separated)::

    python perf/compare_runs.py BEFORE[,BEFORE2] AFTER[,AFTER2] [--show 0.3] [--md]
"""
from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict


def load(paths: str) -> dict[str, float]:
    """``{capture: MAEN}`` from comma-separated JSON-lines files (a later file's row wins)."""
    out = {}
    for p in paths.split(","):
        with open(p) as f:
            for line in f:
                if line.strip():
                    r = json.loads(line)
                    out[r.get("cap") or r["capture"]] = float(r["default"] if "default" in r else r["maen"])
    return out


def classes(cap: str) -> tuple[str, ...]:
    """The material classes a capture counts in."""
    if "-diffuse" in cap:
        return ("diffuse",)
    return ("metal" if "conductor" in cap else "dielectric", "non-diffuse")


def count(cap: str) -> int:
    m = re.search(r"-(?:directional|point)(\d+)-", cap)
    if m is None:
        raise ValueError(f"capture {cap!r}: no light count in its name")
    return int(m.group(1))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--show", type=float, default=0.3, help="list captures that moved by more than this (deg)")
    ap.add_argument("--md", action="store_true", help="a Markdown table")
    a = ap.parse_args(argv)
    b, n = load(a.before), load(a.after)
    both = sorted(set(b) & set(n))
    groups = defaultdict(list)
    for c in both:
        for k in classes(c):
            groups[(count(c), k)].append((b[c], n[c]))
        if abs(n[c] - b[c]) > a.show:
            print(f"{c[:64]:64s} {b[c]:7.2f} -> {n[c]:7.2f}")
    order = {"dielectric": 0, "metal": 1, "non-diffuse": 2, "diffuse": 3}
    if a.md:
        print("| lights | class | n | before | after | better | worse (> 0.05) | largest loss |\n|---|---|---|---|---|---|---|---|")
    for key in sorted(groups, key=lambda k: (k[0], order[k[1]])):
        v = groups[key]
        mb, ma = sum(x for x, _ in v) / len(v), sum(y for _, y in v) / len(v)
        better = sum(y < x - 0.05 for x, y in v)
        worse = sum(y > x + 0.05 for x, y in v)
        loss = max(y - x for x, y in v)
        if a.md:
            print(f"| {key[0]} | {key[1]} | {len(v)} | {mb:.2f} | {ma:.2f} | {better} | {worse} | {loss:.2f} |")
        else:
            print(f"{key[0]:3d} {key[1]:12s} {len(v):3d} {mb:7.2f} -> {ma:7.2f}  better {better:2d} worse {worse:2d} "
                  f"largest loss {loss:.2f}")
    print(f"{len(both)} captures in both ({len(b)} before, {len(n)} after)")


if __name__ == "__main__":
    main()

"""One table from several perf/dev_eval.py runs (each run measures some methods on the same development captures).

    python perf/dev_eval_table.py perf/results/dev_eval_cpu_compare.json perf/results/dev_eval_cpu_refine.json \
        [--methods ls,pipeline,pipeline_refine] [--out perf/results/dev_eval_cpu_refine_table.md]

Rows of a method measured in more than one file: the last file's.  Prints (and writes with ``--out``) the mean MAEN by
material x light count, the non-diffuse means against issue 25's targets, per capture MAEN side by side, and for
each method after the first how many captures it is better / worse than the second method listed (the baseline).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dev_eval import TARGETS, _fmt, _md_table  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--methods", default=None, help="comma-separated, in column order (default: all found)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    rows = {}
    for f in a.files:
        for r in json.loads(Path(f).read_text())["rows"]:
            rows[(r["capture"], r["method"])] = r
    found = []
    for _, m in rows:
        if m not in found:
            found.append(m)
    methods = [m.strip() for m in a.methods.split(",")] if a.methods else found
    missing = sorted(set(methods) - set(found))
    if missing:
        ap.error(f"--methods: not in the files: {missing}; found {found}")
    caps = sorted({(r["scene"], r["material"], r["kind"], r["n_lights"], c) for (c, m), r in rows.items() if m in methods})
    groups = {}
    for scene, mat, kind, n, cap in caps:
        for key in ((mat, n), ("non-diffuse" if mat != "diffuse" else "diffuse-only", n), ("all", n)):
            groups.setdefault(key, []).append(cap)
    body = []
    for (mat, n), cs in sorted(groups.items(), key=lambda kv: (kv[0][0] in ("non-diffuse", "diffuse-only", "all"), kv[0])):
        if mat == "diffuse-only":
            continue
        vals = []
        for m in methods:
            v = [rows[(c, m)]["maen"] for c in cs if (c, m) in rows]
            vals.append(_fmt(float(np.mean(v))) if len(v) == len(cs) else "")
        target = f"<= {TARGETS[n]}" if mat == "non-diffuse" and n in TARGETS else ""
        body.append([mat, n, len(cs), *vals, target])
    means = _md_table(["material", "lights", "captures", *methods, "issue target"], body)
    per = []
    for scene, mat, kind, n, cap in caps:
        per.append([scene, f"{kind[:3]}{n}", *[_fmt(rows[(cap, m)]["maen"]) if (cap, m) in rows else "" for m in methods]])
    per_table = _md_table(["scene", "lights", *methods], per)
    counts = []
    if len(methods) >= 3:
        base = methods[1]
        for m in methods[2:]:
            better = sum(1 for *_, c in caps if (c, m) in rows and (c, base) in rows and rows[(c, m)]["maen"] < rows[(c, base)]["maen"])
            worse = sum(1 for *_, c in caps if (c, m) in rows and (c, base) in rows and rows[(c, m)]["maen"] >= rows[(c, base)]["maen"])
            counts.append(f"- {m} against {base}: better on {better}, worse or equal on {worse} captures")
    text = "\n\n".join([f"# Development set: {', '.join(methods)}", "Files: " + ", ".join(a.files),
                        "## Mean MAEN (deg) by material x light count", means, "\n".join(counts),
                        "## Per capture MAEN (deg)", per_table]) + "\n"
    print(text)
    if a.out:
        Path(a.out).write_text(text)


if __name__ == "__main__":
    main()

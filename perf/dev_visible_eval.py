"""Default pipeline (and least squares) on cached Mitsuba development captures, one JSON line per run; and a
per-capture table comparing such files (session 16: normals facing away from the camera, issue 25).

The captures are perf/dev_eval.py's (seeds 3000-3009, rendered with ``perf/dev_eval.py --render-only``, cached
under ``$GPPS_CACHE_DIR/mitsuba_captures``).  MAEN inside the mask against the pixel-centre ground truth, as
perf/dev_eval.py; ``backfacing`` counts mask pixels whose returned normal has n_z < 0 (under the perspective
camera a few rim pixels may have n_z < 0 and still face the camera).  To compare two trees, run the first mode
from each tree (``PYTHONPATH=<tree>``) into its own file::

    python perf/dev_visible_eval.py run OUT.jsonl "*directional12*seed300*,*point12*seed300*" [pipeline,ls] [cpu]
    python perf/dev_visible_eval.py table A.jsonl B.jsonl [...]

Methods: ``pipeline`` (the default ``FolderConfig()``; from session 21 it compares the rough conductor from 6 images
on, from session 33 plastic too), ``ls`` (least squares), ``norefine`` / ``refine`` (the
default with ``refine=False`` / ``True``: session 18's automatic refinement with 3 images, issue 25), ``subtract``
(the default with ``interreflections="subtract"``: session 20's interreflection compensation), ``compare`` (the
model chosen by residual between Blinn-Phong and plastic: ``models=("plastic",)``), ``compare_subtract`` (both), ``conductor``
(Blinn-Phong or the rough conductor by residual: ``models=("conductor",)``, session 21), ``compare3`` (all three)
and ``nocompare`` (no comparison: ``models=()``, the default before session 21), ``ks0`` (no specular lobe:
``ks=0`` given, session 29).  With ``GPPS_DEV_LOWEST_ENERGY=1`` in the environment ``run`` compares models as
before session 33 (the lowest sampled energy wins, no evidence test: ``gpps.names.MODEL_SWITCH_Z`` set to -inf);
each row records the compared models' energies and the test (``model_energies``, ``model_evidence``).  The table
reads
the ``pipeline`` rows of each file (and ``ls``); the last argument of ``run`` is the device (default ``cpu``).
"""

from __future__ import annotations

import glob
import json
import os
import sys
import time
import warnings

import numpy as np


CONFIGS = {"pipeline": {}, "ls": {"solver": "none", "integrate": False}, "norefine": {"refine": False},
           "refine": {"refine": True}, "subtract": {"interreflections": "subtract"}, "compare": {"models": ("plastic",)},
           "compare_subtract": {"models": ("plastic",), "interreflections": "subtract"},
           "conductor": {"models": ("conductor",)}, "compare3": {"models": ("plastic", "conductor")},
           "conductor_refine": {"models": ("conductor",), "refine": True}, "nocompare": {"models": ()},
           "ks0": {"ks": 0.0}}


def run(out: str, patterns: str, methods: str = "pipeline", device: str = "cpu") -> None:
    import gpps
    if os.environ.get("GPPS_DEV_LOWEST_ENERGY"):  # (a probe: the comparison before session 33, lowest energy wins)
        gpps.names.MODEL_SWITCH_Z = -np.inf
    from gpps.host.metrics import normal_errors
    from gpps.io import read_capture

    warnings.simplefilter("ignore")
    root = os.path.join(os.environ.get("GPPS_CACHE_DIR", ".cache"), "mitsuba_captures")
    caps = sorted(c for p in patterns.split(",") for c in glob.glob(os.path.join(root, p)))
    if not caps:
        raise SystemExit(f"no capture under {root} matches {patterns!r} (render them with perf/dev_eval.py)")
    with open(out, "a") as f:
        for c in caps:
            ds = read_capture(c).dataset
            for m in methods.split(","):
                cfg = gpps.FolderConfig(**CONFIGS[m])
                t = time.perf_counter()
                r = gpps.reconstruct_folder(c, cfg, device=device)
                dt = time.perf_counter() - t
                e = normal_errors(r.normals, ds.normal_gt, ds.mask)
                row = dict(capture=os.path.basename(c), method=m, maen=e["mean"], median=e["median"], seconds=dt,
                           backfacing=int(((r.normals[..., 2] < 0) & ds.mask).sum()), device=device,
                           refine=r.report.get("refine"), material_ambiguity=r.report.get("material_ambiguity"),
                           brdf=(r.report.get("material") or {}).get("brdf"),
                           interreflections=r.report.get("interreflections"),
                           model_energies=r.report.get("model_energies"),
                           model_evidence=r.report.get("model_evidence"))
                f.write(json.dumps(row) + "\n")
                f.flush()
                print(row, flush=True)


def table(files: list[str]) -> None:
    def load(p, m):
        rows = [json.loads(line) for line in open(p)]
        return {r["capture"]: r for r in rows if r["method"] == m}

    runs = [load(f, "pipeline") for f in files]
    ls = {}
    for f in files:
        ls.update(load(f, "ls"))
    names = [os.path.basename(f).rsplit(".", 1)[0] for f in files]
    print("| capture | ls | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    groups: dict = {}
    for c in sorted(set().union(*runs)):
        row = [ls.get(c, {}).get("maen", np.nan)] + [r.get(c, {}).get("maen", np.nan) for r in runs]
        print(f"| {c.split('-s128')[0]} | " + " | ".join(f"{x:.2f}" for x in row) + " |")
        material = c.split("-")[1]
        lights = c.split("-s128")[0].rsplit("-", 1)[-1]
        kind = "diffuse" if material.startswith("diffuse") else "non-diffuse"
        groups.setdefault((kind, lights), []).append(row)
    print()
    print("| materials | lights | captures | ls | " + " | ".join(names) + " |")
    print("|---|---|---|---|" + "---|" * len(names))
    for (kind, lights), v in sorted(groups.items()):
        v = np.array(v, float)
        means = [np.mean(col) if np.all(np.isfinite(col)) else np.nan for col in v.T]
        print(f"| {kind} | {lights} | {len(v)} | " + " | ".join(f"{x:.2f}" for x in means) + " |")


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "run":
        run(*sys.argv[2:6])
    elif len(sys.argv) >= 3 and sys.argv[1] == "table":
        table(sys.argv[2:])
    else:
        raise SystemExit(__doc__)

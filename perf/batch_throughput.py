"""Throughput of ``gpps.reconstruct_many`` (``gpps batch``): captures per second with 1 and 2 workers (or any list).

Renders ``--n`` captures (``--size``^2, 6 directional lights, Blinn-Phong, the three scenes in turn, other seeds
and slants) and runs the batch on a fresh LocalCluster for each worker count, into a fresh output folder, with
the default options of ``gpps reconstruct`` (RON, material estimated) unless ``--options`` says otherwise.  The
wall time counts the cluster's first captures, which pay each worker process's one-time warm-up (imports, Warp
module loads from the kernel cache, Taichi JIT): the per-capture times are split into each worker's first
capture and the rest.  A second run over the same output (resume: every capture skipped) is timed too.  With
``--sequential`` the captures also run one ``gpps reconstruct`` process after another (the baseline the issue
names).  Usage::

    python perf/batch_throughput.py [--n 20] [--size 128] [--workers 1,2] [--device cpu] [--sequential]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from perf._common import write_results  # noqa: E402


def render_captures(root: Path, n: int, size: int) -> list[str]:
    import gpps
    from gpps.io import write_dataset

    dirs = []
    for k in range(n):
        scene = gpps.SCENE_NAMES[k % 3]
        sc = gpps.make_scene(scene, size, "orthographic", albedo="texture", seed=k)
        lights = gpps.default_lights("directional", 6, slant_deg=30 + (k % 5) * 3)
        ds = gpps.render_dataset(sc, gpps.Material.default_for("blinn-phong"), lights, bits=16, seed=k, device=None)  # (CUDA where present: its kit has no CPU backend)
        dirs.append(str(write_dataset(root / f"cap{k:03d}_{scene}", ds)))
    return dirs


def run_batch(dirs, out: Path, workers: int, device: str, options: dict) -> dict:
    import distributed

    from gpps import batch

    load = os.getloadavg()
    t0 = time.perf_counter()
    cluster = batch.make_cluster(workers, device=device, dashboard_address=None)
    client = distributed.Client(cluster)
    t_start = time.perf_counter() - t0
    try:
        t = time.perf_counter()
        res = batch.reconstruct_many(dirs, out, client, device=device, **options)
        wall = time.perf_counter() - t
        t = time.perf_counter()
        again = batch.reconstruct_many(dirs, out, client, device=device, **options)
        wall_resume = time.perf_counter() - t
    finally:
        client.close()
        cluster.close()
    assert res.ok and again.count("skipped") == len(dirs), (res.rows, again.rows)
    first, rest = [], []
    by_worker: dict[str, list[float]] = {}
    for r in res.rows:
        by_worker.setdefault(r["worker"], []).append(r["seconds"])
    for w, ts in by_worker.items():  # the slowest capture of each worker: its first (the one-time warm-up)
        ts = sorted(ts)
        first.append(ts[-1])
        rest += ts[:-1]
    return {"workers": workers, "cluster_start_s": t_start, "wall_s": wall, "captures_per_s": len(dirs) / wall,
            "per_capture_s_median": statistics.median(r["seconds"] for r in res.rows),
            "first_capture_per_worker_s": first, "other_captures_median_s": statistics.median(rest) if rest else None,
            "captures_per_worker": {w: len(ts) for w, ts in by_worker.items()},
            "maen_deg_median": statistics.median(r["maen_deg"] for r in res.rows),
            "resume_wall_s": wall_resume, "load_average_before": load, "load_average_after": os.getloadavg()}


def run_sequential(dirs, out: Path, device: str) -> dict:
    # this checkout first, then whatever the caller's PYTHONPATH holds (the GPU machine's kit lives there)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    t = time.perf_counter()
    for d in dirs:
        subprocess.run([sys.executable, "-m", "gpps", "--device", device, "--quiet", "reconstruct", d,
                        "--out", str(out / Path(d).name)], check=True, env=env)
    wall = time.perf_counter() - t
    return {"wall_s": wall, "captures_per_s": len(dirs) / wall}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sequential", action="store_true", help="also one gpps reconstruct process per capture, in turn")
    ap.add_argument("--options", default="{}", help="FolderConfig fields as JSON, e.g. '{\"known_material\": true}'")
    ap.add_argument("--name", default="batch_throughput")
    a = ap.parse_args(argv)
    options = json.loads(a.options)
    with tempfile.TemporaryDirectory(prefix="gpps-batch-perf-") as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        dirs = render_captures(tmp / "captures", a.n, a.size)
        print(f"rendered {a.n} captures of {a.size}^2 in {time.perf_counter() - t:.1f} s", flush=True)
        runs = []
        for w in (int(x) for x in a.workers.split(",")):
            r = run_batch(dirs, tmp / f"out{w}", w, a.device, options)
            print(json.dumps(r), flush=True)
            runs.append(r)
        seq = run_sequential(dirs, tmp / "seq", a.device) if a.sequential else None
    payload = {"captures": a.n, "size": a.size, "images": 6, "options": options, "cpu_count": os.cpu_count(),
               "runs": runs, "sequential_gpps_reconstruct": seq}
    if len(runs) >= 2:
        payload["throughput_ratio"] = runs[-1]["captures_per_s"] / runs[0]["captures_per_s"]
        payload["throughput_ratio_of"] = f"{runs[-1]['workers']} against {runs[0]['workers']} workers"
    path = write_results(a.name, a.device, payload)
    print(json.dumps({k: payload[k] for k in payload if k != "runs"}, indent=1), f"\nwrote {path}")


if __name__ == "__main__":
    main()

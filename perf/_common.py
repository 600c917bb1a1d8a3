"""Shared helpers of the perf scripts: device-synchronised median timing and JSON output."""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
RESULTS = ROOT / "perf" / "results"


def timeit(fn, sync, *, warmup: int = 3, repeat: int = 20, min_time: float = 0.0) -> dict:
    """Median / IQR wall time of ``fn()`` in seconds, synchronising the device around each call."""
    for _ in range(warmup):
        fn()
    sync()
    ts = []
    t_start = time.perf_counter()
    while len(ts) < repeat or time.perf_counter() - t_start < min_time:
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    q = statistics.quantiles(ts, n=4) if len(ts) >= 4 else [ts[0], statistics.median(ts), ts[-1]]
    return {"median_s": statistics.median(ts), "iqr_s": q[2] - q[0], "runs": len(ts)}


def device_label(device: str) -> str:
    if device.startswith("cuda"):
        from gpps._runtime import warp

        return warp().get_device(device).name.replace(" ", "_")
    return f"cpu-{platform.machine()}-{os.cpu_count()}cores"


def write_results(name: str, device: str, payload: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}_{device_label(device)}.json"
    payload = {"device": device, "device_name": device_label(device), "host": platform.node(), **payload}
    path.write_text(json.dumps(payload, indent=2) + "\n")
    return path

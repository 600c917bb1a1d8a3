"""The first and later calls of a ``gpps.Reconstructor`` on issue 20's 256^2 x 3 capture with the integrator's
multigrid PCG launched ``fused`` (the default) or ``persistent`` (one Taichi task a solve, specialised to the frame
size): what the persistent launch costs a first call (its compile, per frame size and installation) and saves
later.  Run each form in a fresh process with an empty Taichi and Warp cache, e.g.
``GPPS_CACHE_DIR=$(mktemp -d) python perf/pcg_first_call.py persistent``.  One JSON line on stdout."""
import json
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

warnings.simplefilter("ignore")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import gpps  # noqa: E402
from _common import reconstruct_inputs  # noqa: E402
from gpps.flows.ron import RONConfig  # noqa: E402
from gpps.pipeline.integration import IntegratorConfig  # noqa: E402

launch = sys.argv[1] if len(sys.argv) > 1 else "fused"
device = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
c = reconstruct_inputs(256, 3, device)
cfg = RONConfig()
cfg = replace(cfg, integrator=replace(cfg.integrator if cfg.integrator is not None else IntegratorConfig(),
                                      launch=launch))
calls = []
with gpps.Reconstructor(c["mask"], c["lights"], camera=c["camera"], material="cook-torrance", config=cfg,
                        device=device) as rc:
    for _ in range(6):
        t = time.perf_counter()
        rec = rc(c["images"])
        calls.append(round((time.perf_counter() - t) * 1e3, 1))
maen = float(gpps.normal_errors(rec.normals, c["normals"], c["mask"])["mean"])
print(json.dumps({"launch": launch, "device": device, "calls_ms": calls, "maen_deg": maen}))

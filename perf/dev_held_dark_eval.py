"""The default folder flow on cached Mitsuba captures with the neighbour pass's attached / cast shadow choice on or
off (``SolverConfig.held_dark_refit``, session 35), one JSON line per capture.

    python perf/dev_held_dark_eval.py OUT.jsonl "GLOB[,GLOB...]" on|off [THRESHOLD]

``THRESHOLD`` > 0 also drops every observation below that fraction of the pixel's brightest with few images
(``shadow_threshold``, the many-images setting; session 35's first probe).  Captures: perf/dev_eval.py's and
perf/heldout_eval.py's (``--render-only``), under ``$GPPS_CACHE_DIR/mitsuba_captures``.
"""
import sys, glob, os, warnings, json, time, numpy as np
warnings.simplefilter("ignore")
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import gpps, gpps.flows.folder as ff
from gpps.io import read_capture
from gpps.host.metrics import normal_errors
orig = ff.automatic_solver_options
on = {"on": True, "off": False}[sys.argv[3]]
thr = float(sys.argv[4]) if len(sys.argv) > 4 else 0.0
def patched(n, robust=None):
    o = orig(n, robust)
    if n <= ff.MANY_IMAGES and thr > 0:
        o.update(shadow_threshold=thr)
    o.update(held_dark_refit=on)
    return o
ff.automatic_solver_options = patched
root = os.path.join(os.environ.get('GPPS_CACHE_DIR', '.cache'), 'mitsuba_captures')
caps = sorted(c for p in sys.argv[2].split(',') for c in glob.glob(os.path.join(root, p)))
with open(sys.argv[1], 'a') as f:
    for c in caps:
        ds = read_capture(c).dataset
        t = time.perf_counter()
        r = gpps.reconstruct_folder(c, gpps.FolderConfig(), device='cpu')
        e = normal_errors(r.normals, ds.normal_gt, ds.mask)
        row = dict(capture=os.path.basename(c), held_dark_refit=on, threshold=thr, maen=e['mean'], seconds=time.perf_counter()-t,
                   brdf=r.report['material']['brdf'], refine=r.report.get('refine', {}).get('on'))
        f.write(json.dumps(row) + '\n'); f.flush(); print(row['capture'][:50], on, thr, round(e['mean'], 2), flush=True)

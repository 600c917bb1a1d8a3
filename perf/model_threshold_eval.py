"""The folder flow with and without RON's model comparison on cached Mitsuba captures (session 36: the conductor's
image threshold, gpps.names.CONDUCTOR_MIN_IMAGES).  One JSON line a capture: MAEN (deg), the chosen model, seconds.

Variants (env VARIANTS, comma-separated): ``old`` (``FolderConfig(models=())``: nothing compared), ``default``
(``FolderConfig()``: the automatic policy), ``models`` (conductor and plastic compared whatever the image count),
``cond`` (the conductor alone).  Captures: ``$GPPS_CACHE_DIR/mitsuba_captures`` (perf/dev_eval.py and
perf/heldout_eval.py ``--render-only --lights N``).

Usage:  VARIANTS=old,default python perf/model_threshold_eval.py SEEDS COUNTS PART  (e.g. 3000,3001 4,5 0/2)
(env SKIP: comma-separated JSON-lines files whose captures are left out)
"""
import json
import os
import sys
import time
import warnings
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
warnings.simplefilter('ignore')
import gpps
from gpps.io import read_capture
from _common import cached_captures
from gpps.flows.folder import AUTOMATIC_MODELS
seeds, counts, part = sys.argv[1], sys.argv[2].split(','), sys.argv[3]
i_part, n_part = map(int, part.split('/'))
files = cached_captures(seeds, counts)
done = set()
for path in filter(None, os.environ.get('SKIP', '').split(',')):  # (captures already in these JSON-lines files)
    done |= {json.loads(line)['cap'] for line in open(path) if line.strip()}
files = [f for f in files if f.split('/')[-1] not in done]
for j, f in enumerate(files):
    if j % n_part != i_part:
        continue
    ds = read_capture(f).dataset
    row = {'cap': f.split('/')[-1]}
    for tag, cfg in [(k, v) for k, v in (('old', gpps.FolderConfig(models=())), ('default', gpps.FolderConfig()), ('models', gpps.FolderConfig(models=AUTOMATIC_MODELS)), ('cond', gpps.FolderConfig(models=('conductor',)))) if k in os.environ.get('VARIANTS', 'default,models,cond').split(',')]:
        t = time.time()
        res = gpps.reconstruct_folder(f, cfg, device='cpu')
        row[tag] = float(gpps.normal_errors(res.normals, ds.normal_gt, ds.mask)['mean'])
        row[tag + '_brdf'] = res.report['material']['brdf']
        row[tag + '_s'] = round(time.time() - t, 1)
        ir = res.report.get('interreflections') or {}
        if ir.get('tau') is not None or ir.get('skipped'):
            row[tag + '_ir'] = {'tau': ir.get('tau'), 'share': ir.get('indirect_share'), 'skipped': ir.get('skipped'),
                                'why': ir.get('why')}
    print(json.dumps(row), flush=True)

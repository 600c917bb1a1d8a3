"""How the interreflection compensation's result depends on its albedo scale ``tau`` (issue 25): the folder flow with
``interreflections="subtract"`` and ``albedo_scale`` = each value given, on cached Mitsuba captures whose light
intensities are radiometric (the true ``tau`` is 1).  One JSON line a capture: per value the MAEN (deg), the
``tau`` used per round (lowered to the white bound where it exceeds it), the bound, the indirect share, seconds.

Usage:  python perf/interreflection_scale_eval.py SEEDS COUNTS SCALES PART   (e.g. 3000,3001 12 0.5,1,2 0/2)
"""
import json
import os
import sys
import time
import warnings
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
warnings.simplefilter('ignore')
import gpps  # noqa: E402
from gpps.io import read_capture  # noqa: E402
from _common import cached_captures  # noqa: E402

seeds, counts, scales, part = sys.argv[1], sys.argv[2].split(','), sys.argv[3].split(','), sys.argv[4]
i_part, n_part = map(int, part.split('/'))
files = cached_captures(seeds, counts)
for j, f in enumerate(files):
    if j % n_part != i_part:
        continue
    ds = read_capture(f).dataset
    row = {'cap': f.split('/')[-1]}
    for s in scales:
        t = time.time()
        res = gpps.reconstruct_folder(f, gpps.FolderConfig(interreflections='subtract', albedo_scale=float(s)),
                                      device='cpu')
        info = res.report.get('interreflections', {})
        row[s] = {'maen': float(gpps.normal_errors(res.normals, ds.normal_gt, ds.mask)['mean']),
                  'brdf': res.report['material']['brdf'], 'tau': info.get('tau'), 'bound': info.get('bound'),
                  'share': info.get('indirect_share'), 'skipped': info.get('skipped'),
                  's': round(time.time() - t, 1)}
    print(json.dumps(row), flush=True)

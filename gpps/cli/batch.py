"""``gpps batch FOLDER... --out DIR``: many capture folders on a Dask cluster, as ``gpps reconstruct`` would do each.

Each capture's outputs go to ``DIR/<folder name>/`` exactly as ``gpps reconstruct`` writes them, and
``DIR/summary.csv`` gets one row per capture (status, MAEN when ground truth exists, times, error).  By
default a local cluster (one worker process per GPU, else per two CPU cores); ``--scheduler`` connects
to a running one.  A second run skips the captures already done for the same inputs and options.  Exit
status 1 when a capture failed.  The work is :func:`gpps.reconstruct_many`'s (:mod:`gpps.batch`); needs
``pip install 'gpps[batch]'``.
"""

from __future__ import annotations

import sys

import gpps
from gpps.cli._output import as_options
from gpps.cli._progress import bar, quiet
from gpps.cli.reconstruct import _OPTIONS, add_reconstruct_options, folder_config


def register(subparsers) -> None:
    p = subparsers.add_parser("batch", help="reconstruct many capture folders on a Dask cluster (local or remote), with resume",
                              description=__doc__.splitlines()[0])
    p.add_argument("dirs", nargs="+", metavar="FOLDER", help="capture folders (as for gpps reconstruct); their names must differ")
    p.add_argument("--out", required=True, help="batch output folder: DIR/<folder name>/ per capture and DIR/summary.csv; "
                                                "must be new, empty, or an earlier batch output (then finished captures are skipped)")
    p.add_argument("--overwrite", action="store_true", help="replace a capture's earlier gpps output written for other inputs "
                                                            "or options (never files gpps did not write)")
    who = p.add_mutually_exclusive_group()
    who.add_argument("--workers", type=int, default=None, help="worker processes of the local cluster; "
                                                               "default: one per GPU (each pinned to it), else one per two CPU cores")
    who.add_argument("--scheduler", default=None, help="address of a running Dask scheduler (tcp://host:8786) instead of a local cluster")
    p.add_argument("--dashboard-address", default=":8787", help="local cluster's dashboard address (needs bokeh); 'none': no dashboard")
    add_reconstruct_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    config = folder_config(args)
    prog = bar("batch")

    def progress(done, total, message):
        if done == 0 and not quiet():  # names the cluster and its dashboard
            print(f"gpps batch: {message}", file=sys.stderr)
        prog(done, total, message)

    try:
        with as_options(*_OPTIONS, "workers", "scheduler"):
            res = gpps.reconstruct_many(
                args.dirs, args.out, workers=args.workers, scheduler=args.scheduler, config=config, lights=args.lights,
                mask=args.mask, ambient=args.ambient, device=args.device, overwrite=args.overwrite, progress=progress,
                dashboard_address=None if args.dashboard_address == "none" else args.dashboard_address)
    except ImportError as e:
        print(f"gpps batch: error: {e}", file=sys.stderr)
        return 2
    for r in res.rows:
        if r["status"] == "failed":
            print(f"gpps batch: {r['folder']}: failed: {r['error']}", file=sys.stderr)
    print(f"{len(res.rows)} captures: {res.count('done')} done, {res.count('skipped')} skipped, {res.failed} failed "
          f"in {res.seconds:.1f} s; summary: {res.summary}")
    return 0 if res.ok else 1

"""Batches of captures on a Dask cluster: :func:`reconstruct_many` (``gpps batch``) and :func:`reconstruct_tiled`.

:func:`reconstruct_many` runs :func:`gpps.reconstruct_folder` on every capture folder as one task of a
``dask.distributed`` cluster (a :class:`~distributed.LocalCluster` by default, or any cluster through a
``Client`` or a scheduler address) and writes each capture's outputs to ``OUT/<folder name>/`` exactly as
``gpps reconstruct`` writes them (:meth:`gpps.FolderResult.write` into :func:`gpps.io.atomic_dir`: complete or
absent), plus ``OUT/summary.csv``, one row per capture.

* **Workers.**  Processes, not threads (Warp and Taichi keep per-process state), one thread each.  The
  default cluster has one worker per GPU when CUDA is present, each pinned to its GPU
  (``CUDA_VISIBLE_DEVICES``, the worker's device is then ``cuda:0``), else one per two CPU cores
  (:func:`default_workers`).  A worker process lives for the whole batch: the Warp modules it loaded, the
  Taichi kernels it compiled, the integrator's field pool (:mod:`gpps.pipeline.integration`) and the stages'
  device buffers (:mod:`gpps.pipeline.buffers`: the pixel solvers', the material scorer's and DGMC's, given
  back when a reconstruction closes them) serve every later capture of the same size it gets; the compiled
  kernels are also cached on disk (``GPPS_CACHE_DIR``), which the default cluster's workers inherit.
* **Resume.**  Each capture's ``report.json`` records ``batch.input_hash``: SHA-256 over the capture's
  files (names and contents; the light folder and mask file when given), the reconstruction's options and
  the gpps version (:func:`input_hash`).  A capture whose output folder is complete (every file of its
  manifest present) and carries the same hash is skipped.
* **Failures.**  A capture that raises is reported (``status`` ``failed``, the error in ``summary.csv``) and
  the others go on.  A worker that dies (killed, out of memory) loses its task to the scheduler, which runs
  it again on another worker (``distributed.scheduler.allowed-failures`` times); its output folder was being
  written under a temporary name (:func:`gpps.io.atomic_dir`), so nothing half-written is left under the
  real name, and the batch removes such temporary folders of its captures at the end.
* **Users' files.**  ``OUT`` must be new, empty, or an earlier batch output (a ``.gpps-batch.json``
  marker); a capture's folder in it is replaced only when gpps wrote it and ``overwrite`` is given, never
  when it holds other files (:func:`gpps.io.check_output_dir`).

Library code does not print: the progress of the whole batch goes to ``progress(done, total, message)``.
Dask is an optional dependency (``pip install 'gpps[batch]'``), imported on first use.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import importlib.util
import io
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
import traceback
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

import gpps
from gpps import _fpenv
from gpps._check import GppsWarning, as_path
from gpps.flows import tiled
from gpps.flows.folder import FolderConfig, reconstruct_folder
from gpps.io import atomic_dir, atomic_write, check_output_dir, read_marker, save_json
from gpps.material import Material
from gpps.pipeline.solver import SolverConfig

__all__ = ["reconstruct_many", "reconstruct_tiled", "tiled_solver", "BatchResult", "input_hash", "default_workers", "make_cluster",
           "SUMMARY_FIELDS", "BATCH_MARKER"]

Progress = Callable[[float, float, str], None]

BATCH_MARKER = ".gpps-batch.json"
"""The marker :func:`reconstruct_many` writes into ``OUT``: the folder holds a batch's outputs."""

SUMMARY_FIELDS = ("folder", "name", "status", "maen_deg", "seconds", "reconstruct_s", "worker", "error")
"""The columns of ``summary.csv``: the capture folder as given, its output folder's name, ``done`` /
``skipped`` / ``failed``, the mean angular error (deg) when ``normal_gt.npy`` exists, the task's wall time and
the reconstruction's (report.json ``timings.total``; for a skipped capture the recorded one), the worker's
address, the error (``Type: message``) of a failed capture."""

_HASH_CHUNK = 1 << 20


def _dask():
    """``(dask, distributed)``, or an ImportError that says how to install them."""
    try:
        import dask  # optional dependency: the base install of gpps does not need it
        import distributed
    except ImportError as e:
        raise ImportError("gpps.batch needs dask.distributed: pip install 'gpps[batch]'") from e
    return dask, distributed


# ---------------------------------------------------------------------------------------------- the cluster


def _cuda_devices() -> list[str]:
    """The CUDA devices a worker could be pinned to, without touching CUDA in this process: the entries of
    ``CUDA_VISIBLE_DEVICES`` when set, else the GPUs ``nvidia-smi -L`` lists, else none."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [d.strip() for d in env.split(",") if d.strip() and d.strip() != "-1"]
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return []
    try:
        out = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=20).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(k) for k, line in enumerate(ln for ln in out.splitlines() if ln.startswith("GPU "))]


def default_workers(device: str | None = None) -> tuple[int, list[str]]:
    """The default cluster's size: ``(workers, the CUDA device of each worker)``.

    One worker per GPU when CUDA is present and ``device`` is not ``"cpu"`` (the list names the device each
    worker is pinned to), else one per two CPU cores (at least one) and an empty list.
    """
    gpus = [] if device == "cpu" else _cuda_devices()
    if gpus:
        return len(gpus), gpus
    return max(1, (os.cpu_count() or 2) // 2), []


THREAD_VARIABLES = ("TI_CPU_MAX_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""The thread counts a CPU worker of the default cluster is given (Taichi's CPU pool, BLAS): the cores shared
out, so that two workers on two cores do not run four spinning pools.  ``GPPS_CPU_THREADS`` (Warp's row split)
stays as in a ``gpps reconstruct`` process: it decides which threads run the pixel solves (each in its
caller's floating-point mode, :func:`gpps.pipeline.cpu_threads.run_all`)."""


def worker_env(gpus: list[str], index: int, threads: int | None = None) -> dict:
    """Environment of the default cluster's worker ``index``: pinned to ``gpus[index % len(gpus)]`` when there
    are GPUs; with ``threads``, each of :data:`THREAD_VARIABLES` not set in this process set to it; the kernel
    cache folder (``GPPS_CACHE_DIR``), ``GPPS_CPU_THREADS`` and the Taichi settings passed on."""
    env = {k: os.environ[k] for k in ("GPPS_CACHE_DIR", "WARP_CACHE_PATH", "ENABLE_TAICHI_HEADER_PRINT", "GPPS_CPU_THREADS",
                                       "TI_SKIP_VERSION_CHECK", *THREAD_VARIABLES) if k in os.environ}
    if threads is not None:
        for k in THREAD_VARIABLES:
            env.setdefault(k, str(int(threads)))
    if gpus:
        env["CUDA_VISIBLE_DEVICES"] = gpus[index % len(gpus)]
    return env


def make_cluster(workers: int | None = None, *, device: str | None = None, dashboard_address: str | None = ":8787",
                 memory_limit="auto"):
    """A :class:`distributed.LocalCluster` of worker processes (one task thread each) for :func:`reconstruct_many`.

    CPU workers share the cores out: each gets ``cores // workers`` threads for Taichi and BLAS
    (:data:`THREAD_VARIABLES`; a variable set in this process wins).

    Args:
        workers: worker processes; None: :func:`default_workers` (one per GPU, each pinned to it; else one
            per two CPU cores).
        device: ``"cpu"``: CPU workers even where CUDA is present; else CUDA workers where present.
        dashboard_address: the dashboard's address (``":8787"``; another free port if taken; None: no
            dashboard).  The dashboard needs ``bokeh``.
        memory_limit: each worker's memory limit (dask's forms: ``"auto"``, ``"4GiB"``, bytes).

    Returns:
        The cluster (``cluster.dashboard_link`` is the dashboard's URL); close it when done.
    """
    _, distributed = _dask()
    n_default, gpus = default_workers(device)
    n = n_default if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"workers: expected an integer >= 1, got {workers!r}")
    threads = None if gpus else max(1, (os.cpu_count() or 1) // n)

    class PinnedCluster(distributed.LocalCluster):
        """A LocalCluster whose worker ``k`` gets :func:`worker_env` ``(gpus, k)`` (its own GPU)."""

        def new_worker_spec(self):
            spec = {}
            for name, s in super().new_worker_spec().items():  # (the spec is shared between workers: copied)
                opts = dict(s.get("options", {}))
                opts["env"] = {**opts.get("env", {}), **worker_env(gpus, int(name) if str(name).isdigit() else 0, threads)}
                spec[name] = {**s, "options": opts}
            return spec

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Port 8787 is already in use" / "dashboard requires bokeh": not errors here
        cluster = PinnedCluster(n_workers=0, threads_per_worker=1, processes=True, dashboard_address=dashboard_address,
                                memory_limit=memory_limit)
    cluster.scale(n)  # through new_worker_spec: each worker its own environment
    cluster.wait_for_workers(n)
    return cluster


# ---------------------------------------------------------------------------------------------- resume


def _config(config: FolderConfig | None, options: dict) -> FolderConfig:
    if config is None:
        return FolderConfig(**options)
    if not isinstance(config, FolderConfig):
        raise TypeError(f"config: expected gpps.FolderConfig, got {type(config).__name__}")
    return replace(config, **options) if options else config


def _hash_file(h, path: Path) -> None:
    with open(path, "rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            h.update(chunk)


def _hash_tree(h, root: Path, label: str) -> None:
    """Names and contents of the files directly in ``root`` (a folder) or of ``root`` (a file)."""
    files = [root] if root.is_file() else sorted(p for p in root.iterdir() if p.is_file())
    for p in files:
        h.update(f"{label}/{p.name}:{p.stat().st_size}\n".encode())
        _hash_file(h, p)


def input_hash(folder, config: FolderConfig, *, lights=None, mask=None, ambient="auto") -> str:
    """SHA-256 (hex) of what a capture's result depends on: the files directly in ``folder`` (names and
    contents), the files of ``lights`` (a folder) and of ``mask`` / ``ambient`` when they name files, every
    field of ``config`` and the gpps version.  The device is not part of it."""
    h = hashlib.sha256()
    opts = {"config": asdict(config), "lights": lights is not None, "mask": None if mask is None else str(mask),
            "ambient": None if ambient is None else str(ambient), "gpps": gpps.__version__}
    h.update(json.dumps(opts, sort_keys=True, default=str).encode())
    folder = Path(folder)
    _hash_tree(h, folder, "capture")
    if lights is not None:
        _hash_tree(h, Path(lights), "lights")
    for label, f in (("mask", mask), ("ambient", ambient)):
        if f is not None and str(f) not in ("auto", "none"):
            p = Path(f) if Path(f).is_absolute() or Path(f).exists() else folder / f
            if p.is_file():
                _hash_tree(h, p, label)
    return h.hexdigest()


def _complete(dest: Path, digest: str) -> dict | None:
    """The report of an output folder that is complete (its manifest's files all present) and was written
    for ``digest``; else None."""
    manifest = read_marker(dest)
    if manifest is None or not all((dest / f).exists() for f in manifest["files"]):
        return None
    try:
        report = json.loads((dest / "report.json").read_text())
    except (OSError, ValueError):
        return None
    return report if isinstance(report, dict) and report.get("batch", {}).get("input_hash") == digest else None


# ---------------------------------------------------------------------------------------------- one capture


def default_fp_environment() -> None:
    """Reset this thread's floating-point environment to the default (:func:`gpps._fpenv.set_default`; a no-op
    elsewhere).  A capture on a worker that ran others before starts from the environment a fresh ``gpps
    reconstruct`` process has, so that its results are the same to the last bit, whatever a task left set
    (Taichi's initialisation turns flush-to-zero on in its thread: :func:`gpps._taichi.init` puts the
    caller's mode back, :mod:`gpps._fpenv`; this reset covers any other code that changes it)."""
    _fpenv.set_default()


def _worker_name() -> str:
    try:
        from distributed import (
            get_worker,  # only inside a task, on a worker (dask is installed there)
        )

        return get_worker().address
    except (ImportError, ValueError):
        return socket.gethostname()


def run_capture(folder: str, dest: str, config: FolderConfig, *, lights=None, mask=None, ambient="auto",
                device=None, overwrite: bool = False) -> dict:
    """One capture of a batch (a Dask task; also callable on its own): skip it when ``dest`` holds its
    complete output for the same inputs, else reconstruct and write ``dest`` as ``gpps reconstruct`` does.

    Never raises for the capture's own errors: they come back as ``status="failed"`` with the message
    (the batch goes on).  Returns a row of ``summary.csv`` (:data:`SUMMARY_FIELDS`).
    """
    t0 = time.perf_counter()
    row = {"folder": str(folder), "name": Path(dest).name, "status": "failed", "maen_deg": None, "seconds": None,
           "reconstruct_s": None, "worker": _worker_name(), "error": ""}
    try:
        digest = input_hash(folder, config, lights=lights, mask=mask, ambient=ambient)
        done = _complete(Path(dest), digest)
        if done is not None:
            row.update(status="skipped", maen_deg=done.get("maen_deg"), reconstruct_s=done.get("timings", {}).get("total"))
        else:
            mask_file = mask if mask not in (None, "auto", "none") else None
            inputs = [i for i in (folder, lights, mask_file) if i is not None]
            check_output_dir(dest, inputs=inputs, overwrite=overwrite, name="out")  # before any computing
            default_fp_environment()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", GppsWarning)
                res = reconstruct_folder(folder, config, lights=lights, mask=mask, ambient=ambient, device=device)
                res.report["batch"] = {"input_hash": digest}
                messages = [str(w.message) for w in caught if issubclass(w.category, GppsWarning)]
                with atomic_dir(dest, overwrite=overwrite, inputs=inputs, name="out") as tmp:
                    report = res.write(tmp, warnings=messages, started=t0)
            row.update(status="done", maen_deg=report.get("maen_deg"), reconstruct_s=report["timings"]["total"])
    except Exception as e:  # the capture's error, reported in summary.csv; the batch goes on
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc(limit=8)
    row["seconds"] = time.perf_counter() - t0
    return row


# ---------------------------------------------------------------------------------------------- the batch


@dataclass
class BatchResult:
    """What :func:`reconstruct_many` did.

    Attributes:
        rows: one dict per capture, in the order given (:data:`SUMMARY_FIELDS`; a failed one also has
            ``traceback``).
        summary: the path of ``summary.csv``.
        dashboard: the cluster's dashboard URL (None when unknown).
        seconds: the batch's wall time.
    """

    rows: list[dict] = field(default_factory=list)
    summary: Path | None = None
    dashboard: str | None = None
    seconds: float = 0.0

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.rows)

    @property
    def failed(self) -> int:
        return self.count("failed")

    @property
    def ok(self) -> bool:
        return self.failed == 0


def _check_out(out, folders: list[Path]) -> Path:
    """``OUT`` checked before anything runs: a new or empty folder or an earlier batch's (its marker)."""
    p = Path(out).expanduser()
    real = p.resolve()
    if real.exists() and not real.is_dir():
        raise gpps.io.OutputError(f"out: {p} is an existing file; expected a folder (new, empty, or an earlier gpps batch output)")
    for f in folders:
        r = f.resolve()
        if r == real or real in r.parents or r in real.parents:
            raise gpps.io.OutputError(f"out: {p} contains or is inside the capture folder {f}; choose another output folder")
    if real.is_dir() and any(real.iterdir()) and not (real / BATCH_MARKER).is_file():
        raise gpps.io.OutputError(f"out: {p} is a non-empty folder that gpps batch did not write; expected a new or "
                                  "empty folder or an earlier batch output (gpps never replaces other files)")
    return real


def _names(folders: list[Path]) -> list[str]:
    names = [f.resolve().name for f in folders]
    seen: dict[str, Path] = {}
    for f, n in zip(folders, names):
        if n in seen:
            raise ValueError(f"folders: two capture folders share the name {n!r} ({seen[n]} and {f}); their outputs "
                             "would collide in OUT/<folder name>")
        if n in ("summary.csv", BATCH_MARKER) or n.startswith("."):
            raise ValueError(f"folders: {f}: expected a folder name usable as OUT/<name>, got {n!r}")
        seen[n] = f
    return names


def _write_summary(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_FIELDS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]))
                    for k in SUMMARY_FIELDS})
    with atomic_write(path) as tmp:
        tmp.write_text(buf.getvalue())


def _remove_leftovers(out: Path, names: list[str]) -> None:
    """The temporary folders of this batch's captures that a killed worker left (``.<name>.*.tmp``/``.old``,
    :func:`gpps.io.atomic_dir`'s names); nothing else."""
    for n in names:
        for p in out.glob(f".{n}.*"):
            if p.is_dir() and p.name.endswith((".tmp", ".old")):
                shutil.rmtree(p, ignore_errors=True)


def reconstruct_many(folders, out, client=None, *, workers: int | None = None, scheduler: str | None = None,
                     config: FolderConfig | None = None, lights=None, mask=None, ambient: str | None = "auto",
                     device: str | None = None, overwrite: bool = False, progress: Progress | None = None,
                     dashboard_address: str | None = ":8787", **options) -> BatchResult:
    """Reconstruct many capture folders on a Dask cluster; outputs in ``out/<folder name>/``, ``out/summary.csv``.

    Args:
        folders: capture folders (each as :func:`gpps.reconstruct_folder` reads it); their names must differ.
        out: the batch's output folder: new, empty, or an earlier batch's (then complete captures with the same
            inputs and options are skipped).
        client: a ``distributed.Client`` to run on (its cluster is left running); None: ``scheduler``, else
            a :func:`make_cluster` LocalCluster for this call (closed at the end).
        workers: the LocalCluster's worker processes (None: :func:`default_workers`).
        scheduler: address of a running scheduler (``"tcp://host:8786"``) to connect to.
        config: :class:`gpps.FolderConfig` (None: the defaults); ``options`` (its field names) override it.
        lights, mask, ambient: :func:`gpps.reconstruct_folder`'s, for every capture.
        device: the workers' Warp/Taichi device (None / ``"auto"``: the worker's GPU if it has one; ``"cpu"``).
        overwrite: replace a capture's earlier gpps output written for other inputs or options (never a
            folder gpps did not write).
        progress: ``progress(done, total, message)`` as captures finish; the first call (0, total, message)
            names the dashboard.
        dashboard_address: the LocalCluster's dashboard address (None: none).
        **options: :class:`gpps.FolderConfig` fields (``method="ppn"``, ``rounds=3``, ...).

    Returns:
        :class:`BatchResult` (``result.ok`` is False when a capture failed).

    Raises:
        ImportError: dask.distributed missing (``pip install 'gpps[batch]'``).
        ValueError / TypeError: bad options, two folders with the same name, ``client`` and ``scheduler`` both.
        gpps.io.OutputError: ``out`` is a file, an input, or a non-empty folder gpps batch did not write.
    """
    t0 = time.perf_counter()
    cfg = _config(config, options)
    if isinstance(folders, (str, os.PathLike)):
        folders = [folders]
    try:
        folders = list(folders)
    except TypeError:
        raise TypeError(f"folders: expected a folder path or a sequence of them, got {type(folders).__name__}") from None
    folders = [as_path(f"folders[{k}]", f) for k, f in enumerate(folders)]
    if not folders:
        raise ValueError("folders: expected at least one capture folder, got none")
    names = _names(folders)
    if client is not None and scheduler is not None:
        raise ValueError("client, scheduler: expected one of them, got both")
    out = _check_out(out, folders)
    step = progress or (lambda *a: None)
    with _client(client, scheduler, workers, device, dashboard_address) as (client, device):
        return _run_batch(client, folders, names, out, cfg, lights=lights, mask=mask, ambient=ambient, device=device,
                          overwrite=overwrite, step=step, t0=t0)


@contextlib.contextmanager
def _client(client, scheduler, workers, device, dashboard_address):
    """``(client, the workers' device)``: the one given, one connected to ``scheduler``, or one of a new
    :func:`make_cluster` cluster; closed at the end unless given."""
    _, distributed = _dask()
    cluster = None
    if client is None:
        if scheduler is not None:
            client = distributed.Client(scheduler)
        else:
            cluster = make_cluster(workers, device=device, dashboard_address=dashboard_address)
            client = distributed.Client(cluster)
    own = cluster is not None or scheduler is not None
    if cluster is not None and device not in (None, "auto", "cpu") and default_workers(device)[1]:
        device = None  # each pinned worker sees its own GPU as cuda:0
    device = None if device == "auto" else device
    try:
        yield client, device
    finally:
        if own:
            client.close()
        if cluster is not None:
            cluster.close()


def _dashboard(client) -> str | None:
    """The dashboard's URL: a remote scheduler's always; a local one's only where bokeh (which serves it) is installed."""
    link = getattr(client, "dashboard_link", None)
    if getattr(client, "cluster", None) is not None and importlib.util.find_spec("bokeh") is None:
        return None
    return link


def _run_batch(client, folders, names, out, cfg, *, lights, mask, ambient, device, overwrite, step, t0) -> BatchResult:
    _, distributed = _dask()
    res = BatchResult(summary=out / "summary.csv", dashboard=_dashboard(client))
    out.mkdir(parents=True, exist_ok=True)
    if not (out / BATCH_MARKER).is_file():
        save_json(out / BATCH_MARKER, {"gpps": gpps.__version__, "written_by": "gpps batch"})
    total = len(folders)
    futures = {}
    for k, (f, n) in enumerate(zip(folders, names)):
        fut = client.submit(run_capture, str(f), str(out / n), cfg, lights=lights, mask=mask, ambient=ambient,
                            device=device, overwrite=overwrite, key=f"gpps-capture-{k}-{n}-{time.time_ns()}", pure=False)
        futures[fut] = k
    step(0, total, f"{total} captures on {len(client.scheduler_info().get('workers', {}))} workers"
                   + (f"; dashboard {res.dashboard}" if res.dashboard else ""))
    rows: list[dict | None] = [None] * total
    for fut in distributed.as_completed(list(futures)):
        k = futures[fut]
        try:
            rows[k] = fut.result()
        except Exception as e:  # the task itself was lost (a worker died more often than allowed)
            rows[k] = {"folder": str(folders[k]), "name": names[k], "status": "failed",
                       "error": f"{type(e).__name__}: {e}"}
        done = [r for r in rows if r is not None]
        _write_summary(res.summary, [r for r in rows if r is not None])
        failed = sum(r["status"] == "failed" for r in done)
        skipped = sum(r["status"] == "skipped" for r in done)
        step(len(done), total, f"{len(done)}/{total} captures, {failed} failed, {skipped} skipped; "
                               f"{names[k]}: {rows[k]['status']}")
    res.rows = rows
    _write_summary(res.summary, rows)
    _remove_leftovers(out, names)
    res.seconds = time.perf_counter() - t0
    return res



# ---------------------------------------------------------------------------------------------- large captures


class _NpyWindow:
    """A ``.npy`` file read a window at a time (dask.array's source; pickles as its path, so each task reads
    only its block from storage the workers share)."""

    def __init__(self, path):
        arr = np.load(path, mmap_mode="r")
        self.path, self.shape, self.dtype, self.ndim = str(path), arr.shape, arr.dtype, arr.ndim

    def __getitem__(self, key):
        return np.array(np.load(self.path, mmap_mode="r")[key])


def _solve_block(block, **kwargs):
    return tiled.solve_block(block, **kwargs)


def _chunks(size: int, tile: int, halo: int) -> tuple[int, ...]:
    """Tiles of ``tile`` pixels along a side of ``size``; a last tile narrower than the halo joins the one
    before (dask's overlap needs every block at least as wide as the halo)."""
    sizes = [tile] * (size // tile) + ([size % tile] if size % tile else [])
    if len(sizes) > 1 and sizes[-1] < max(halo, 1):
        sizes[-2] += sizes.pop()
    return tuple(sizes)


def tiled_solver(client, *, tile: int = 1024, scratch=None) -> Callable:
    """A drop-in :func:`gpps.solve_normals` that solves the frame in ``tile`` x ``tile`` blocks on ``client``'s
    workers (dask.array blocks with the halo the solver needs, :mod:`gpps.flows.tiled`).

    The frame-wide steps (checks, noise levels) run here; the packed inputs go to a scratch ``.npy`` in
    ``scratch`` (a folder the workers can read; None: the system's temporary folder), removed at the end.
    Each block's result equals the untiled solve's at its pixels.
    """
    _dask()
    import dask.array as da  # (numpy is a dependency of gpps: dask.array needs nothing more)
    tile = int(tile)

    def solve(images, mask, lights, *, camera=None, material=None, solver="lm", depth=None, robust=None, valid=None,
              config=None, device=None, progress=None, **options):
        t0 = time.perf_counter()
        cfg = config if config is not None else SolverConfig(solver=solver, robust=robust or "none", **options)
        material = Material("lambertian", ks=0.0) if material is None else material
        prep = tiled.prepare(images, mask, lights, camera=camera, config=cfg, valid=valid, depth=depth)
        n, h, w = prep["shape"]
        r = prep["halo"]
        if tile < max(r, 8):
            raise ValueError(f"tile: expected at least the halo ({r} pixels) and 8, got {tile}")
        t1 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix=".gpps-tiles-", dir=scratch) as tmp:
            path = Path(tmp) / "inputs.npy"
            np.save(path, prep.pop("packed"))
            x = da.from_array(_NpyWindow(path), chunks=(_chunks(h, tile, r), _chunks(w, tile, r), -1), asarray=True)
            depth_map = {0: r, 1: r, 2: 0}
            g = da.overlap.overlap(x, depth=depth_map, boundary="none")
            y = g.map_blocks(_solve_block, dtype=np.float32, chunks=(g.chunks[0], g.chunks[1], (tiled.output_channels(n),)),
                             n=n, shape=(h, w), lights=lights, camera=prep["camera"], material=material,
                             config=prep["config"], noise=prep["noise"], has_valid=prep["has_valid"],
                             has_depth=depth is not None, device=device)
            z = da.overlap.trim_internal(y, depth_map, boundary="none")
            if progress:
                progress(0, 1, f"normals: {x.numblocks[0] * x.numblocks[1]} tiles")
            solved = client.compute(z, sync=True)
        t2 = time.perf_counter()
        if progress:
            progress(1, 1, "normals: tiles assembled")
        return tiled.unpack(solved, prep, np.asarray(mask, bool), config=prep["config"], material=material,
                            timings={"setup": t1 - t0, "solve": t2 - t1, "total": time.perf_counter() - t0,
                                     "tiles": int(x.numblocks[0] * x.numblocks[1]), "halo": r})

    return solve


_GIVEN = ("ks", "shininess", "roughness", "f0")


def _sample_material(folder, config: FolderConfig, lights, mask, ambient, device) -> dict:
    """The material RON estimates on a downscaled copy of the capture (a worker task)."""
    res = reconstruct_folder(folder, config, lights=lights, mask=mask, ambient=ambient, device=device)
    return res.report["material"]


def reconstruct_tiled(folder, out, client=None, *, tile: int = 1024, workers: int | None = None,
                      scheduler: str | None = None, config: FolderConfig | None = None, lights=None, mask=None,
                      ambient: str | None = "auto", device: str | None = None, overwrite: bool = False,
                      sample_size: int = 512, progress: Progress | None = None, dashboard_address: str | None = ":8787",
                      **options) -> dict:
    """One large capture: the per-pixel solve tiled over the cluster's workers, then the integration of the
    assembled normal map; the outputs written to ``out`` as ``gpps reconstruct`` writes them.

    The material is estimated once (RON, :func:`gpps.reconstruct_folder` on a copy downscaled to
    ``sample_size`` pixels, on a worker) unless given or known (``known_material``), and shared by every
    tile; then the capture runs as ``method="ppn"`` with that material given and
    :func:`tiled_solver` as its per-pixel solve (:func:`gpps.reconstruct_folder`'s ``pixel_solve``): the
    result equals ``reconstruct_folder(folder, <that config>)`` untiled.  Reading, the frame-wide checks,
    the assembly and the integration run in this process (on ``device``).

    Args:
        folder, lights, mask, ambient: as :func:`gpps.reconstruct_folder`'s.
        out: the output folder (new, empty, or an earlier gpps output with ``overwrite``).
        client, workers, scheduler, dashboard_address: the cluster, as :func:`reconstruct_many`'s.
        tile: tile side (pixels, at least the solver's halo, ``neighbour_radius``).
        config, **options: :class:`gpps.FolderConfig` and field overrides (methods ``"ron"`` and ``"ppn"``).
        sample_size: the longer side of the downscaled copy the material is estimated on.
        device: this process's device (reading, integration); the workers use theirs.
        progress: ``progress(done, total, message)``.

    Returns:
        The report as written (``report.json``), with ``tiled``: tile, halo, tiles, workers, the material's source.
    """
    cfg = _config(config, options)
    if cfg.method not in ("ron", "ppn"):
        raise ValueError(f"method: expected 'ron' or 'ppn' for a tiled capture, got {cfg.method!r}")
    mask_file = mask if mask not in (None, "auto", "none") else None
    inputs = [i for i in (folder, lights, mask_file) if i is not None]
    check_output_dir(out, inputs=inputs, overwrite=overwrite, name="out")
    step = progress or (lambda *a: None)
    t0 = time.perf_counter()
    local = None if device in (None, "auto") else device
    with _client(client, scheduler, workers, device, dashboard_address) as (client, wdevice):
        source = "given" if cfg.method == "ppn" or cfg.known_material or not cfg.estimate else None
        if source is None:
            step(0, 3, f"material: RON on a copy downscaled to {sample_size} px")
            sample = replace(cfg, max_size=sample_size, integrate=False)
            mat = client.submit(_sample_material, str(folder), sample, lights, mask, ambient, wdevice, pure=False).result()
            given = {k: mat[k] for k in _GIVEN if k in mat}
            if "eta_u" in mat:
                given["eta"] = mat["eta_u"]
            cfg = replace(cfg, brdf=mat["brdf"], **given)
            source = f"RON on the capture downscaled to {sample_size} px: " + ", ".join(f"{k}={v:.4g}" for k, v in given.items())
        cfg = replace(cfg, method="ppn")
        step(1, 3, "normals: tiles")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", GppsWarning)
            res = reconstruct_folder(folder, cfg, lights=lights, mask=mask, ambient=ambient, device=local,
                                     pixel_solve=tiled_solver(client, tile=tile, scratch=Path(out).resolve().parent))
        n_workers = len(client.scheduler_info().get("workers", {}))
    t = res.report.get("timings", {})
    res.report["tiled"] = {"tile": int(tile), "halo": t.pop("halo", None), "tiles": t.pop("tiles", None),
                           "workers": n_workers, "material": source, "config": asdict(cfg)}
    step(2, 3, "writing")
    with atomic_dir(out, overwrite=overwrite, inputs=inputs, name="out") as tmp:
        report = res.write(tmp, warnings=[str(w.message) for w in caught if issubclass(w.category, GppsWarning)], started=t0)
    step(3, 3, "done")
    return report

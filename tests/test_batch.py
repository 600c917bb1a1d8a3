"""gpps batch / gpps.reconstruct_many on a LocalCluster of 2 worker processes (CPU): 6 small rendered captures and
a broken one give the same files as separate ``gpps reconstruct`` runs, the broken one a failed row in summary.csv
and exit status 1; a worker killed mid-batch loses nothing; a second run skips everything."""

from __future__ import annotations

import csv
import ctypes
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

import gpps  # noqa: E402
from gpps import batch  # noqa: E402
from gpps.cli import main  # noqa: E402
from gpps.io import write_dataset  # noqa: E402

SIZE, N_LIGHTS = 48, 4
OPTIONS = ["--known-material", "--rounds", "2"]  # the material of material.json: ~0.5 s a capture on a warm worker
CONFIG = {"known_material": True, "rounds": 2}


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """6 rendered captures (3 scenes, 2 seeds, two of them perspective) and a broken one (an image that is not one)."""
    root = tmp_path_factory.mktemp("captures")
    dirs = []
    for k in range(6):
        scene = gpps.SCENE_NAMES[k % 3]
        sc = gpps.make_scene(scene, SIZE, "perspective" if k >= 4 else "orthographic", albedo="texture", seed=k)
        lights = gpps.default_lights("directional", N_LIGHTS, slant_deg=30 + 3 * k)
        ds = gpps.render_dataset(sc, gpps.Material.default_for("blinn-phong"), lights, bits=16, seed=k, device="cpu")
        dirs.append(str(write_dataset(root / f"cap{k}_{scene}", ds)))
    broken = root / "broken"
    write_dataset(broken, ds)
    (broken / "002.png").write_bytes(b"not a PNG at all")
    return dirs, str(broken)


@pytest.fixture(scope="module")
def references(captures, tmp_path_factory):
    """The outputs of a separate ``gpps reconstruct`` process for each good capture (a process each, as users run it)."""
    dirs, _ = captures
    root = tmp_path_factory.mktemp("reference")
    out = {}
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for d in dirs:
        ref = root / Path(d).name
        p = subprocess.run([sys.executable, "-m", "gpps", "--device", "cpu", "--quiet", "reconstruct", d, "--out", str(ref),
                            *OPTIONS], capture_output=True, text=True, env=env)
        assert p.returncode == 0, p.stderr
        out[Path(d).name] = ref
    return out


@pytest.fixture(scope="module")
def client():
    distributed = pytest.importorskip("distributed")
    cluster = batch.make_cluster(2, device="cpu", dashboard_address=None)
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


def _same_outputs(ref: Path, got: Path) -> None:
    """Every file of the reference run, byte for byte (arrays value for value; report.json less its timings,
    the batch entry and its run-specific paths)."""
    names = sorted(p.name for p in ref.iterdir())
    assert names == sorted(p.name for p in got.iterdir())
    for nm in names:
        a, b = ref / nm, got / nm
        if nm.endswith(".npy"):
            x, y = np.load(a), np.load(b)
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), nm
        elif nm == "report.json":
            ra, rb = json.loads(a.read_text()), json.loads(b.read_text())
            assert "input_hash" in rb.pop("batch")
            ra.pop("timings"), rb.pop("timings")
            assert ra == rb
        else:
            assert a.read_bytes() == b.read_bytes(), nm


def _summary(out: Path) -> dict[str, dict]:
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(batch.SUMMARY_FIELDS)
    return {r["name"]: r for r in rows}


def _no_leftovers(out: Path) -> None:
    hidden = sorted(p.name for p in out.rglob(".*") if p.name not in (batch.BATCH_MARKER, gpps.io.MARKER))
    assert hidden == [], hidden


def test_batch_cli_matches_reconstruct_reports_the_broken_one_and_resumes(captures, references, client, tmp_path, capsys):
    dirs, broken = captures
    out = tmp_path / "out"
    argv = ["--device", "cpu", "batch", *dirs, broken, "--out", str(out), "--scheduler", client.scheduler.address, *OPTIONS]
    assert main(argv) == 1  # the broken capture failed
    cap = capsys.readouterr()
    assert "7 captures: 6 done, 0 skipped, 1 failed" in cap.out
    assert "batch:" in cap.err and "100.0%" in cap.err  # the whole batch's progress
    assert f"{broken}: failed:" in cap.err
    rows = _summary(out)
    assert set(rows) == {Path(d).name for d in dirs} | {"broken"}
    assert rows["broken"]["status"] == "failed" and "002.png" in rows["broken"]["error"], rows["broken"]
    assert not (out / "broken").exists()
    for name, ref in references.items():
        assert rows[name]["status"] == "done" and rows[name]["error"] == ""
        assert float(rows[name]["maen_deg"]) == pytest.approx(json.loads((ref / "report.json").read_text())["maen_deg"], abs=1e-6)
        _same_outputs(ref, out / name)
    _no_leftovers(out)
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != "summary.csv"}

    # a second run: the finished captures are skipped (not rewritten), the broken one fails again
    assert main(argv) == 1
    assert "7 captures: 0 done, 6 skipped, 1 failed" in capsys.readouterr().out
    rows = _summary(out)
    assert sorted(r["status"] for r in rows.values()) == ["failed"] + ["skipped"] * 6
    assert stamps == {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != "summary.csv"}

    # other options: not the same result, so not skipped; an earlier output is replaced only with --overwrite
    other = [a for a in argv if a != broken and a != "2"]
    other[other.index("--rounds")] = "--rounds=3"
    assert main(other) == 1
    assert "pass --overwrite" in capsys.readouterr().err
    assert stamps == {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != "summary.csv"}


def test_a_worker_killed_mid_batch_loses_nothing(captures, references, client, tmp_path):
    dirs, _ = captures
    out = tmp_path / "out"
    pids = client.run(os.getpid)
    killed = []

    def progress(done, total, message):
        if killed:
            return
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # a worker with a task of this batch
            busy = [w for w, keys in client.processing().items() if keys]
            if busy:
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed.append(busy[0])
                return
            time.sleep(0.01)

    res = gpps.reconstruct_many(dirs, out, client, device="cpu", progress=progress, **CONFIG)
    assert killed and res.ok and res.count("done") == 6, res.rows
    assert killed[0] not in {r["worker"] for r in res.rows}  # its task ran again elsewhere
    for name, ref in references.items():
        _same_outputs(ref, out / name)
    _no_leftovers(out)
    assert sorted(r["status"] for r in _summary(out).values()) == ["done"] * 6
    # the nanny started a new worker process in place of the killed one; the cluster goes on with 2
    deadline = time.monotonic() + 60
    while len(client.scheduler_info()["workers"]) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert len(client.scheduler_info()["workers"]) == 2


def test_outputs_of_others_are_refused_before_anything_runs(captures, tmp_path):
    dirs, _ = captures
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(gpps.io.OutputError, match="did not write"):
        gpps.reconstruct_many(dirs, foreign)
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
    with pytest.raises(gpps.io.OutputError, match="capture folder"):
        gpps.reconstruct_many(dirs, Path(dirs[0]) / "out")
    twin = tmp_path / "twin" / Path(dirs[0]).name
    twin.mkdir(parents=True)
    with pytest.raises(ValueError, match="share the name"):
        gpps.reconstruct_many([dirs[0], twin], tmp_path / "o")
    with pytest.raises(TypeError, match="rounds_cap"):
        gpps.reconstruct_many(dirs, tmp_path / "o", rounds_cap=2)
    with pytest.raises(TypeError, match="folders: expected a folder path or a sequence of them, got int"):
        gpps.reconstruct_many(5, tmp_path / "o")
    with pytest.raises(TypeError, match=r"folders\[1\]: expected a path"):
        gpps.reconstruct_many([dirs[0], 3], tmp_path / "o")
    assert not (tmp_path / "o").exists()


def test_a_capture_folder_that_gpps_did_not_write_is_never_replaced(captures, client, tmp_path):
    dirs, _ = captures
    out = tmp_path / "out"
    (out / Path(dirs[0]).name).mkdir(parents=True)
    (out / Path(dirs[0]).name / "mine.txt").write_text("keep me")
    (out / batch.BATCH_MARKER).write_text("{}")
    res = gpps.reconstruct_many(dirs[:1], out, client, overwrite=True, device="cpu", **CONFIG)
    assert res.failed == 1 and "did not write" in res.rows[0]["error"]
    assert (out / Path(dirs[0]).name / "mine.txt").read_text() == "keep me"


def test_input_hash_follows_contents_and_options(captures, tmp_path):
    import shutil

    dirs, _ = captures
    cfg = gpps.FolderConfig(**CONFIG)
    h = batch.input_hash(dirs[0], cfg)
    copy = Path(shutil.copytree(dirs[0], tmp_path / "copy"))
    assert batch.input_hash(copy, cfg) == h  # contents, not paths or times
    assert batch.input_hash(copy, gpps.FolderConfig(known_material=True, rounds=3)) != h
    (copy / "001.png").write_bytes((copy / "001.png").read_bytes() + b"\0")
    assert batch.input_hash(copy, cfg) != h


def test_default_cluster_pins_one_worker_per_gpu(monkeypatch):
    """Where CUDA is present (here: CUDA_VISIBLE_DEVICES names two GPUs) each worker process sees only its own."""
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    assert batch.default_workers() == (2, ["0", "1"])
    n_cpu = max(1, (os.cpu_count() or 2) // 2)
    assert batch.default_workers("cpu") == (n_cpu, [])
    distributed = pytest.importorskip("distributed")
    cluster = batch.make_cluster(dashboard_address=None)
    try:
        with distributed.Client(cluster) as c:
            seen = c.run(lambda: os.environ.get("CUDA_VISIBLE_DEVICES"))
            assert sorted(seen.values()) == ["0", "1"]
            assert all(w["nthreads"] == 1 for w in c.scheduler_info()["workers"].values())
    finally:
        cluster.close()
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert batch.default_workers() == (n_cpu, [])
    for k in batch.THREAD_VARIABLES:
        monkeypatch.delenv(k, raising=False)
    env = batch.worker_env([], 0, threads=3)
    assert all(env[k] == "3" for k in batch.THREAD_VARIABLES) and "CUDA_VISIBLE_DEVICES" not in env
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setenv("GPPS_CPU_THREADS", "2")
    env = batch.worker_env(["2"], 5, threads=3)
    assert env["OMP_NUM_THREADS"] == "1" and env["GPPS_CPU_THREADS"] == "2"  # the user's settings win
    assert env["CUDA_VISIBLE_DEVICES"] == "2"


def test_missing_dask_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"pip install 'gpps\[batch\]'"):
        batch._dask()


# ---------------------------------------------------------------------------------------------- large captures


@pytest.fixture(scope="module")
def large_capture(tmp_path_factory):
    """A 'large' capture for the tiled path, small enough for CI: a 150x150 perspective sphere, 4 lights, Blinn-Phong,
    with attached shadows (a 45 deg slant: 948 rim pixels with fewer than 3 lit images), so that the neighbour pass
    (radius 32) runs across the tile borders."""
    root = tmp_path_factory.mktemp("large")
    sc = gpps.make_scene("sphere", 150, "perspective", albedo="texture", seed=3)
    lights = gpps.default_lights("directional", N_LIGHTS, slant_deg=45)
    ds = gpps.render_dataset(sc, gpps.Material.default_for("blinn-phong"), lights, bits=16, seed=3, device="cpu")
    return str(write_dataset(root / "big", ds))


def test_tiled_solve_equals_the_untiled_one(large_capture, client, tmp_path, monkeypatch):
    from gpps.flows import tiled
    from gpps.host.metrics import angular_error

    ref = gpps.reconstruct_folder(large_capture, gpps.FolderConfig(method="ppn", known_material=True), device="cpu")
    flags = ref.report["flagged_pixels"]
    rep = batch.reconstruct_tiled(large_capture, tmp_path / "tiled", client, tile=48, method="ppn", known_material=True,
                                  device="cpu")
    assert rep["tiled"]["tiles"] == 9 and rep["tiled"]["halo"] == 32 and rep["tiled"]["workers"] == 2
    got = np.load(tmp_path / "tiled" / "normals.npy")
    m = ref.mask
    err = angular_error(got, ref.normals, m)[m]
    assert err.max() < 1e-3, err.max()  # the same pixels to float32 rounding (the shifted principal point)
    print(f"tiled against untiled: largest angle {err.max():.2e} deg, flagged pixels {flags}")
    assert abs(rep["maen_deg"] - ref.report["maen_deg"]) < 1e-4
    assert rep["flagged_pixels"] == flags
    d_ref, d = ref.depth, np.load(tmp_path / "tiled" / "depth.npy")
    fin = np.isfinite(d_ref)
    assert np.array_equal(fin, np.isfinite(d)) and np.allclose(d[fin], d_ref[fin], atol=1e-4 * np.ptp(d_ref[fin]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiled"]  # the scratch inputs are gone
    # the halo is what makes them equal: without it the neighbour pass misses pixels across the tile borders
    monkeypatch.setattr(tiled, "halo", lambda config: 0)
    batch.reconstruct_tiled(large_capture, tmp_path / "no_halo", client, tile=48, method="ppn", known_material=True,
                            device="cpu", integrate=False)
    bad = angular_error(np.load(tmp_path / "no_halo" / "normals.npy"), ref.normals, m)[m]
    assert bad.max() > 0.1, bad.max()


def test_tiled_material_from_a_downscaled_sample(large_capture, client, tmp_path):
    """The material is RON's on the downscaled copy (a worker's), given to every tile."""
    rep = batch.reconstruct_tiled(large_capture, tmp_path / "t", client, tile=80, sample_size=100, rounds=2, device="cpu")
    sample = gpps.reconstruct_folder(large_capture, gpps.FolderConfig(max_size=100, integrate=False, rounds=2), device="cpu")
    est = sample.report["material"]
    assert rep["tiled"]["material"].startswith("RON on the capture downscaled to 100 px")
    assert rep["method"] == "ppn"
    assert all(rep["material"][k] == pytest.approx(est[k], rel=1e-9) for k in ("ks", "shininess")), (rep["material"], est)
    assert rep["tiled"]["config"]["ks"] == pytest.approx(est["ks"], rel=1e-9)
    with pytest.raises(ValueError, match="tile"):
        batch.reconstruct_tiled(large_capture, tmp_path / "u", client, tile=16, known_material=True, method="ppn")


def test_each_capture_starts_from_the_default_floating_point_environment():
    """Taichi's initialisation turns flush-to-zero on in its thread: gpps puts the caller's mode back
    (gpps._taichi.init), so Taichi work leaves denormals alone here; and a warm worker resets the mode per capture
    (batch.default_fp_environment), whoever set it."""
    if not sys.platform.startswith("linux"):
        pytest.skip("fesetenv(FE_DFL_ENV) through glibc")
    from gpps import _fpenv
    from gpps.flows.integrate import integrate_normals

    def denormal():  # (made here: with flush-to-zero set, even the conversion of 1e-39 gives 0)
        return float((np.array([1e-39], np.float32) * np.float32(1.0))[0])

    sc = gpps.make_scene("sphere", 24, "orthographic")
    integrate_normals(sc.normals, sc.mask, device="cpu")  # (Taichi initialised here or earlier, kernels run)
    assert denormal() > 0.0
    if platform.machine() not in ("x86_64", "AMD64"):
        return
    saved = _fpenv.get()
    on = ctypes.create_string_buffer(saved.raw, len(saved.raw))
    on[28:32] = (int.from_bytes(saved.raw[28:32], "little") | 0x8040).to_bytes(4, "little")  # FTZ and DAZ
    try:
        _fpenv.set_env(on)
        assert denormal() == 0.0
        batch.default_fp_environment()
        assert denormal() > 0.0
    finally:
        _fpenv.set_env(saved)


def _worker_buffer_stats():
    from gpps.pipeline import buffers

    return buffers.stats()


def test_workers_keep_their_stage_buffers_between_captures(captures, client, tmp_path):
    """A worker's later captures of the same size take the device buffers its earlier ones gave back
    (gpps.pipeline.buffers), instead of allocating their own."""
    dirs, _ = captures
    before = client.run(_worker_buffer_stats)
    res = gpps.reconstruct_many(dirs, tmp_path / "out", client, device="cpu", **CONFIG)
    assert res.ok
    after = client.run(_worker_buffer_stats)
    reused = sum(after[w]["reused"] - before.get(w, {"reused": 0})["reused"] for w in after)
    # 6 captures of one size on 2 workers: at least 4 of them ran after an earlier one on the same worker,
    # each taking back its pixel solver's buffers at least (13 arrays)
    assert reused >= 4 * 13, (before, after)

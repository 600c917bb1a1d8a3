"""Users' files are sacred: every writing command checks --out before computing and never loses data."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from gpps.cli import main
from gpps.io import MARKER, OutputError, atomic_dir, check_output_dir, read_marker, save_npy


def _snapshot(root: Path) -> dict:
    """Every file below root with its content hash (what a user would not want to lose)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _no_leftovers(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if p.name.endswith((".tmp", ".old")) or ".tmp" in p.name]
    assert not left, f"temporary files left behind: {left}"


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A tiny rendered capture (written by gpps render) and a normal map with its mask."""
    root = tmp_path_factory.mktemp("cap")
    assert main(["--device", "cpu", "render", "--scene", "sphere", "--size", "24", "--camera", "orthographic",
                 "--out", str(root / "cap")]) == 0
    n = np.load(root / "cap" / "normal_gt.npy")
    np.save(root / "normals.npy", n)
    from gpps.io import save_png

    m = np.linalg.norm(n, axis=-1) > 0.5
    save_png(root / "mask.png", m.astype(np.uint8) * 255)
    return root


# ------------------------------------------------------------------ the checker


def test_check_output_dir_rules(tmp_path):
    f = tmp_path / "file.txt"
    f.write_text("user data")
    with pytest.raises(OutputError, match="--out: .*existing file"):
        check_output_dir(f)
    with pytest.raises(OutputError, match="parent that is a file"):
        check_output_dir(f / "sub")
    inp = tmp_path / "in"
    inp.mkdir()
    (inp / "001.png").write_bytes(b"x")
    with pytest.raises(OutputError, match="is an input"):
        check_output_dir(inp, inputs=[inp])
    with pytest.raises(OutputError, match="contains an input"):
        check_output_dir(tmp_path, inputs=[inp / "001.png"])
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "todo.txt").write_text("mine")
    with pytest.raises(OutputError, match="non-empty folder that gpps did not write"):
        check_output_dir(notes, overwrite=True)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check_output_dir(empty) == empty.resolve()
    assert check_output_dir(tmp_path / "new" / "deeper") == (tmp_path / "new" / "deeper").resolve()
    with pytest.raises(OutputError, match="expected a folder path"):
        check_output_dir("")


def test_gpps_output_needs_overwrite_and_only_its_own_files(tmp_path):
    out = tmp_path / "out"
    with atomic_dir(out) as d:
        save_npy(d / "a.npy", np.zeros(3))
    assert read_marker(out)["files"] == ["a.npy"]
    with pytest.raises(OutputError, match="pass --overwrite"):
        check_output_dir(out)
    with atomic_dir(out, overwrite=True) as d:
        save_npy(d / "b.npy", np.ones(3))
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER, "b.npy"])
    (out / "my_notes.txt").write_text("do not delete")
    with pytest.raises(OutputError, match="files gpps did not write"):
        check_output_dir(out, overwrite=True)
    assert (out / "my_notes.txt").read_text() == "do not delete"
    _no_leftovers(tmp_path)


@pytest.mark.parametrize("exc", [RuntimeError("boom"), KeyboardInterrupt()])
def test_failure_leaves_nothing_and_keeps_the_earlier_output(tmp_path, exc):
    out = tmp_path / "out"
    with atomic_dir(out) as d:
        save_npy(d / "a.npy", np.arange(3))
    before = _snapshot(out)
    with pytest.raises(type(exc)):
        with atomic_dir(out, overwrite=True) as d:
            save_npy(d / "a.npy", np.zeros(3))
            raise exc
    assert _snapshot(out) == before
    _no_leftovers(tmp_path)
    with pytest.raises(type(exc)):
        with atomic_dir(tmp_path / "fresh") as d:
            save_npy(d / "x.npy", np.zeros(3))
            raise exc
    assert not (tmp_path / "fresh").exists()
    _no_leftovers(tmp_path)


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_outputs_respect_the_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        out = tmp_path / "out"
        with atomic_dir(out) as d:
            save_npy(d / "a.npy", np.zeros(3))
            (d / "sub").mkdir()
            save_npy(d / "sub" / "b.npy", np.zeros(3))
    finally:
        os.umask(old)
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    assert mode(out) == 0o777 & ~umask
    assert mode(out / "sub") == 0o777 & ~umask
    assert mode(out / "a.npy") == 0o666 & ~umask
    assert mode(out / "sub" / "b.npy") == 0o666 & ~umask
    assert mode(out / MARKER) == 0o666 & ~umask


# ------------------------------------------------------------------ the commands


def _refused(capsys, argv, what):
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1 and "--out" in lines[0] and what in lines[0], err


def test_reconstruct_refuses_before_computing(capture, tmp_path, capsys, monkeypatch):
    import gpps.io

    cap = capture / "cap"
    before = _snapshot(cap)
    # nothing is read or computed when --out is refused
    monkeypatch.setattr(gpps.io, "read_dataset", lambda *a, **k: pytest.fail("computed before checking --out"))
    base = ["--device", "cpu", "reconstruct", str(cap), "--method", "ppn", "--no-integrate"]
    _refused(capsys, base + ["--out", str(cap)], "is an input")
    _refused(capsys, base + ["--out", str(capture)], "contains an input")
    f = tmp_path / "existing.txt"
    f.write_text("keep me")
    _refused(capsys, base + ["--out", str(f)], "existing file")
    _refused(capsys, base + ["--out", str(f / "x")], "parent that is a file")
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "notes.txt").write_text("keep me too")
    _refused(capsys, base + ["--out", str(notes), "--overwrite"], "did not write")
    assert f.read_text() == "keep me" and (notes / "notes.txt").read_text() == "keep me too"
    assert _snapshot(cap) == before
    _no_leftovers(tmp_path)
    _no_leftovers(capture)


def test_integrate_outputs_and_overwrite(capture, tmp_path, capsys):
    argv = ["--device", "cpu", "integrate", str(capture / "normals.npy"), "--mask", str(capture / "mask.png")]
    f = tmp_path / "depth.npy"
    f.write_bytes(b"user file")
    _refused(capsys, argv + ["--out", str(f)], "existing file")
    _refused(capsys, argv + ["--out", str(f / "sub")], "parent that is a file")
    _refused(capsys, argv + ["--out", str(capture)], "contains an input")
    out = tmp_path / "res"
    assert main(argv + ["--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    assert {"depth.npy", "depth.tiff", "mesh.ply", "report.json", MARKER} <= names
    _refused(capsys, argv + ["--out", str(out)], "--overwrite")
    assert main(argv + ["--out", str(out), "--overwrite"]) == 0
    assert f.read_bytes() == b"user file"
    _no_leftovers(tmp_path)


def test_out_dot_in_an_empty_folder(tmp_path, monkeypatch, capsys):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["--device", "cpu", "render", "--size", "16", "--out", "."]) == 0
    assert (work / "001.png").is_file() and (work / MARKER).is_file()
    _no_leftovers(tmp_path)
    # a second run needs --overwrite, and then replaces it in place
    _refused(capsys, ["--device", "cpu", "render", "--size", "16", "--out", "."], "--overwrite")
    assert main(["--device", "cpu", "render", "--size", "16", "--n-lights", "4", "--out", ".", "--overwrite"]) == 0
    monkeypatch.chdir(tmp_path)
    assert (work / "004.png").is_file()
    _no_leftovers(tmp_path)


def test_interrupt_leaves_nothing(capture, tmp_path, capsys, monkeypatch):
    import gpps.cli.integrate as ci

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ci, "_write", lambda out, *a: (save_npy(out / "depth.npy", np.zeros(2)), interrupted()))
    out = tmp_path / "res"
    rc = main(["--device", "cpu", "integrate", str(capture / "normals.npy"), "--mask", str(capture / "mask.png"),
               "--out", str(out)])
    assert rc == 130
    assert "interrupted" in capsys.readouterr().err
    assert not out.exists()
    _no_leftovers(tmp_path)


def test_out_of_memory_is_one_line_and_leaves_nothing(capture, tmp_path, capsys, monkeypatch):
    """An input too large for the memory (gpps render --size 100000 asked numpy for 74.5 GiB) ends in one line on
    stderr, exit 2 and no output, not a MemoryError traceback."""
    import gpps.cli.integrate as ci

    def huge(*a, **k):
        raise MemoryError("Unable to allocate 74.5 GiB for an array")

    monkeypatch.setattr(ci, "_write", lambda out, *a: (save_npy(out / "depth.npy", np.zeros(2)), huge()))
    out = tmp_path / "res"
    rc = main(["--device", "cpu", "integrate", str(capture / "normals.npy"), "--mask", str(capture / "mask.png"),
               "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "error: not enough memory (Unable to allocate 74.5 GiB" in err and "Traceback" not in err
    assert not out.exists()
    _no_leftovers(tmp_path)


def test_render_errors_name_the_options(tmp_path, capsys):
    for extra, want in ((["--size", "0"], "--size: expected"), (["--n-lights", "0"], "--n-lights: expected"),
                        (["--slant", "95"], "--slant: expected <= 89"), (["--noise", "-1"], "--noise: expected"),
                        (["--ks", "-1"], "--ks: expected"), (["--brdf", "plastic", "--ior", "0.5"], "--ior: expected")):
        assert main(["--device", "cpu", "render", "--size", "16", *extra, "--out", str(tmp_path / "o")]) == 2
        assert f"error: {want}" in capsys.readouterr().err, extra
        assert not (tmp_path / "o").exists()

"""The package's folders are its layers: this test reads every import (ast) and fails on one that runs upward.

Layers, lowest first (README, "Package map"):

* ``base``: ``gpps._check``, ``gpps.names``, ``gpps._runtime``, ``gpps._taichi``, ``gpps._fpenv`` (checks, names, device runtime);
* ``types``: ``gpps.camera``, ``gpps.lights``, ``gpps.material`` (value types);
* ``kernels``: ``gpps.kernels`` (device math only);
* ``host``: ``gpps.host``, ``gpps.nn`` (numpy / scipy algorithms);
* ``io``: ``gpps.io`` (readers and writers);
* ``pipeline``: ``gpps.pipeline`` (stages that own device buffers and launch);
* ``flows``: ``gpps.flows`` (whole reconstructions);
* ``api``: ``gpps`` itself (the public names) and ``gpps.batch`` (batches of captures on Dask);
* ``cli``: ``gpps.cli`` and ``gpps.__main__`` (``python -m gpps``), which may use only the public face (``gpps`` and
  ``gpps.io``).

Each layer may import the layers listed for it in ``ALLOWED``; imports inside functions count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "gpps"

LAYER_OF_TOP = {
    "_check": "base", "names": "base", "_version": "base", "_runtime": "base", "_taichi": "base", "_fpenv": "base",
    "camera": "types", "lights": "types", "material": "types",
    "kernels": "kernels", "host": "host", "nn": "host", "io": "io", "pipeline": "pipeline", "flows": "flows",
    "__init__": "api", "batch": "api", "__main__": "cli", "cli": "cli",
}
ALLOWED = {
    "base": {"base"},
    "types": {"base", "types"},
    "kernels": {"base", "kernels"},
    "host": {"base", "types", "host"},
    "io": {"base", "types", "host", "io"},
    "pipeline": {"base", "types", "kernels", "host", "io", "pipeline"},
    "flows": {"base", "types", "host", "io", "pipeline", "flows"},
    "api": {"base", "types", "host", "io", "pipeline", "flows", "api"},
    "cli": {"api", "cli", "public-io"},
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts = parts[:-1]
    return ".".join(parts)


def layer_of(module: str) -> str:
    """The layer of a ``gpps...`` module name."""
    parts = module.split(".")
    if parts == ["gpps"]:
        return "api"
    return LAYER_OF_TOP[parts[1]]


def _imported(path: Path):
    """(line, imported gpps module) for every import of the file, functions included."""
    tree = ast.parse(path.read_text(), filename=str(path))
    submodules = {p.stem for p in PACKAGE.glob("*.py")} | {p.name for p in PACKAGE.iterdir() if p.is_dir()}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "gpps":
                    yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: relative import (write gpps.… in full)"
            if node.module is None or node.module.split(".")[0] != "gpps":
                continue
            if node.module == "gpps":
                for alias in node.names:  # ``from gpps import _taichi`` imports a submodule
                    yield node.lineno, f"gpps.{alias.name}" if alias.name in submodules else "gpps"
            else:
                yield node.lineno, node.module


def upward_imports() -> list[str]:
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        mod = _module_name(path)
        here = layer_of(mod)
        for line, target in _imported(path):
            there = layer_of(target)
            if here == "cli" and target.startswith("gpps.io"):
                there = "public-io" if target == "gpps.io" else there
            if there not in ALLOWED[here]:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {mod} ({here}) imports {target} ({there})")
    return bad


def test_every_top_level_name_has_a_layer():
    for p in PACKAGE.iterdir():
        if p.name.startswith(".") or p.name == "__pycache__" or (p.is_file() and p.suffix != ".py"):
            continue
        assert (p.stem if p.is_file() else p.name) in LAYER_OF_TOP, f"{p.name}: add it to a layer"


def test_no_import_runs_upward():
    bad = upward_imports()
    assert not bad, "imports that run upward between layers:\n" + "\n".join(bad)


@pytest.mark.parametrize("case, expected", [
    ("from gpps.pipeline.solver import PixelSolver", "pipeline"),
    ("from gpps import _taichi", "gpps._taichi"),
    ("import gpps.flows.ron", "flows"),
])
def test_the_reader_sees_imports(tmp_path, case, expected):
    """The checker itself: an import in a function body is found and classified."""
    f = tmp_path / "m.py"
    f.write_text(f"def f():\n    {case}\n")
    (target,) = [t for _, t in _imported(f)]
    assert target == expected or layer_of(target) == expected

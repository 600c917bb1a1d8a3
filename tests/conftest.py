"""Shared test set-up: project-controlled caches, devices, data paths."""

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

SHARED = ROOT.parent / "shared"
DATA = Path(os.environ.get("GPPS_DATA", SHARED / "data"))


def pytest_configure(config):
    # `pytest -m fuzz`: the property tests of tests/test_fuzz_api.py run their large profile (10,000 inputs)
    if "fuzz" in (config.getoption("markexpr", "") or ""):
        os.environ["GPPS_FUZZ"] = "1"


def _devices():
    from gpps._runtime import available_devices

    devs = ["cpu"]
    if any(d.startswith("cuda") for d in available_devices()):
        devs.append("cuda:0")
    only = os.environ.get("GPPS_TEST_DEVICES")  # e.g. "cuda:0" on the GPU machine
    if only:
        devs = [d for d in devs if d in only.split(",")]
    return devs


DEVICES = _devices()


def _render_device():
    """The device for a test's set-up renders: ``"cpu"`` where Warp has one (the development machine, CI), else the
    first test device (the GPU machine's Warp is built without its CPU compiler)."""
    from gpps._runtime import available_devices

    return "cpu" if "cpu" in available_devices() else DEVICES[0]


RENDER_DEVICE = _render_device()


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", DEVICES)


@pytest.fixture(scope="session")
def data_root():
    if not DATA.is_dir():
        pytest.skip(f"real data not found at {DATA}")
    return DATA

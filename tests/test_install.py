"""The locked install (requirements/lock.txt against pyproject.toml) and ``cosy doctor``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LOCK = REPO / "requirements" / "lock.txt"


def _requirements():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    from packaging.requirements import Requirement

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in project.get("optional-dependencies", {}).values():
        reqs += extra
    return [Requirement(r) for r in reqs]


def test_lock_pins_every_dependency_within_its_range_and_nothing_twice():
    """Every dependency of pyproject.toml (extras included) is pinned with == in the lock at a
    version its range allows; every range has an upper bound (below the next major) except
    calendar-versioned dask and exact pins; no package is pinned twice; pip and setuptools are
    pinned too (the Makefile installs pip from the lock first and builds cosy without isolation)."""
    from packaging.utils import canonicalize_name
    from packaging.version import Version

    from cosy_cli.doctor import read_lock

    lines = [ln.strip() for ln in LOCK.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert all("==" in ln and ln.count("==") == 1 for ln in lines), [ln for ln in lines if "==" not in ln]
    names = [canonicalize_name(ln.split("==")[0]) for ln in lines]
    assert len(names) == len(set(names)), "a package is pinned twice"
    pins = {canonicalize_name(k): v for k, v in read_lock(LOCK).items()}
    assert {"pip", "setuptools", "torch"} <= set(pins)
    assert "+" not in pins["torch"]  # ==2.13.0 also takes the local CPU build 2.13.0+cpu
    for req in _requirements():
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not in the lock"
        assert req.specifier.contains(Version(pins[name]), prereleases=True), f"{req} vs locked {pins[name]}"
        ops = {s.operator for s in req.specifier}
        assert ops & {"<", "=="} or name == "dask", f"{req} has no upper bound"
        pin = Version(pins[name])
        for s in req.specifier:
            if s.operator == "<":  # capped below the next major release after the locked one (0.x: 1.0 or the next minor)
                cap = Version(s.version)
                assert cap == Version(str(pin.major + 1)) if pin.major else cap in (Version("1"), Version(f"0.{pin.minor + 1}")), \
                    f"{req}: cap {cap} is not the next major after the locked {pin}"


def test_read_lock_and_differences(tmp_path):
    from importlib import metadata

    from cosy_cli.doctor import lock_differences, read_lock

    np_version = metadata.version("numpy")
    lock = tmp_path / "lock.txt"
    lock.write_text(f"# a comment\nnumpy=={np_version}\nNo_Such_Package==1.0  # trailing\ntorch==0.0.1\n")
    assert read_lock(lock) == {"numpy": np_version, "no-such-package": "1.0", "torch": "0.0.1"}
    diff = lock_differences(lock)
    assert not any(d.startswith("numpy") for d in diff)
    assert "no-such-package missing (locked 1.0)" in diff
    assert any(d.startswith("torch ") and d.endswith("(locked 0.0.1)") for d in diff)


def test_doctor_lists_versions_threads_providers_and_renders_a_triangle():
    from click.testing import CliRunner

    from cosy_cli.cli.main import cli

    r = CliRunner().invoke(cli, ["doctor"])
    assert r.exit_code == 0, r.output
    out = r.output
    for topic in ("cosy", "python", "packages", "lock", "cpu", "torch", "onnxruntime", "opencv", "rendering"):
        assert any(line.startswith(topic) for line in out.splitlines()), topic
    assert "opencv-python-headless " in out and "CPUExecutionProvider" in out
    assert "a test triangle rendered right" in out
    assert "locked versions installed" in out or "differ from the tested versions" in out  # a source checkout


def test_doctor_says_in_one_line_why_rendering_cannot_work():
    env = dict(os.environ, COSY_GL="vulkan")
    env.pop("PYOPENGL_PLATFORM", None)
    r = subprocess.run([sys.executable, "-m", "cosy_cli", "doctor"], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("error: rendering cannot work:") and "COSY_GL='vulkan'" in last
    assert "FAILS" in r.stdout  # the report itself is still printed

"""The installable product: a wheel that carries everything and serves from any folder, the
Docker image built from that wheel, and the pinned versions CI and the image install."""

from __future__ import annotations

import inspect
import os
import re
import shutil
import site as sitemodule
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement

from eqgw.ingest.service import IngestService
from tests.proc_helpers import ROOT, Process, free_port
from tests.support import web

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_subpackage_is_packaged() -> None:
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    top = next(p for p in listed if "." not in p)
    found = {
        ".".join([top, *d.relative_to(ROOT / "app").parts]).rstrip(".")
        for d in (ROOT / "app").rglob("*")
        if d.is_dir() and (d / "__init__.py").is_file()
    } | {top}
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"
    mapped = PYPROJECT["tool"]["setuptools"]["package-dir"]
    assert mapped == {top: "app", f"{top}.migrations": "migrations", f"{top}.static": "static"}


def test_constraints_pin_every_dependency_and_ci_uses_them() -> None:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[re.sub(r"[-_.]+", "-", name).lower()] = version
    project = PYPROJECT["project"]
    wanted = [Requirement(r) for r in project["dependencies"]]
    wanted += [Requirement(r) for extra in project["optional-dependencies"].values() for r in extra]
    for req in wanted:
        name = re.sub(r"[-_.]+", "-", req.name).lower()
        assert name in pins, f"{req.name} is not pinned: python scripts/constraints.py"
        assert req.specifier.contains(pins[name], prereleases=True), (req, pins[name])
    assert "-c constraints.txt" in (ROOT / ".ci" / "run").read_text()


def test_the_image_installs_the_wheel_with_a_health_check_and_a_grace_period() -> None:
    docker = (ROOT / "Dockerfile").read_text()
    lines = [line.strip() for line in docker.splitlines() if line.strip() and line[0] != "#"]
    assert "pip install -e" not in docker and "pip wheel" in docker
    assert any(
        line.startswith("RUN pip install -c /tmp/constraints.txt /tmp/wheels/") for line in lines
    ), lines
    health = next(i for i, line in enumerate(lines) if line.startswith("HEALTHCHECK"))
    assert "/readyz" in lines[health] + lines[health + 1]
    # The compose stop grace period outlasts the shutdown's bound (the writer's last flush).
    bound = inspect.signature(IngestService.stop).parameters["timeout"].default
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    grace = compose["services"]["eqgw"]["stop_grace_period"]
    assert grace.endswith("s") and float(grace[:-1]) > bound, (grace, bound)
    for service in ("simulator", "forwarder"):  # no HTTP in those: no /readyz to check
        assert compose["services"][service]["healthcheck"] == {"disable": True}


@pytest.mark.slow
def test_a_wheel_installed_elsewhere_serves_from_an_empty_folder(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("app", "migrations", "static"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp_path / "dist"
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(src)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr
    (wheel,) = dist.glob("eqgw-*.whl")
    top = next(p for p in PYPROJECT["tool"]["setuptools"]["packages"] if "." not in p)
    names = set(zipfile.ZipFile(wheel).namelist())
    for inside in (
        "migrations/env.py",
        "migrations/versions/0001_initial_schema.py",
        "static/index.html",
        "static/vendor/swagger-ui/swagger-ui-bundle.js",
        "protocol/vanner_equalizer.dbc",
        "sim/scenarios/equalizer-fault.yaml",
    ):
        assert f"{top}/{inside}" in names, inside
    assert {n.split("/")[0] for n in names} == {
        top,
        wheel.name.split("-")[0] + "-" + wheel.name.split("-")[1] + ".dist-info",
    }

    # A fresh environment: the wheel alone, the dependencies visible as a plain path (no
    # editable install of this checkout, whose import hook would win over the wheel).
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    vpy = venv / "bin" / "python"
    site = subprocess.run(
        [str(vpy), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    installed = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(vpy), "install", "-q", "--no-deps",
         "--no-index", str(wheel)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert installed.returncode == 0, installed.stderr
    deps = dict.fromkeys([sysconfig.get_path("purelib"), *sitemodule.getsitepackages()])
    Path(site, "deps.pth").write_text("".join(f"{d}\n" for d in deps))

    empty = tmp_path / "empty"
    empty.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("EQGW_", "PYTHON"))}
    where = subprocess.run(
        [str(vpy), "-c", f"import {top}; print({top}.__file__)"],
        cwd=empty, env=env, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    assert where.startswith(site), where
    port = free_port()
    proc = Process([str(venv / "bin" / "eqgw"), "serve", "--simulate", "1", "--port", str(port)],
                   empty, {**env, "PYTHONPATH": ""})  # fmt: skip
    try:
        proc.wait_line(re.compile("serving on"), timeout=120)
        base = f"http://127.0.0.1:{port}"
        assert web.get(f"{base}/readyz", timeout=10).status_code == 200
        assert web.get(f"{base}/docs", timeout=10).status_code == 200
        js = web.get(f"{base}/static/vendor/swagger-ui/swagger-ui-bundle.js", timeout=10)
        assert js.status_code == 200 and len(js.content) > 100_000
        assert web.get(base + "/", timeout=10).status_code == 200  # the dashboard
    finally:
        proc.stop()
    assert sorted(p.name for p in empty.iterdir() if not p.name.startswith("eqgw.db")) == []


def test_importing_the_folder_name_fails_with_one_line() -> None:
    """`import app` from a checkout's root would load every module a second time: it fails."""
    done = subprocess.run(
        [sys.executable, "-c", "import app"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: the package folder app/ is imported as 'app'"), last
    assert "import it as 'eqgw'" in last

"""Packaging: `pipeline/` and `stages/` install as skyroute.pipeline / skyroute.stages only,
from an editable install and from a built wheel."""

from __future__ import annotations

import json
import site
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

import skyroute.pipeline

REPO = Path(__file__).resolve().parents[1]

PROBE = (
    "import json, importlib.util, skyroute.pipeline, skyroute.stages, skyroute.catalogs;"
    "from skyroute.pipeline.settings import load_scenario;"
    "sc = load_scenario('helsinki-medical');"
    "print(json.dumps({'pipeline': skyroute.pipeline.__file__, 'catalogs': str(sc.source_path),"
    " 'top_pipeline': importlib.util.find_spec('pipeline') is not None,"
    " 'top_stages': importlib.util.find_spec('stages') is not None, 'nx': sc.grid.nx}))"
)


def _probe(python: str, cwd: Path) -> dict:
    out = subprocess.run([python, "-c", PROBE], cwd=cwd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_editable_install_imports_from_the_repo(tmp_path):
    info = _probe(sys.executable, tmp_path)
    assert Path(info["pipeline"]).resolve() == (REPO / "pipeline" / "__init__.py").resolve()
    assert not info["top_pipeline"] and not info["top_stages"]
    assert Path(skyroute.pipeline.__file__).parent.name == "pipeline"


@pytest.mark.slow
def test_built_wheel_installs_and_runs(tmp_path):
    wheel_dir = tmp_path / "wheel"
    # build with isolation, as a user's `pip install .` does: the build backend comes from
    # pyproject's build-system (setuptools>=77 for the SPDX licence string), not this venv
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(wheel_dir), str(REPO)],
                   check=True, capture_output=True, text=True)
    wheels = list(wheel_dir.glob("skyroute-*.whl"))
    assert len(wheels) == 1
    import zipfile

    names = zipfile.ZipFile(wheels[0]).namelist()
    assert "skyroute/pipeline/cli.py" in names and "skyroute/stages/surface.py" in names
    assert "skyroute/catalogs/scenarios/helsinki-medical.yaml" in names
    assert "skyroute/catalogs/data/helsinki_center.osm.pbf" in names
    for f in ("leaflet.js", "leaflet.css", "LICENSE", "images/layers.png"):   # plan.html inlines them
        assert f"skyroute/pipeline/vendor/leaflet/{f}" in names, f
    assert not any(n.startswith(("pipeline/", "stages/")) for n in names)
    # every source file of the three folders is in the wheel (sub-packages included)
    for folder in ("pipeline", "stages", "catalogs"):
        for f in (REPO / folder).rglob("*.py"):
            assert f"skyroute/{f.relative_to(REPO).as_posix()}" in names, f"{f} missing from the wheel"
    # a fresh venv that sees this environment's dependencies but not the editable skyroute
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    purelib = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()}
    (purelib / "deps.pth").write_text("\n".join(sorted(deps)) + "\n")  # plain paths: no editable finder
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--target", str(purelib), str(wheels[0])],
                   check=True, capture_output=True, text=True)
    info = _probe(str(py), tmp_path)
    assert Path(info["pipeline"]).is_relative_to(purelib)
    assert Path(info["catalogs"]).is_relative_to(purelib)
    assert not info["top_pipeline"] and not info["top_stages"] and info["nx"] == 527
    out = subprocess.run([str(py), "-m", "skyroute.pipeline.cli", "scenarios"], cwd=tmp_path,
                         capture_output=True, text=True, check=True)
    assert "helsinki-medical" in out.stdout
    # every stage module imports from the installed wheel
    mods = sorted("skyroute." + ".".join(f.relative_to(REPO).with_suffix("").parts)
                  for folder in ("pipeline", "stages") for f in (REPO / folder).rglob("*.py")
                  if f.name != "__init__.py")
    code = "import importlib, sys; [importlib.import_module(m) for m in sys.argv[1:]]; print('ok')"
    out = subprocess.run([str(py), "-c", code, *mods], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]

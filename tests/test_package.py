"""EBRL as a package: the wheel built from the repository holds the services and the stock configs, and runs
outside any clone (an empty directory, a new venv: `ebrl up quickstart` and `ebrl.train`). The new venv takes
the dependencies from this one's site-packages (a .pth file) instead of downloading them again; EBRL itself
comes only from the wheel."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import zipfile

import pytest

from ebrl.testing import free_port
from helpers import ROOT


@pytest.mark.slow
def test_the_wheel_runs_the_quickstart_by_name_outside_the_repository(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(wheels), str(ROOT)],
                   check=True, timeout=300)
    wheel = next(wheels.glob("ebrl-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert "ebrl/services/gen.py" in names and "ebrl/configs/quickstart.toml" in names
    assert not any(n.startswith(("services/", "tests/", "configs/")) for n in names)  # no top-level packages
    dist = next(n.split("/")[0] for n in names if n.endswith(".dist-info/METADATA"))
    assert f"{dist}/licenses/LICENSE" in names  # Apache-2.0, its text as the repository has it
    metadata = zipfile.ZipFile(wheel).read(f"{dist}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in metadata and "Classifier: Intended Audience :: Science/Research" in metadata

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True, timeout=300)
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (tmp_path / "venv" / site.split(str(venv) + "/", 1)[1] / "deps.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n")  # this venv's dependencies (EBRL's editable finder is not run)
    empty = tmp_path / "empty"
    empty.mkdir()
    where = subprocess.run([str(python), "-c", "import ebrl; print(ebrl.__file__)"], capture_output=True,
                           text=True, cwd=empty, check=True).stdout
    assert where.startswith(str(venv)), where

    listen = f'bus.listen=["tcp/127.0.0.1:{free_port()}"]'
    up = subprocess.run([str(venv / "bin" / "ebrl"), "up", "quickstart", "--set", "run.iterations=2", "--set",
                         listen], capture_output=True, text=True, cwd=empty, timeout=300)
    assert up.returncode == 0 and "run quickstart finished: 2 iterations" in up.stdout, up.stdout + up.stderr
    script = (f'import ebrl\nrun = ebrl.train("quickstart", run={{"iterations": 2, "name": "api"}}, '
              f'bus={{"listen": ["tcp/127.0.0.1:{free_port()}"]}})\nprint(run.exit_code, run.policy_path)\n')
    trained = subprocess.run([str(python), "-c", script], capture_output=True, text=True, cwd=empty, timeout=300)
    assert trained.returncode == 0 and trained.stdout.splitlines()[-1].startswith("0 runs/api-"), \
        trained.stdout + trained.stderr

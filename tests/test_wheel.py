"""The package as a user installs it: ``python -m build`` makes an sdist and, from the sdist, a pure
Python wheel (``py3-none-any``); the wheel installs (not editable) into a fresh virtual environment,
runs there, and a user's type checker sees its real signatures (tensor in, tensor out; the string
options as Literal types).

The environment finds the torch, jax, numpy and mypy of the Python running the tests, without
downloading them, through a ``.pth`` file that appends that Python's site-packages folders to its
path. Not ``--system-site-packages``: from inside a virtual environment (where the README runs the
tests) that reaches the base interpreter's packages, not the environment's, and torch is missing
there. What makes it a test of the wheel is that the environment's own site-packages, where the
wheel goes, comes first (the appended folders' own ``.pth`` files, such as an editable install's, are
not read), which every test here checks (``diffquat.__file__`` and the files mypy reads lie in the
environment).
"""

from __future__ import annotations

import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str | Path], cwd: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    # Away from the repository (no checkout on sys.path) and without PYTHONPATH.
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True)
    if check and out.returncode != 0:
        raise AssertionError(f"{args} failed ({out.returncode}):\n{out.stdout}\n{out.stderr}")
    return out


def build(out: Path) -> None:
    """``python -m build``: the sdist, then the wheel built from the unpacked sdist (so the sdist must
    hold everything the build needs). ``--no-isolation``: the build runs on the setuptools installed
    here (the build-system requirement), with no download."""
    _run([sys.executable, "-m", "build", "--no-isolation", "--outdir", out, ROOT], cwd=out)


def packages_here() -> list[str]:
    """The folders the Python running the tests imports installed packages from: its site-packages
    (a virtual environment's own, or the base interpreter's), and the user's where it is on."""
    folders = [*site.getsitepackages(), sysconfig.get_path("purelib"), sysconfig.get_path("platlib")]
    if site.ENABLE_USER_SITE:
        folders.append(site.getusersitepackages())
    return [f for f in dict.fromkeys(folders) if Path(f).is_dir()]


def install(dist: Path, home: Path) -> Path:
    """A fresh virtual environment with the wheel installed in it, not editable; its Python."""
    _run([sys.executable, "-m", "venv", "--without-pip", home / "env"], cwd=home)
    python = home / "env" / "bin" / "python"
    own = _run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], cwd=home)
    # After the environment's own site-packages: the packages installed here, pip included.
    (Path(own.stdout.strip()) / "packages_of_the_tests.pth").write_text("\n".join(packages_here()) + "\n")
    (wheel,) = dist.glob("*.whl")
    # The pip installed here, run by the environment's Python, installs into the environment.
    _run([python, "-m", "pip", "install", "--no-deps", "--no-index", "--quiet", wheel], cwd=home)
    return python


def check_contents(dist: Path) -> None:
    (sdist,) = dist.glob("*.tar.gz")
    with tarfile.open(sdist) as tar:
        in_sdist = {name.split("/", 1)[1] for name in tar.getnames() if "/" in name}
    for name in ("diffquat/__init__.py", "diffquat/py.typed", "pyproject.toml", "README.md"):
        assert name in in_sdist, name
    (wheel,) = dist.glob("*.whl")
    # Pure Python: one wheel for every platform and every Python 3.
    assert wheel.name == "diffquat-0.1.0-py3-none-any.whl", wheel.name
    in_wheel = set(zipfile.ZipFile(wheel).namelist())
    assert {
        "diffquat/py.typed",
        "diffquat/torch/nn.py",
        "diffquat/jax/nn.py",
    } <= in_wheel
    packaged = in_sdist | in_wheel
    native = [n for n in packaged if re.search(r"\.(c|h|so|pyd|dylib)$", n) or "_kernels" in n]
    assert native == [], native


SMOKE = """
import sys
import numpy as np, torch, jax.numpy as jnp
import diffquat, diffquat.numpy as dn, diffquat.torch as dt, diffquat.jax as dj
from diffquat.torch.nn import RotationHead

prefix = sys.argv[1]
assert diffquat.__file__.startswith(prefix), diffquat.__file__
assert torch.__file__ and not torch.__file__.startswith(prefix), torch.__file__  # torch from here
half_turn_x = np.diag([1.0, -1.0, -1.0])
q = [0.0, 1.0, 0.0, 0.0]
np.testing.assert_allclose(dn.quaternion_to_matrix(np.array(q)), half_turn_x, atol=1e-15)
np.testing.assert_allclose(dt.quaternion_to_matrix(torch.tensor(q)).numpy(), half_turn_x, atol=1e-7)
np.testing.assert_allclose(np.asarray(dj.quaternion_to_matrix(jnp.array(q))), half_turn_x, atol=1e-7)
r = RotationHead(8, "6d")(torch.zeros(2, 8))
assert r.shape == (2, 3, 3)
print("ok", diffquat.__version__)
"""


def smoke(venv: Path, tmp_path: Path) -> None:
    script = tmp_path / "smoke.py"
    script.write_text(SMOKE)
    out = _run([venv, script, venv.parents[1]], cwd=tmp_path)
    assert out.stdout.strip() == "ok 0.1.0"


# A user's script: each ``assert_type`` must hold, and each line marked ``# error`` must be the one
# error mypy reports on that line (a wrong string option is caught where it is written).
USER_SCRIPT = """
from typing import Any, assert_type

import jax
import numpy as np
import torch
from numpy.typing import NDArray

import diffquat.jax as dqj
import diffquat.numpy as dqn
import diffquat.torch as dqt
from diffquat.jax.nn import rotation_head
from diffquat.torch.nn import RotationHead

q = torch.randn(8, 4)
assert_type(dqt.quaternion_to_matrix(q), torch.Tensor)
assert_type(dqt.matrix_to_quaternion(dqt.quaternion_to_matrix(q), scalar_first=False), torch.Tensor)
assert_type(dqt.euler_angles_to_matrix(torch.zeros(3), "ZYX"), torch.Tensor)
assert_type(dqt.rotation_6d_to_matrix(torch.zeros(6), layout="rows"), torch.Tensor)
assert_type(dqn.quaternion_to_matrix(np.zeros(4)), NDArray[Any])
assert_type(dqj.quaternion_to_matrix(np.zeros(4)), jax.Array)
assert_type(RotationHead(16, "6d")(torch.zeros(2, 16)), torch.Tensor)
assert_type(rotation_head({}, np.zeros(3), "quaternion"), jax.Array)
dqt.euler_angles_to_matrix(torch.zeros(3), "XYW")  # error: arg-type
RotationHead(16, "rot6d")  # error: arg-type
dqt.rotation_6d_to_matrix(q, layout="row")  # error: arg-type
dqt.quaternion_to_matrix(q, scalar_first="yes")  # error: arg-type
"""


def type_check(venv: Path, tmp_path: Path) -> None:
    """mypy, run by the environment's Python on a user's script, reads the installed wheel (its
    ``py.typed``): the expected types hold and exactly the marked lines are errors. It runs with the
    project's mypy settings and, where the test command's ``mypy`` left one, a copy of its cache, so
    that torch and jax are not analysed again (a minute otherwise)."""
    script = tmp_path / "user.py"
    script.write_text(USER_SCRIPT)
    cache = tmp_path / "mypy_cache"
    if (ROOT / ".mypy_cache").is_dir():
        shutil.copytree(ROOT / ".mypy_cache", cache)
    args = [venv, "-m", "mypy", "--config-file", ROOT / "pyproject.toml", "--cache-dir", cache, "-v", script]
    out = _run(args, cwd=tmp_path, check=False)
    read = set(re.findall(r"(/\S+/diffquat/\S+?\.pyi?)\b", out.stderr))
    assert read and all(path.startswith(str(venv.parents[1])) for path in read), sorted(read)
    lines = USER_SCRIPT.splitlines()
    expected = {
        (i + 1, m.group(1)) for i, line in enumerate(lines) if (m := re.search(r"# error: (\S+)", line))
    }
    reported = {
        (int(m.group(1)), m.group(2))
        for m in re.finditer(r"^user\.py:(\d+): error: .*\[(\S+)\]$", out.stdout, re.MULTILINE)
    }
    assert reported == expected, out.stdout
    assert len(expected) == 4


def test_wheel_builds_installs_runs_and_type_checks(tmp_path: Path) -> None:
    """One test (the build is its cost, ~15 s): the sdist and the wheel hold what they must, the wheel
    runs in a fresh environment, and mypy there sees the real signatures."""
    dist, home = tmp_path / "dist", tmp_path / "home"
    dist.mkdir(), home.mkdir()
    build(dist)
    check_contents(dist)
    python = install(dist, home)
    smoke(python, home)
    type_check(python, home)

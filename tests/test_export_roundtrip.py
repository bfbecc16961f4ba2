"""The documented jax deployment path, in an environment made from the ``[jax]`` extra alone: a
function exported with ``jax.export``, serialised to bytes, deserialised and called gives the direct
call's values and gradient. jax does not require ``flatbuffers``, which ``serialize`` imports: the
extra must.

The environment is a fresh virtual environment holding exactly the packages that
``pip install "diffquat[jax]"`` installs: the closure of the extra's requirements over the installed
packages' metadata, each linked in from where it is installed here (no download), and diffquat from
this checkout. A package that only another extra brings (the test extra's onnxruntime requires
flatbuffers too) is absent there, so it cannot hide a missing requirement. The round trip runs in
that environment's Python, isolated (``-I``), with jax's defaults (float32).
"""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]

ROUND_TRIP = """
import jax, jax.numpy as jnp, numpy as np
import diffquat.jax as dq

q = dq.random_quaternions((5,), key=jax.random.key(0))
(batch,) = jax.export.symbolic_shape("b")
functions = {
    "quaternion_to_matrix": (dq.quaternion_to_matrix, q),
    "matrix_to_quaternion": (dq.matrix_to_quaternion, dq.quaternion_to_matrix(q)),
    "so3_log": (dq.so3_log, dq.quaternion_to_matrix(q)),
    "euler_angles_to_matrix": (lambda a: dq.euler_angles_to_matrix(a, "ZYX"), q[:, :3]),
}
for name, (fn, x) in functions.items():
    shape = jax.ShapeDtypeStruct((batch, *x.shape[1:]), x.dtype)
    blob = jax.export.export(jax.jit(fn))(shape).serialize(vjp_order=1)
    assert isinstance(blob, bytearray) and len(blob) > 0, name
    loaded = jax.export.deserialize(blob)
    np.testing.assert_allclose(loaded.call(x), fn(x), rtol=2e-6, atol=2e-7, err_msg=name)
    grad = jax.grad(lambda x: jnp.sum(loaded.call(x) ** 2))(x)
    np.testing.assert_allclose(grad, jax.grad(lambda x: jnp.sum(fn(x) ** 2))(x), rtol=2e-5, atol=2e-6,
                               err_msg=name)
print("round trip ok:", ", ".join(functions))
"""


def _name(requirement: str) -> str:
    return re.sub(r"[-_.]+", "-", requirement).lower()


def installed_by(package: str, extra: str) -> set[str]:
    """The distributions ``pip install "<package>[<extra>]"`` installs: the closure of its
    requirements (their extras followed, markers evaluated here) over the installed metadata."""
    found: set[str] = set()
    todo = [(package, {extra})]
    while todo:
        name, extras = todo.pop()
        if _name(name) in found and not extras:
            continue
        found.add(_name(name))
        for line in importlib.metadata.requires(name) or []:
            requirement = Requirement(line)
            chosen = requirement.marker is None or any(
                requirement.marker.evaluate({**default_environment(), "extra": e}) for e in extras | {""}
            )
            if chosen and _name(requirement.name) not in found:
                todo.append((requirement.name, set(requirement.extras)))
    return found


def environment_of(package: str, extra: str, home: Path) -> Path:
    """A virtual environment (no pip, nothing of this Python's) with what ``installed_by`` finds
    linked into its site-packages; its Python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", home], check=True)
    python = home / "bin" / "python"
    own = subprocess.run(
        [python, "-I", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True,
        text=True,
        check=True,
    )
    site = Path(own.stdout.strip())
    for name in sorted(installed_by(package, extra)):
        if name == _name(package):
            (site / package).symlink_to(ROOT / package)  # this checkout's, as an editable install
            continue
        distribution = importlib.metadata.distribution(name)
        tops = {f.parts[0] for f in distribution.files or [] if f.parts[0] not in ("..", "__pycache__")}
        for top in sorted(tops):
            source = Path(str(distribution.locate_file(top)))
            if source.exists() and not (site / top).exists():
                (site / top).symlink_to(source)
    return python


def test_serialize_deserialize_call_in_an_environment_of_the_jax_extra(tmp_path: Path) -> None:
    assert "flatbuffers" in installed_by("diffquat", "jax")
    python = environment_of("diffquat", "jax", tmp_path / "env")
    out = subprocess.run(
        [python, "-I", "-c", ROUND_TRIP], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("so3_log, euler_angles_to_matrix"), out.stdout

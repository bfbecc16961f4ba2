"""The C kernels (``diffquat/_kernels.c``) as a release builds them beyond this machine: warning-free
with gcc and clang at ``-Wall -Wextra``, and for aarch64 (no x86 intrinsics), where a standalone build
of the kernels, run under qemu, gives the same bits as the native one.

The compilers come from Debian's packages (``scripts/install-test-tools``, part of the README's test
command); a test skips only where its compiler is absent, naming it.
"""

from __future__ import annotations

import shutil
import subprocess
import sysconfig
from pathlib import Path

import numpy as np
import pytest
import tomllib

from diffquat import _algebra, _lie

ROOT = Path(__file__).resolve().parents[1]
KERNELS = ROOT / "diffquat" / "_kernels.c"
HARNESS = Path(__file__).resolve().parent / "kernels_harness.c"
WARNINGS = ["-Wall", "-Wextra", "-Werror"]
INSTALL = "scripts/install-test-tools installs it"


def release_flags() -> list[str]:
    """The extension's compile flags, as pyproject.toml gives them to setuptools."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    (ext,) = config["tool"]["setuptools"]["ext-modules"]
    return list(ext["extra-compile-args"])


def series_defines() -> list[str]:
    """The series tables of the Jacobian and quaternion_plus kernels for the harness, from the core
    (``_lie.series_table``, ``_algebra.exp_series_table``), as diffquat/torch/_cpu.py passes them: C
    initialisers in float64's shortest round-trip form."""
    defines = []
    for name, dtype in (("F32", np.float32), ("F64", np.float64)):
        flat, terms = _lie.series_table(float(np.finfo(dtype).eps))
        defines += [
            f"-DSERIES_{name}={{{', '.join(map(repr, flat))}}}",
            f"-DTERMS_{name}={{{', '.join(map(str, terms))}}}",
            f"-DEXP_{name}={{{', '.join(map(repr, _algebra.exp_series_table(np, dtype)))}}}",
        ]
    return defines


def compiler(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"{name} not found ({INSTALL})")
    return path


def compile_check(cc: str, variants: tuple[str, ...] = ("", "-DDIFFQUAT_PORTABLE")) -> None:
    """The extension's translation unit compiled to an object file, as the release builds it and (on
    x86-64, where it differs) as the portable build of tests/test_kernels.py does; any warning fails."""
    python = f"-I{sysconfig.get_paths()['include']}"
    for variant in variants:
        command = [
            cc,
            "-c",
            "-fPIC",
            *release_flags(),
            *WARNINGS,
            *filter(None, [variant]),
            python,
            str(KERNELS),
        ]
        result = subprocess.run([*command, "-o", "/dev/null"], capture_output=True, text=True)
        assert result.returncode == 0 and not result.stderr, (command, result.stderr)


@pytest.mark.parametrize("name", ["gcc", "clang"])
def test_kernels_compile_without_warnings(name: str) -> None:
    compile_check(compiler(name))


def test_kernels_cross_compile_for_aarch64_and_give_the_same_bits(tmp_path: Path) -> None:
    """The whole extension compiles for aarch64 without a warning (against this machine's Python
    headers: a compile check, which is all a cross build of the module needs of them); then the
    kernels alone, in a standalone program, built natively and for aarch64 (static, run under qemu),
    print the same hash of every kernel's output bytes, in both dtypes and storage orders."""
    cross = compiler("aarch64-linux-gnu-gcc")
    compile_check(cross, variants=("",))  # the portable variant only drops x86 code
    flags = [
        *release_flags(),
        *WARNINGS,
        f'-DKERNELS_C="{KERNELS}"',
        *series_defines(),
        str(HARNESS),
        "-lm",
        "-lpthread",
    ]
    subprocess.run([compiler("gcc"), *flags, "-o", tmp_path / "native"], check=True)
    subprocess.run([cross, "-static", *flags, "-o", tmp_path / "aarch64"], check=True)
    native = subprocess.run([tmp_path / "native"], capture_output=True, text=True, check=True).stdout
    emulated = subprocess.run(
        [compiler("qemu-aarch64"), tmp_path / "aarch64"], capture_output=True, text=True, check=True
    ).stdout
    assert len(native.splitlines()) == 48
    assert emulated == native

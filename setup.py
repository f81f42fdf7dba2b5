"""Package discovery for the folder-per-subpackage layout.

`pyproject.toml`'s `[tool.setuptools.package-dir]` maps each top-level folder to `pallet6d.<name>`
(`pallet6d.runtime` -> `runtime/`, ...). setuptools' own discovery cannot add that prefix, so this file
finds every package under each mapped folder (a folder with `__init__.py`) and names it under its
mapping: a new subpackage ships in every install without a list to update. It also declares the one compiled
part, the runtime's kernels (`runtime/kernels.c`: refinement's ICP and fit scores, the levelled refinement's ray
hits and scores, the registration test's pair counts; loaded with ctypes by `pallet6d.runtime.kernels`): an
optional extension, so that an install without a C compiler still works (refinement then runs in numpy).
Everything else about the distribution is in `pyproject.toml`.
"""
from __future__ import annotations

import sys
from pathlib import Path

from setuptools import Extension, find_packages, setup

if sys.version_info >= (3, 11):
    import tomllib
else:  # a build requirement on Python 3.10 (pyproject.toml)
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent


def mapped_folders(root: Path = ROOT) -> dict[str, str]:
    """`[tool.setuptools.package-dir]`: import name -> folder (relative to `root`)."""
    with open(root / "pyproject.toml", "rb") as f:
        return dict(tomllib.load(f)["tool"]["setuptools"]["package-dir"])


def discover_packages(root: Path = ROOT) -> list[str]:
    """Every package under the mapped folders, named under its mapping, e.g. `pallet6d.runtime.cameras`."""
    packages = []
    for name, folder in mapped_folders(root).items():
        if not (root / folder / "__init__.py").is_file():
            raise SystemExit(f"setup.py: {folder}/ (mapped to {name}) has no __init__.py")
        packages.append(name)
        packages += [f"{name}.{sub}" for sub in find_packages(str(root / folder))]
    return sorted(packages)


# Plain C, no Python C API. -ffp-contract=off: no fused multiply-adds, so the kernel's float arithmetic rounds as
# the numpy path's does on every machine; no floating-point exceptions or errno (nothing reads them), which lets
# the compiler vectorise the comparisons and inline sqrt.
KERNELS = Extension("pallet6d.runtime._kernels", sources=["runtime/kernels.c"], libraries=["m", "pthread"],
                    optional=True,
                    extra_compile_args=["-O3", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno"])


if __name__ == "__main__":
    setup(packages=discover_packages(), ext_modules=[KERNELS])

"""Check the built wheels against the source tree: every module and data file is in, nothing else is.

    python .ci/wheel_contents.py DIST_DIR [--root REPO] [--max-runtime-mb 2]

The runtime wheel (`pallet6d-*.whl`) must hold every file under each folder that `pyproject.toml` maps to a
`pallet6d.<name>` package (`runtime/` -> `pallet6d/runtime/`, ...; `__pycache__` aside; C sources are compiled,
not shipped), each C extension that setup.py declares, compiled (`pallet6d/runtime/_kernels.*.so`), and nothing
else besides its `.dist-info`: no tests, benchmark results, training data or model bundles, and it must stay under
`--max-runtime-mb`. The models wheel (`pallet6d_models-*.whl`) must hold `models/__init__.py` and every file
of each bundle folder under `models/` (a folder with a manifest.json), and nothing else. Prints each wheel's
size and file count; exits 1 listing what is missing or unexpected.
"""
from __future__ import annotations

import argparse
import ast
import sys
import zipfile
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

RUNTIME_WHEEL = "pallet6d-*.whl"
MODELS_WHEEL = "pallet6d_models-*.whl"
MODELS_PACKAGE = "pallet6d_models"
# C sources are built into extension modules; built modules in the tree (an editable install's) are not sources
COMPILED_SUFFIXES = (".c", ".so", ".pyd")


def _files_under(folder: Path) -> list[Path]:
    """Files below `folder`, relative to it, without bytecode caches and hidden files."""
    return sorted(p.relative_to(folder) for p in folder.rglob("*")
                  if p.is_file() and "__pycache__" not in p.parts and not p.name.startswith(".")
                  and p.suffix != ".pyc" and p.suffix not in COMPILED_SUFFIXES)


def expected_runtime_files(root: Path) -> set[str]:
    """Wheel paths of every file in the folders mapped by `[tool.setuptools.package-dir]`."""
    with open(root / "pyproject.toml", "rb") as f:
        package_dir = tomllib.load(f)["tool"]["setuptools"]["package-dir"]
    return {f"{name.replace('.', '/')}/{rel.as_posix()}" for name, folder in package_dir.items()
            for rel in _files_under(root / folder)}


def extension_modules(root: Path) -> list[str]:
    """Import names of the C extensions setup.py declares (`Extension("pallet6d.runtime._kernels", ...)`),
    read from its source without running it."""
    names = []
    for node in ast.walk(ast.parse((root / "setup.py").read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Extension" and node.args \
                and isinstance(node.args[0], ast.Constant):
            names.append(str(node.args[0].value))
    return sorted(names)


def compiled_files(extensions: list[str], actual: set[str]) -> tuple[set[str], list[str]]:
    """The wheel's built extension files (`name.<tag>.so` or `.pyd`), and a problem for each extension that has
    none or several."""
    found, problems = set(), []
    for name in extensions:
        stem = name.replace(".", "/") + "."
        files = {f for f in actual if f.startswith(stem) and f.endswith((".so", ".pyd")) and "/" not in f[len(stem):]}
        if len(files) != 1:
            problems.append(f"missing compiled {name} (a C compiler is needed to build the wheel)" if not files
                            else f"several builds of {name}: {sorted(files)}")
        found |= files
    return found, problems


def expected_models_files(root: Path) -> set[str]:
    """Wheel paths of `models/__init__.py` and every file of each bundle folder under `models/`."""
    models = root / "models"
    bundles = [d for d in sorted(models.iterdir()) if (d / "manifest.json").is_file()]
    if not bundles:
        raise SystemExit(f"{models}: no bundle folder (a folder with manifest.json)")
    return {f"{MODELS_PACKAGE}/__init__.py"} | {f"{MODELS_PACKAGE}/{d.name}/{rel.as_posix()}" for d in bundles
                                                for rel in _files_under(d)}


def wheel_files(wheel: Path) -> set[str]:
    """The files of a wheel, without its `.dist-info` metadata."""
    with zipfile.ZipFile(wheel) as z:
        return {n for n in z.namelist() if not n.endswith("/") and ".dist-info/" not in n}


def compare(label: str, expected: set[str], actual: set[str]) -> list[str]:
    """Problems: each expected file the wheel lacks, each file it holds that is not expected."""
    return ([f"{label}: missing {p}" for p in sorted(expected - actual)]
            + [f"{label}: unexpected {p}" for p in sorted(actual - expected)])


def _one(dist: Path, pattern: str) -> Path:
    found = sorted(dist.glob(pattern))
    if len(found) != 1:
        raise SystemExit(f"{dist}: expected one {pattern}, found {[p.name for p in found] or 'none'}")
    return found[0]


def check(dist: Path, root: Path, max_runtime_mb: float) -> list[str]:
    """Every problem with the two wheels in `dist`; prints a summary of each."""
    runtime, models = _one(dist, RUNTIME_WHEEL), _one(dist, MODELS_WHEEL)
    runtime_files, models_files = wheel_files(runtime), wheel_files(models)
    compiled, problems = compiled_files(extension_modules(root), runtime_files)
    problems = [f"{runtime.name}: {p}" for p in problems]
    problems += compare(runtime.name, expected_runtime_files(root), runtime_files - compiled)
    problems += compare(models.name, expected_models_files(root), models_files)
    runtime_mb = runtime.stat().st_size / 1e6
    if runtime_mb > max_runtime_mb:
        problems.append(f"{runtime.name}: {runtime_mb:.2f} MB, over the {max_runtime_mb} MB limit for the runtime")
    for wheel, files in ((runtime, runtime_files), (models, models_files)):
        folders = sorted({"/".join(f.split("/")[:2]) for f in files})
        print(f"{wheel.name}: {wheel.stat().st_size / 1e6:.2f} MB, {len(files)} files in {', '.join(folders)}")
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dist", type=Path, help="folder holding the built wheels")
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1], help="repository root")
    ap.add_argument("--max-runtime-mb", type=float, default=2.0, help="size limit of the runtime wheel (MB)")
    args = ap.parse_args(argv)
    problems = check(args.dist, args.root, args.max_runtime_mb)
    for p in problems:
        print(f"  - {p}", file=sys.stderr)
    if problems:
        print(f"wheel contents: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    print("wheel contents: OK")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Packaging: setup.py's package discovery and the wheel contents check that `make wheels` runs.

Building and installing the real wheels is `make wheel-check`'s job (CI); these tests check the two pieces of
logic that decide what a wheel holds, on small synthetic trees, and the shipped bundle against the models
package's data patterns.
"""
from __future__ import annotations

import fnmatch
import importlib.util
import re
import sys
import zipfile
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


pytest.importorskip("setuptools")
setup_py = _load("pallet6d_setup_py", REPO / "setup.py")          # its setup() runs only as __main__
wheel_contents = _load("pallet6d_wheel_contents", REPO / ".ci" / "wheel_contents.py")


def _tree(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root


PYPROJECT = '[tool.setuptools.package-dir]\n"pallet6d.a" = "a"\n"pallet6d.b" = "b"\n'


@pytest.fixture
def source(tmp_path):
    """A project with two mapped folders, a nested subpackage, a data file, a folder without __init__.py, and a
    C extension (its source and an editable install's build of it in the tree)."""
    return _tree(tmp_path / "src", {
        "pyproject.toml": PYPROJECT,
        "setup.py": 'from setuptools import Extension\nK = Extension("pallet6d.a._k", sources=["a/k.c"])\n',
        "a/k.c": "", "a/_k.cpython-311-x86_64-linux-gnu.so": "",
        "a/__init__.py": "", "a/m.py": "", "a/py.typed": "",
        "a/sub/__init__.py": "", "a/sub/deep/__init__.py": "", "a/sub/deep/x.py": "",
        "a/scripts/tool.py": "",                      # not a package: setuptools ships no module here
        "a/__pycache__/m.cpython-311.pyc": "",
        "b/__init__.py": "",
        "tests/test_a.py": "",
    })


def _wheel(path: Path, files: list[str]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as z:
        for f in files:
            z.writestr(f, "")
        z.writestr(f"{path.name.split('-')[0]}-0.1.0.dist-info/RECORD", "")
    return path


def test_discovery_finds_nested_subpackages_under_their_mapping(source):
    assert setup_py.discover_packages(source) == ["pallet6d.a", "pallet6d.a.sub", "pallet6d.a.sub.deep",
                                                  "pallet6d.b"]


def test_discovery_refuses_a_mapped_folder_without_init(source):
    (source / "b" / "__init__.py").unlink()
    with pytest.raises(SystemExit, match=r"b/ \(mapped to pallet6d.b\) has no __init__.py"):
        setup_py.discover_packages(source)


def test_discovery_lists_every_package_of_the_repository():
    packages = setup_py.discover_packages()
    mapping = setup_py.mapped_folders()
    on_disk = {f"{name}.{'.'.join(init.parent.relative_to(REPO / folder).parts)}".rstrip(".")
               for name, folder in mapping.items() for init in (REPO / folder).rglob("__init__.py")}
    assert set(packages) == on_disk
    assert "pallet6d.runtime.cameras" in packages


def test_expected_runtime_files_skip_caches_but_keep_data(source):
    assert wheel_contents.expected_runtime_files(source) == {
        "pallet6d/a/__init__.py", "pallet6d/a/m.py", "pallet6d/a/py.typed", "pallet6d/a/sub/__init__.py",
        "pallet6d/a/sub/deep/__init__.py", "pallet6d/a/sub/deep/x.py", "pallet6d/a/scripts/tool.py",
        "pallet6d/b/__init__.py"}


@pytest.mark.parametrize("drop, add, problems", [
    (None, None, []),
    ("pallet6d/a/sub/deep/x.py", None, ["missing pallet6d/a/sub/deep/x.py"]),
    ("pallet6d/a/py.typed", None, ["missing pallet6d/a/py.typed"]),
    (None, "tests/test_a.py", ["unexpected tests/test_a.py"]),
    (None, "pallet6d_models/epal-default/fusion.onnx", ["unexpected pallet6d_models/epal-default/fusion.onnx"]),
], ids=["complete", "module-missing", "data-file-missing", "tests-inside", "bundle-inside"])
def test_compare_names_missing_and_unexpected_files(source, tmp_path, drop, add, problems):
    expected = wheel_contents.expected_runtime_files(source)
    files = sorted((expected - {drop}) | ({add} if add else set()))
    wheel = _wheel(tmp_path / "dist" / "pallet6d-0.1.0-py3-none-any.whl", files)
    found = wheel_contents.compare("w", expected, wheel_contents.wheel_files(wheel))
    assert found == [f"w: {p}" for p in problems]


def test_check_covers_both_wheels_and_the_size_limit(source, tmp_path, capsys):
    _tree(source, {"models/__init__.py": "", "models/pyproject.toml": "",
                   "models/m1/manifest.json": "{}", "models/m1/g.onnx": "", "models/notes/readme.md": ""})
    dist = tmp_path / "dist"
    _wheel(dist / "pallet6d-0.1.0-py3-none-any.whl", sorted(wheel_contents.expected_runtime_files(source))
           + ["pallet6d/a/_k.cpython-310-x86_64-linux-gnu.so"])
    _wheel(dist / "pallet6d_models-0.1.0-py3-none-any.whl", ["pallet6d_models/__init__.py",
                                                             "pallet6d_models/m1/manifest.json"])
    problems = wheel_contents.check(dist, source, max_runtime_mb=1e-6)
    assert problems[0] == "pallet6d_models-0.1.0-py3-none-any.whl: missing pallet6d_models/m1/g.onnx"
    assert "over the 1e-06 MB limit" in problems[1] and len(problems) == 2
    assert "pallet6d-0.1.0-py3-none-any.whl" in capsys.readouterr().out


def test_extensions_are_read_from_setup_py():
    assert wheel_contents.extension_modules(REPO) == ["pallet6d.runtime._kernels"]


@pytest.mark.parametrize("files, problems", [
    (["pallet6d/a/_k.cpython-311-x86_64-linux-gnu.so"], []),
    (["pallet6d/a/_k.pyd"], []),
    ([], ["missing compiled pallet6d.a._k (a C compiler is needed to build the wheel)"]),
    (["pallet6d/a/_k/x.so"], ["missing compiled pallet6d.a._k (a C compiler is needed to build the wheel)"]),
    (["pallet6d/a/_k.abi3.so", "pallet6d/a/_k.cpython-311-x86_64-linux-gnu.so"], ["several builds of pallet6d.a._k"]),
], ids=["linux", "windows", "missing", "not-the-module", "twice"])
def test_compiled_files_want_one_build_of_each_extension(files, problems):
    found, got = wheel_contents.compiled_files(["pallet6d.a._k"], set(files) | {"pallet6d/a/m.py"})
    assert [g.split(":")[0] for g in got] == problems
    assert found == (set(files) if not problems else set(files) - {"pallet6d/a/_k/x.so"})


def test_check_wants_the_compiled_extension(source, tmp_path):
    _tree(source, {"models/__init__.py": "", "models/m1/manifest.json": "{}"})
    dist = tmp_path / "dist"
    _wheel(dist / "pallet6d-0.1.0-py3-none-any.whl", sorted(wheel_contents.expected_runtime_files(source)))
    _wheel(dist / "pallet6d_models-0.1.0-py3-none-any.whl", ["pallet6d_models/__init__.py",
                                                             "pallet6d_models/m1/manifest.json"])
    assert wheel_contents.check(dist, source, max_runtime_mb=2.0) == [
        "pallet6d-0.1.0-py3-none-any.whl: missing compiled pallet6d.a._k (a C compiler is needed to build the wheel)"]


def test_check_wants_exactly_one_wheel_of_each(source, tmp_path):
    _wheel(tmp_path / "dist" / "pallet6d-0.1.0-py3-none-any.whl", [])
    with pytest.raises(SystemExit, match=r"expected one pallet6d_models-\*.whl, found none"):
        wheel_contents.check(tmp_path / "dist", source, 2.0)


def test_models_package_data_covers_every_shipped_bundle_file():
    with open(REPO / "models" / "pyproject.toml", "rb") as f:
        patterns = tomllib.load(f)["tool"]["setuptools"]["package-data"]["pallet6d_models"]
    expected = wheel_contents.expected_models_files(REPO)
    bundle_files = [p.removeprefix("pallet6d_models/") for p in expected if p.count("/") == 2]
    assert bundle_files, "no bundle under models/"
    assert [f for f in bundle_files if not any(fnmatch.fnmatch(f, pat) for pat in patterns)] == []


def test_dockerfile_runs_the_checks_that_make_wheel_check_runs():
    """CI cannot run Docker: the image's recipe is checked by keeping its steps those of `make wheel-check`."""
    docker = (REPO / "Dockerfile").read_text()
    make = (REPO / "Makefile").read_text()
    for step in ("pip wheel", "--no-deps", " . ./models", ".ci/wheel_contents.py", "smoke-installed"):
        assert step in docker and step in make, step
    assert re.search(r"^USER (?!root\b)\w+", docker, re.M), "the image must not run as root"
    assert re.search(r"^HEALTHCHECK ", docker, re.M)
    assert not re.search(r"^COPY .*\b(tests|benchmarks|docs)\b", docker, re.M)
    assert "export" not in re.search(r"ARG CAMERAS=(\S*)", docker).group(1)

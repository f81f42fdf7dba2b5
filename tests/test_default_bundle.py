"""The default bundle (`--bundle` left out): $PALLET6D_BUNDLE, then the installed pallet6d-models, then
./models/epal-default; a clear error naming what to install when none is there."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

from pallet6d.runtime import cli
from pallet6d.runtime.bundle import BundleError
from pallet6d.runtime.default_bundle import (BUNDLE_ENV, CHECKOUT_BUNDLE, MODELS_PACKAGE, BundleNotFoundError,
                                             default_bundle)

REPO = Path(__file__).resolve().parents[1]


def _bundle_folder(path: Path) -> Path:
    """A folder that looks like a bundle to the locator (it only looks for manifest.json)."""
    path.mkdir(parents=True)
    (path / "manifest.json").write_text(json.dumps({"name": path.name}))
    return path


@pytest.fixture
def nowhere(tmp_path, monkeypatch):
    """No default bundle anywhere: an empty working directory, no $PALLET6D_BUNDLE, pallet6d-models not
    importable. Returns the working directory."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.delenv(BUNDLE_ENV, raising=False)
    monkeypatch.setitem(sys.modules, MODELS_PACKAGE, None)   # import raises ModuleNotFoundError
    return work


@pytest.fixture
def installed_models(nowhere, tmp_path, monkeypatch):
    """`nowhere`, but with the shipped models/__init__.py installed as `pallet6d_models` on sys.path, without a
    bundle folder yet. Returns the package folder."""
    package = tmp_path / "site-packages" / MODELS_PACKAGE
    package.mkdir(parents=True)
    shutil.copy(REPO / "models" / "__init__.py", package / "__init__.py")
    monkeypatch.delitem(sys.modules, MODELS_PACKAGE)   # lift `nowhere`'s block
    monkeypatch.syspath_prepend(str(package.parent))
    return package


def test_nothing_found_says_what_to_install(nowhere):
    with pytest.raises(BundleNotFoundError, match=r"--bundle DIR.*PALLET6D_BUNDLE.*pip install pallet6d_models"):
        default_bundle(environ={})


def test_not_found_is_a_bundle_error():
    assert issubclass(BundleNotFoundError, BundleError)


def test_checkout_bundle_from_the_working_directory(nowhere):
    _bundle_folder(nowhere / CHECKOUT_BUNDLE)
    assert default_bundle(environ={}) == CHECKOUT_BUNDLE


def test_environment_variable_comes_first(nowhere, tmp_path, installed_models):
    _bundle_folder(nowhere / CHECKOUT_BUNDLE)
    _bundle_folder(installed_models / "epal-default")
    chosen = _bundle_folder(tmp_path / "chosen")
    assert default_bundle(environ={BUNDLE_ENV: str(chosen)}) == chosen


@pytest.mark.parametrize("what", ["missing", "empty-folder", "a-file"])
def test_environment_variable_that_is_not_a_bundle_is_an_error(nowhere, tmp_path, what):
    _bundle_folder(nowhere / CHECKOUT_BUNDLE)   # never a silent fallback to another model
    path = tmp_path / "configured"
    if what == "empty-folder":
        path.mkdir()
    elif what == "a-file":
        path.write_text("x")
    with pytest.raises(BundleNotFoundError, match=f"\\${BUNDLE_ENV}=.*configured is not a model bundle"):
        default_bundle(environ={BUNDLE_ENV: str(path)})


def test_empty_environment_variable_is_unset(nowhere):
    _bundle_folder(nowhere / CHECKOUT_BUNDLE)
    assert default_bundle(environ={BUNDLE_ENV: ""}) == CHECKOUT_BUNDLE


def test_installed_models_package_comes_before_the_checkout(nowhere, installed_models):
    _bundle_folder(nowhere / CHECKOUT_BUNDLE)
    bundle = _bundle_folder(installed_models / "epal-default")
    assert default_bundle(environ={}) == bundle.resolve()


def test_installed_models_package_without_its_bundle_is_an_error(nowhere, installed_models):
    _bundle_folder(nowhere / CHECKOUT_BUNDLE)
    with pytest.raises(BundleNotFoundError, match="installed pallet6d-models has no bundle.*reinstall"):
        default_bundle(environ={})


def test_run_without_a_bundle_exits_2_with_the_hint(nowhere, capsys):
    assert cli.main(["run", "--frame", "camera", "--source", "bop:does-not-matter"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pallet6d run: no model bundle given") and "pip install pallet6d_models" in err


def test_eval_without_a_bundle_exits_2_with_the_hint(nowhere, capsys):
    assert cli.main(["eval", "--data", "does-not-matter"]) == 2
    assert "pallet6d eval: no model bundle given" in capsys.readouterr().err


def test_bundle_check_without_a_path_and_no_default_fails(nowhere, capsys):
    assert cli.main(["bundle", "check", "--no-run"]) == 1
    assert "no model bundle given" in capsys.readouterr().err


def test_bundle_check_without_a_path_checks_the_default(nowhere, monkeypatch, capsys):
    monkeypatch.setenv(BUNDLE_ENV, str(REPO / "models" / "epal-default"))
    assert cli.main(["bundle", "check", "--no-run"]) == 0
    assert capsys.readouterr().out.strip() == f"bundle {REPO / 'models' / 'epal-default'}: OK"


def test_run_uses_the_default_bundle(nowhere, monkeypatch, bundle_dir, sim_bop_dataset, capsys):
    monkeypatch.setenv(BUNDLE_ENV, str(bundle_dir))
    assert cli.main(["run", "--frame", "camera", "--source", f"bop:{sim_bop_dataset}", "--max-frames", "1", "--max-failures", "1"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [x["frame"] for x in lines if "frame" in x] == [0]
    assert all("error" not in x for x in lines)

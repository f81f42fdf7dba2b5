"""Where the default model bundle is when a command is given no `--bundle`.

In order, the first that applies:

1. `$PALLET6D_BUNDLE`: a bundle folder chosen by the deployment (a path that is not a bundle is an
   error, never skipped: a configured model must not be silently replaced by another);
2. the `pallet6d-models` distribution, when installed (`pip install pallet6d_models-*.whl`): its
   `epal-default` folder;
3. `models/epal-default` under the working directory: a checkout of the repository.

Nothing found raises `BundleNotFoundError`, whose message says what to install.
"""
from __future__ import annotations

import importlib
import os
from pathlib import Path

from .bundle import MANIFEST, BundleError

__all__ = ["BUNDLE_ENV", "CHECKOUT_BUNDLE", "MODELS_PACKAGE", "BundleNotFoundError", "default_bundle"]

BUNDLE_ENV = "PALLET6D_BUNDLE"
MODELS_PACKAGE = "pallet6d_models"
CHECKOUT_BUNDLE = Path("models") / "epal-default"


class BundleNotFoundError(BundleError):
    """No bundle was given and no default bundle is installed or configured."""


def default_bundle(environ: dict[str, str] | None = None) -> Path:
    """The default bundle folder (see the module docstring for the order).

    :param environ: the environment to read `PALLET6D_BUNDLE` from (default: `os.environ`).
    :return: a folder that holds `manifest.json` (its contents are checked when the bundle is loaded).
    :raises BundleNotFoundError: `PALLET6D_BUNDLE` names no bundle, the installed `pallet6d-models` lacks its
        bundle, or no default bundle exists.
    """
    env = os.environ if environ is None else environ
    configured = env.get(BUNDLE_ENV, "")
    if configured:
        path = Path(configured).expanduser()
        if not (path / MANIFEST).is_file():
            raise BundleNotFoundError(f"${BUNDLE_ENV}={configured} is not a model bundle folder (no {MANIFEST} "
                                      f"in it): point it at a bundle folder or unset it")
        return path
    try:
        models = importlib.import_module(MODELS_PACKAGE)
    except ModuleNotFoundError as exc:
        if exc.name != MODELS_PACKAGE:
            raise
    else:
        path = models.bundle_path()
        if not (path / MANIFEST).is_file():
            raise BundleNotFoundError(f"the installed pallet6d-models has no bundle at {path}: reinstall it "
                                      f"(pip install --force-reinstall pallet6d_models-*.whl)")
        return path
    if (CHECKOUT_BUNDLE / MANIFEST).is_file():
        return CHECKOUT_BUNDLE
    raise BundleNotFoundError(
        f"no model bundle given and no default one found: name a bundle folder (--bundle DIR), set "
        f"${BUNDLE_ENV}=DIR, or install the default model: pip install pallet6d_models-*.whl (built from the "
        f"repository's models/ folder with `make wheels`; see docs/packaging.md)")

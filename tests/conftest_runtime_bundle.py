"""Shared fixture helper: a random-init `tiny` bundle from the exporter (session scope, built once).

`PALLET6D_TEST_BUNDLE=/path/to/bundle` uses an existing bundle instead (e.g. while the exporter is busy).
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest


def make_tiny_bundle(tmp_path_factory) -> Path:
    env = os.environ.get("PALLET6D_TEST_BUNDLE")
    if env:
        return Path(env)
    pytest.importorskip("torch")
    try:
        from pallet6d.export import cli as export_cli  # noqa: F401
    except ModuleNotFoundError:
        pytest.skip("pallet6d export is not available in this checkout: no random-init bundle to test on")
    from pallet6d.runtime.cli import main
    out = tmp_path_factory.mktemp("bundle") / "tiny"
    rc = main(["export", "--config", "tiny", "--random-init", "--out", str(out)])
    assert rc == 0, "pallet6d export --config tiny --random-init failed"
    return out

"""The shipped pallet6d model bundles as an installable package (`pip install pallet6d-models`).

Each bundle is a folder of this package (`epal-default/`: manifest.json, the ONNX graphs, the pallet
model points). The runtime finds the default one through `bundle_path()` when a command gets no
`--bundle` (see `pallet6d.runtime.default_bundle`); this package holds data only and needs nothing else.
"""
from __future__ import annotations

from pathlib import Path

DEFAULT_BUNDLE = "epal-default"


def bundle_path(name: str = DEFAULT_BUNDLE) -> Path:
    """The installed folder of bundle `name` (it holds manifest.json); it may be missing in a broken install."""
    return Path(__file__).resolve().parent / name

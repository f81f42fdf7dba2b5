"""Checking a command's output folder before any work starts, so a bad `--out` is one line and exit status 2."""
from __future__ import annotations

import tempfile
from pathlib import Path

__all__ = ["writable_folder"]


def writable_folder(out: Path) -> str | None:
    """Create `out` (and its parents) if needed and try writing a file in it; the reason it cannot hold the
    command's files, or None when it can."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        return f"--out {out} exists and is not a folder"
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        return f"--out {out} is not a writable folder: {exc.strerror or exc}"
    return None

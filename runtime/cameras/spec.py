"""`open_source(spec)`: one string names any frame source (CLI flags, config files)."""
from __future__ import annotations

from pathlib import Path

from .base import FrameSource
from .errors import SourceSpecError

__all__ = ["open_source", "parse_source_spec", "SOURCE_KINDS"]

# kind -> (argument, required?)
SOURCE_KINDS: dict[str, tuple[str, bool]] = {
    "realsense": ("SERIAL", False),
    "oakd": ("MXID", False),
    "bag": ("FILE", True),
    "replay": ("DIR", True),
    "bop": ("DIR", True),
}

_USAGE = "expected one of: realsense[:SERIAL], oakd[:MXID], bag:FILE, replay:DIR, bop:DIR"


def parse_source_spec(spec: str) -> tuple[str, str | None]:
    """Split a source spec into (kind, argument or None).

    :raises SourceSpecError: unknown kind, missing or empty argument.
    """
    if not isinstance(spec, str):
        raise TypeError(f"source spec must be a string, got {type(spec).__name__}")
    kind, sep, arg = spec.strip().partition(":")
    kind = kind.lower()
    if kind not in SOURCE_KINDS:
        raise SourceSpecError(f"unknown source {spec!r}: {_USAGE}")
    name, required = SOURCE_KINDS[kind]
    arg = arg.strip()
    if required and not arg:
        raise SourceSpecError(f"source {spec!r} needs a {name}: {kind}:{name}")
    if sep and not arg:
        raise SourceSpecError(f"source {spec!r} has an empty {name}; write '{kind}' or '{kind}:{name}'")
    return kind, (arg or None)


def open_source(spec: str, **options) -> FrameSource:
    """Create (not start) the frame source a spec names; `options` go to its constructor.

    >>> with open_source("replay:/data/run1", realtime=True) as cam:
    ...     for frame in cam: ...
    """
    kind, arg = parse_source_spec(spec)
    if kind == "replay":
        from .replay import ReplaySource
        return ReplaySource(Path(arg), **options)
    if kind == "bop":
        from .bop_source import BopSource
        return BopSource(Path(arg), **options)
    if kind == "bag":
        from .realsense import RealSenseCamera
        return RealSenseCamera(bag_path=Path(arg), **options)
    if kind == "realsense":
        from .realsense import RealSenseCamera
        return RealSenseCamera(serial=arg, **options)
    from .oakd import OakDCamera
    return OakDCamera(mxid=arg, **options)

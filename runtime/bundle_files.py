"""Safe access to a bundle's files: names confined to the bundle folder, regular files of bounded size,
sha256, and a cheap structural check that a graph is an ONNX model (without onnxruntime).
"""
from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path
from typing import Any

from .manifest_fields import BundleError, FieldError, relative_name

__all__ = ["MAX_FILE_BYTES", "MAX_JSON_BYTES", "confined_file", "sha256_file", "check_onnx_file", "read_json"]

# larger than any graph of the configs (paper fp32: ~0.2 GB), small enough to refuse a device or a runaway file
MAX_FILE_BYTES = 2 << 30
MAX_JSON_BYTES = 16 << 20


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def confined_file(root: Path, rel: str, where: str, max_bytes: int | None = None) -> Path:
    """The regular file `rel` names inside the bundle folder `root` (resolved).

    :param where: the manifest and field that name it, for the message (e.g. "m.json: field 'pose.file'").
    :raises BundleError: an absolute name, a `..` part, a link that leads out of the folder, a missing file,
        something that is not a regular file, or a file larger than `max_bytes` (default MAX_FILE_BYTES).
    """
    try:
        relative_name("", rel)
    except FieldError as exc:
        raise BundleError(f"{where} {exc.msg}") from None
    base = root.resolve()
    path = (base / rel).resolve()
    if base not in path.parents:
        raise BundleError(f"{where} names {rel!r}, which leads outside the bundle folder (to {path})")
    try:
        st = os.stat(path)
    except OSError:
        raise BundleError(f"{where} names {rel!r}, which is not in the bundle ({path} does not exist)") from None
    if not stat.S_ISREG(st.st_mode):
        raise BundleError(f"{where} names {rel!r}, which is not a regular file")
    max_bytes = MAX_FILE_BYTES if max_bytes is None else max_bytes
    if st.st_size > max_bytes:
        raise BundleError(f"{where} names {rel!r}, {st.st_size} bytes: more than the limit of {max_bytes}")
    return path


def _varint(fh) -> int | None:
    """Read a protobuf varint; None at a clean end of file."""
    value, shift = 0, 0
    while True:
        b = fh.read(1)
        if not b:
            if shift:
                raise ValueError("truncated varint")
            return None
        value |= (b[0] & 0x7F) << shift
        if not b[0] & 0x80:
            return value
        shift += 7
        if shift > 63:
            raise ValueError("varint longer than 10 bytes")


def check_onnx_file(path: Path, label: str) -> None:
    """Walk the top-level protobuf fields of an ONNX file: every field well formed and inside the file, and
    the model's `ir_version` (1) and `graph` (7) present. Catches garbage, truncation and another format.

    :raises BundleError: naming `label` (e.g. "detector (detector.onnx)").
    """
    size = path.stat().st_size
    seen: set[int] = set()
    try:
        with open(path, "rb") as fh:
            while (key := _varint(fh)) is not None:
                number, wire = key >> 3, key & 7
                if number == 0:
                    raise ValueError("field number 0")
                if wire == 0:
                    if _varint(fh) is None:
                        raise ValueError("truncated varint")
                elif wire in (1, 5):
                    n = 8 if wire == 1 else 4
                    if fh.seek(n, os.SEEK_CUR) > size:
                        raise ValueError("truncated fixed-size field")
                elif wire == 2:
                    n = _varint(fh)
                    if n is None or fh.seek(n, os.SEEK_CUR) > size:
                        raise ValueError(f"field {number} runs past the end of the file")
                else:
                    raise ValueError(f"wire type {wire} of field {number} is not used by ONNX")
                seen.add(number)
    except ValueError as exc:
        raise BundleError(f"{label}: not a valid ONNX model ({exc}): the file is damaged or of another format") \
            from None
    missing = [name for number, name in ((1, "ir_version"), (7, "graph")) if number not in seen]
    if missing:
        raise BundleError(f"{label}: not a valid ONNX model (no {' or '.join(missing)}): the file is damaged "
                          "or of another format")


def read_json(path: Path, what: str) -> Any:
    """A JSON file of at most MAX_JSON_BYTES. :raises BundleError: unreadable, too large or not JSON."""
    try:
        if path.stat().st_size > MAX_JSON_BYTES:
            raise BundleError(f"{path}: larger than {MAX_JSON_BYTES} bytes; not a {what}")
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BundleError(f"{path}: not valid JSON ({exc})") from None
    except OSError as exc:
        raise BundleError(f"{path}: cannot read it ({exc.strerror})") from None

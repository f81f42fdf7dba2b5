"""Reading and checking manifest fields: typed access to JSON objects whose errors name the file and the field,
and the value checks the schema's dataclasses apply (`manifest.py`, `pallet_type.py`)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["BundleError", "FieldError", "Fields", "positive", "nonempty_name", "relative_name", "graph_file",
           "constant", "rgb_norm", "frozen_array"]


class BundleError(ValueError):
    """A bundle that cannot be used: the message names the bundle file and the field or graph at fault."""


class FieldError(BundleError):
    """A field with a value that means nothing usable; `Fields.build` adds the file and section to it."""

    def __init__(self, key: str, msg: str) -> None:
        super().__init__(f"field '{key}' {msg}")
        self.key, self.msg = key, msg


# -- value checks (raise FieldError naming the key) ------------------------------------------------------

def positive(key: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise FieldError(key, f"must be a finite number > 0, got {value!r}")


def nonempty_name(key: str, value: str) -> None:
    if not value.strip():
        raise FieldError(key, "must be a non-empty name")


def relative_name(key: str, rel: str) -> None:
    """`rel` must name a file inside the bundle folder: relative, '/'-separated, without '.', '..' or '//'."""
    parts = rel.split("/")
    if not rel or "\\" in rel or rel.startswith(("/", "~")) or (len(rel) > 1 and rel[1] == ":") \
            or any(part in ("", ".", "..") for part in parts):
        raise FieldError(key, f"must be a relative file name inside the bundle folder (no absolute path, '..', "
                              f"'.' or '//'), got {rel!r}")


def graph_file(key: str, value: str | None) -> None:
    if value is None:
        return
    relative_name(key, value)
    if not value.endswith(".onnx"):
        raise FieldError(key, f"must name an .onnx file, got {value!r}")


def constant(key: str, value: str, expected: str) -> None:
    if value != expected:
        raise FieldError(key, f"must be {expected!r} (the only convention this runtime knows), got {value!r}")


def rgb_norm(pixel_scale: float, rgb_std: tuple[float, ...]) -> None:
    positive("pixel_scale", pixel_scale)
    for v in rgb_std:
        positive("rgb_std", v)


def frozen_array(a: Any, dtype=np.float64) -> np.ndarray:
    arr = np.array(a, dtype=dtype)
    arr.setflags(write=False)
    return arr


# -- JSON reading with the file and field named ---------------------------------------------------------

class Fields:
    """Typed access to one JSON object; errors name `source: field 'where.key'`; `build` refuses unknown keys."""

    def __init__(self, data: Any, where: str, source: str, version: int = 2) -> None:
        if not isinstance(data, dict):
            raise BundleError(f"{source}: field '{where}' must be an object, got {type(data).__name__}")
        self.data, self.where, self.source, self.version = data, where, source, version
        self.used: set[str] = set()

    def path(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def fail(self, key: str, msg: str) -> BundleError:
        return BundleError(f"{self.source}: field '{self.path(key)}' {msg}")

    def get(self, key: str, types: type | tuple, default: Any = ...) -> Any:
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise self.fail(key, "is missing")
            return default
        value = self.data[key]
        if value is None and default is None:
            return None
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in _as_tuple(types)):
            raise self.fail(key, f"must be {_type_names(types)}, got {value!r}")
        return value

    def str(self, key: str, default: Any = ...) -> str:
        return self.get(key, str, default)

    def num(self, key: str) -> float:
        value = self.get(key, (int, float))
        if not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        return float(value)

    def int(self, key: str) -> int:
        return self.get(key, int)

    def nums(self, key: str, n: int) -> tuple[float, ...]:
        value = self.get(key, list)
        if len(value) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                      and math.isfinite(v) for v in value):
            raise self.fail(key, f"must be a list of {n} finite numbers, got {value!r}")
        return tuple(float(v) for v in value)

    def ints(self, key: str, n: int) -> tuple[int, ...]:
        value = self.get(key, list)
        if len(value) != n or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            raise self.fail(key, f"must be a list of {n} integers, got {value!r}")
        return tuple(value)

    def int_rows(self, key: str, n: int, default: Any = ...) -> tuple[tuple[int, ...], ...] | None:
        """A list of lists of `n` integers each (e.g. [[H, W], ...]); `default` when absent or null."""
        value = self.get(key, list, default)
        if value is None:
            return None
        if not all(isinstance(row, list) and len(row) == n and all(isinstance(v, int) and not isinstance(v, bool)
                                                                   for v in row) for row in value):
            raise self.fail(key, f"must be a list of lists of {n} integers, got {value!r}")
        return tuple(tuple(row) for row in value)

    def array(self, key: str, default: Any = ...) -> np.ndarray | None:
        value = self.get(key, list, default)
        if value is None:
            return None
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(key, "must be a nested list of numbers of one shape") from None
        if not np.all(np.isfinite(arr)):
            raise self.fail(key, "must hold finite numbers only")
        return arr

    def names(self, key: str) -> tuple[str, ...]:
        value = self.get(key, list)
        if not all(isinstance(v, str) for v in value):
            raise self.fail(key, f"must be a list of names, got {value!r}")
        return tuple(value)

    def constant(self, key: str, expected: str) -> None:
        """A string field that must hold `expected`: a convention of the graphs this runtime implements."""
        value = self.str(key)
        if value != expected:
            raise self.fail(key, f"must be {expected!r} (the only convention this runtime knows), got {value!r}")

    def section(self, key: str) -> "Fields":
        return Fields(self.get(key, dict), self.path(key), self.source, self.version)

    def build(self, cls: type, **kwargs: Any) -> Any:
        """`cls(**kwargs)`, after refusing keys this object holds but nobody read; FieldErrors get the path."""
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise self.fail(unknown[0], f"is not a field of format version {self.version} "
                                        f"(known here: {', '.join(sorted(self.used))})")
        try:
            return cls(**kwargs)
        except FieldError as exc:
            raise self.fail(exc.key, exc.msg) from None


def _as_tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)


def _type_names(types) -> str:
    if set(_as_tuple(types)) == {int, float}:
        return "a number"
    names = {"str": "a string", "int": "an integer", "float": "a number", "list": "a list", "dict": "an object",
             "bool": "true or false"}
    return " or ".join(dict.fromkeys(names.get(t.__name__, t.__name__) for t in _as_tuple(types)))

"""The daemon's TOML configuration, validated at start: a wrong key, type or value fails with a message that names
the file, the key and what is allowed, before any model or camera is opened.

    [camera]
    source = "realsense"          # realsense[:SERIAL], oakd[:MXID], bag:FILE, replay:DIR, bop:DIR
    mode = "continuous"           # or "triggered": estimate only on POST /v1/detect
    frame_timeout_s = 5.0         # no frame for this long: the camera counts as down and is reopened
    reconnect_min_s = 0.5         # first wait before reopening a failed camera, doubled up to reconnect_max_s
    reconnect_max_s = 10.0
    realtime = true               # recordings (replay:, bop:) only: play at the recorded rate, start over at the end
    max_rate_hz = 0.0             # take at most this many frames a second (0: every frame the estimator keeps up
                                  # with); leaves the cores' remaining time to the vehicle's other software

    [model]
    bundle = ""                   # "" = the default bundle ($PALLET6D_BUNDLE, the installed pallet6d-models, ...)
    precision = "int8"            # or "fp32"
    threads = 2

    [estimator]                   # any `EstimatorOptions` field, e.g.
    score_threshold = 0.25

    [output]
    calibration = ""              # the camera's calibration file (pallet6d calib): poses in the vehicle frame
    frame = ""                    # "" = "vehicle" with a calibration; without one, "camera" must be asked for

    [floor_check]                 # with a calibration: does the floor still lie where it says? (GET /readyz)
    interval_s = 2.0              # seconds between checks (on the newest frame, beside the camera loop)
    max_tilt_deg = 2.0            # the seen floor may tilt this much from the calibrated one ...
    max_height_diff_m = 0.03      # ... and the camera's height above it differ this much
    when_unseen = "ready"         # no floor in view: "ready" or "not_ready"

    [api]
    host = "127.0.0.1"            # any other address needs a bearer token
    port = 8080
    token_file = ""               # a file holding the bearer token (or $PALLET6D_API_TOKEN)
    max_body_bytes = 65536

    [snapshot]
    frames = 30                   # recent frames kept in memory for POST /v1/snapshot
    dir = "/var/lib/pallet6d/snapshots"

Relative paths are relative to the config file's folder.
"""
from __future__ import annotations

import dataclasses
import ipaddress
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..calibration import Calibration, CalibrationError, load_calibration
from ..cameras import parse_source_spec
from ..estimator import MAX_THREADS, EstimatorOptions

if sys.version_info >= (3, 11):
    import tomllib
else:  # the serve extra installs tomli on 3.10
    import tomli as tomllib

__all__ = ["ConfigError", "ServeConfig", "CameraConfig", "ModelConfig", "OutputConfig", "FloorCheckConfig",
           "ApiConfig", "SnapshotConfig", "TOKEN_ENV", "MODES", "FRAMES", "WHEN_UNSEEN"]

TOKEN_ENV = "PALLET6D_API_TOKEN"
MODES = ("continuous", "triggered")
FRAMES = ("vehicle", "camera")
WHEN_UNSEEN = ("ready", "not_ready")
MAX_SNAPSHOT_FRAMES = 300   # about 2 MB per 848x480 frame in memory
MIN_TOKEN_CHARS = 16


class ConfigError(ValueError):
    """The configuration file is missing, unreadable or invalid."""


@dataclass(frozen=True)
class CameraConfig:
    source: str = "realsense"
    mode: str = "continuous"
    frame_timeout_s: float = 5.0
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 10.0
    realtime: bool = True
    max_rate_hz: float = 0.0


@dataclass(frozen=True)
class ModelConfig:
    bundle: str = ""
    precision: str = "int8"
    threads: int = 2


@dataclass(frozen=True)
class OutputConfig:
    """:ivar frame: "vehicle" or "camera" after validation ("" in the file: vehicle with a calibration).
    :ivar loaded: the validated calibration (read at start, never from the TOML)."""

    frame: str = ""
    calibration: str = ""
    loaded: Calibration | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class FloorCheckConfig:
    """The floor-consistency check of a calibrated daemon (`GET /readyz`, `pallet6d_floor_checks_total`)."""

    interval_s: float = 2.0
    max_tilt_deg: float = 2.0
    max_height_diff_m: float = 0.03
    when_unseen: str = "ready"


@dataclass(frozen=True)
class ApiConfig:
    host: str = "127.0.0.1"
    port: int = 8080
    token_file: str = ""
    max_body_bytes: int = 65536
    token: str = field(default="", repr=False)   # read from token_file or the environment, never from the TOML


@dataclass(frozen=True)
class SnapshotConfig:
    frames: int = 30
    dir: str = "/var/lib/pallet6d/snapshots"


SECTIONS = {"camera": CameraConfig, "model": ModelConfig, "output": OutputConfig, "floor_check": FloorCheckConfig,
            "api": ApiConfig, "snapshot": SnapshotConfig}
INTERNAL_FIELDS = ("token", "loaded")   # filled in at start, never read from the TOML


@dataclass(frozen=True)
class ServeConfig:
    camera: CameraConfig = CameraConfig()
    model: ModelConfig = ModelConfig()
    estimator: EstimatorOptions = EstimatorOptions()
    output: OutputConfig = OutputConfig()
    floor_check: FloorCheckConfig = FloorCheckConfig()
    api: ApiConfig = ApiConfig()
    snapshot: SnapshotConfig = SnapshotConfig()
    path: str = ""

    @classmethod
    def load(cls, path: str | Path, environ: dict[str, str] | None = None) -> "ServeConfig":
        """Read and validate a TOML file. :raises ConfigError: with the file, the key and the reason."""
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text())
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from None
        return cls.from_dict(doc, base_dir=path.parent, name=str(path), environ=environ)

    @classmethod
    def from_dict(cls, doc: dict, base_dir: Path = Path("."), name: str = "config",
                  environ: dict[str, str] | None = None) -> "ServeConfig":
        environ = os.environ if environ is None else environ
        unknown = set(doc) - set(SECTIONS) - {"estimator"}
        if unknown:
            raise ConfigError(f"{name}: unknown section(s) {sorted(unknown)}; allowed: "
                              f"{sorted([*SECTIONS, 'estimator'])}")
        parts: dict[str, Any] = {}
        for section, kind in SECTIONS.items():
            parts[section] = _section(doc.get(section, {}), kind, section, name)
        parts["estimator"] = _estimator(doc.get("estimator", {}), name)
        cfg = cls(**parts, path=name)
        return cfg._checked(base_dir, name, environ)

    def _checked(self, base_dir: Path, name: str, environ) -> "ServeConfig":
        c, m, o, f, a, s = self.camera, self.model, self.output, self.floor_check, self.api, self.snapshot

        def bad(key: str, msg: str) -> ConfigError:
            return ConfigError(f"{name}: {key}: {msg}")

        try:
            parse_source_spec(c.source)
        except ValueError as exc:
            raise bad("camera.source", str(exc)) from None
        if c.mode not in MODES:
            raise bad("camera.mode", f"must be one of {MODES}, got {c.mode!r}")
        if not c.frame_timeout_s > 0:
            raise bad("camera.frame_timeout_s", f"must be positive, got {c.frame_timeout_s}")
        if not 0 < c.reconnect_min_s <= c.reconnect_max_s:
            raise bad("camera.reconnect_min_s", f"must be positive and <= reconnect_max_s, got "
                                                f"{c.reconnect_min_s} and {c.reconnect_max_s}")
        if not (c.max_rate_hz == 0 or 0.1 <= c.max_rate_hz <= 1000):
            raise bad("camera.max_rate_hz", f"must be 0 (no limit) or in 0.1..1000, got {c.max_rate_hz}")
        if m.precision not in ("fp32", "int8"):
            raise bad("model.precision", f"must be 'fp32' or 'int8', got {m.precision!r}")
        if not 1 <= m.threads <= MAX_THREADS:
            raise bad("model.threads", f"must be in 1..{MAX_THREADS}, got {m.threads}")
        calibration = _resolve(o.calibration, base_dir)
        frame = o.frame or ("vehicle" if calibration else "")
        if frame not in FRAMES:
            raise bad("output.frame", (f"must be one of {FRAMES}, got {o.frame!r}" if o.frame else
                                       "vehicle-frame output (the default) needs output.calibration, the camera's "
                                       "calibration file (pallet6d calib floor ... --out cam.toml, see "
                                       "docs/forklift.md); for camera-frame poses set frame = \"camera\""))
        if frame == "vehicle" and not calibration:
            raise bad("output.calibration", "frame = \"vehicle\" needs the camera's calibration file (pallet6d "
                                            "calib floor ... --out cam.toml, see docs/forklift.md)")
        loaded = None
        if calibration:
            try:
                loaded = load_calibration(calibration)
            except CalibrationError as exc:
                raise bad("output.calibration", str(exc)) from None
            kind, serial = parse_source_spec(c.source)
            if kind in ("realsense", "oakd") and serial and loaded.serial and serial != loaded.serial:
                raise bad("output.calibration", f"is of camera {loaded.serial!r}, camera.source names {serial!r}")
        if not 0.1 <= f.interval_s <= 3600:
            raise bad("floor_check.interval_s", f"must be in 0.1..3600, got {f.interval_s}")
        if not 0 < f.max_tilt_deg <= 45:
            raise bad("floor_check.max_tilt_deg", f"must be in (0, 45], got {f.max_tilt_deg}")
        if not 0 < f.max_height_diff_m <= 1:
            raise bad("floor_check.max_height_diff_m", f"must be in (0, 1], got {f.max_height_diff_m}")
        if f.when_unseen not in WHEN_UNSEEN:
            raise bad("floor_check.when_unseen", f"must be one of {WHEN_UNSEEN}, got {f.when_unseen!r}")
        try:
            ip = ipaddress.ip_address(a.host)
        except ValueError:
            raise bad("api.host", f"must be an IP address (127.0.0.1, 0.0.0.0, ...), got {a.host!r}") from None
        if not 1 <= a.port <= 65535:
            raise bad("api.port", f"must be in 1..65535, got {a.port}")
        if not 1024 <= a.max_body_bytes <= 16 * 2**20:
            raise bad("api.max_body_bytes", f"must be in 1024..16777216, got {a.max_body_bytes}")
        token = _token(_resolve(a.token_file, base_dir), environ, bad)
        if not ip.is_loopback and not token:
            raise bad("api.host", f"{a.host} is reachable from other machines: set a bearer token "
                                  f"(api.token_file, or ${TOKEN_ENV}) or bind 127.0.0.1")
        if not 1 <= s.frames <= MAX_SNAPSHOT_FRAMES:
            raise bad("snapshot.frames", f"must be in 1..{MAX_SNAPSHOT_FRAMES}, got {s.frames}")
        if not s.dir:
            raise bad("snapshot.dir", "must name a folder")
        source = c.source
        kind, arg = parse_source_spec(source)
        if kind in ("replay", "bop", "bag") and arg:
            source = f"{kind}:{_resolve(arg, base_dir)}"
        return dataclasses.replace(
            self, camera=dataclasses.replace(c, source=source),
            model=dataclasses.replace(m, bundle=_resolve(m.bundle, base_dir)),
            output=dataclasses.replace(o, frame=frame, calibration=calibration, loaded=loaded),
            api=dataclasses.replace(a, token=token, token_file=_resolve(a.token_file, base_dir)),
            snapshot=dataclasses.replace(s, dir=_resolve(s.dir, base_dir)))


def _section(values: Any, kind: type, section: str, name: str):
    if not isinstance(values, dict):
        raise ConfigError(f"{name}: [{section}] must be a table, got {type(values).__name__}")
    fields = _fields(values, kind, f"[{section}]", name)
    out = {}
    for key, value in values.items():
        out[key] = _typed(value, type(fields[key].default), f"{section}.{key}", name)
    return kind(**out)


def _fields(values: dict, kind: type, where: str, name: str) -> dict:
    """`kind`'s fields that a file may set, by name; a `ConfigError` names the keys of `values` that are none."""
    fields = {f.name: f for f in dataclasses.fields(kind) if f.name not in INTERNAL_FIELDS}
    unknown = set(values) - set(fields)
    if unknown:
        raise ConfigError(f"{name}: {where} unknown key(s) {sorted(unknown)}; allowed: {sorted(fields)}")
    return fields


def _typed(value: Any, want: type, key: str, name: str):
    """`value` as `want` (bool, int, float or str); an int is a float, nothing else is converted."""
    ok = (isinstance(value, want) and not (want is int and isinstance(value, bool))) or \
        (want is float and isinstance(value, int) and not isinstance(value, bool))
    if not ok:
        raise ConfigError(f"{name}: {key}: expected {want.__name__}, got {type(value).__name__} {value!r}")
    return want(value)


def _estimator(values: Any, name: str) -> EstimatorOptions:
    if not isinstance(values, dict):
        raise ConfigError(f"{name}: [estimator] must be a table, got {type(values).__name__}")
    fields = _fields(values, EstimatorOptions, "[estimator]", name)
    out = {}
    for key, value in values.items():
        default = fields[key].default
        if dataclasses.is_dataclass(default):       # a group of settings (structure): false = off, a table = set
            out[key] = _settings(value, type(default), f"estimator.{key}", name)
        elif key == "pallet_types":
            if not (isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)):
                raise ConfigError(f"{name}: estimator.pallet_types: expected a list of pallet type names, "
                                  f"e.g. [\"epal\"], got {value!r}")
            out[key] = tuple(value)
        elif key == "depth_range_m" or isinstance(value, list) or isinstance(default, tuple):
            size = 2 if key == "depth_range_m" else len(default) if isinstance(default, tuple) else None
            if not (isinstance(value, list) and (size is None or len(value) == size)
                    and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
                raise ConfigError(f"{name}: estimator.{key}: expected a list of {size or 'some'} numbers, "
                                  f"got {value!r}")
            out[key] = tuple(float(v) for v in value)
        elif default is None or default is dataclasses.MISSING:
            out[key] = value          # an option without a typed default: EstimatorOptions checks it
        else:
            out[key] = _typed(value, type(default), f"estimator.{key}", name)
    try:
        return EstimatorOptions(**out)
    except (TypeError, ValueError, IndexError) as exc:
        raise ConfigError(f"{name}: [estimator]: {exc}") from None


def _settings(value: Any, kind: type, key: str, name: str):
    """An estimator option that is a group of settings: `false` (off: None), `true` (its defaults) or a table of
    its fields."""
    if isinstance(value, bool):
        return kind() if value else None
    if not isinstance(value, dict):
        raise ConfigError(f"{name}: {key}: expected true, false or a table, got {type(value).__name__} {value!r}")
    fields = _fields(value, kind, f"{key}:", name)
    try:
        return kind(**{k: _typed(v, type(fields[k].default), f"{key}.{k}", name) for k, v in value.items()})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: {key}: {exc}") from None


def _resolve(path: str, base_dir: Path) -> str:
    if not path:
        return ""
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else (base_dir / p).resolve())


def _token(token_file: str, environ, bad) -> str:
    if token_file:
        try:
            token = Path(token_file).read_text().strip()
        except OSError as exc:
            raise bad("api.token_file", f"cannot read {token_file}: {exc.strerror or exc}") from None
        where = "api.token_file"
    else:
        token, where = environ.get(TOKEN_ENV, "").strip(), f"${TOKEN_ENV}"
    if token and (len(token) < MIN_TOKEN_CHARS or not token.isprintable() or " " in token):
        raise bad(where, f"the bearer token must be at least {MIN_TOKEN_CHARS} printable characters without spaces")
    return token

"""Pinhole camera intrinsics: a validated record, JSON I/O, and rescaling for resized images."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pallet6d.runtime.geometry import check_K

__all__ = ["CameraIntrinsics"]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Intrinsics of one image stream.

    :param width: image width in pixels.
    :param height: image height in pixels.
    :param K: (3, 3) pinhole matrix for that image size.
    :param dist: (5,) OpenCV distortion coefficients k1, k2, p1, p2, k3 (zeros for a rectified stream).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", check_K(self.K))
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if dist.shape not in ((4,), (5,), (8,)) or not np.all(np.isfinite(dist)):
            raise ValueError(f"dist must hold 4, 5 or 8 finite OpenCV coefficients, got shape {dist.shape}")
        object.__setattr__(self, "dist", dist)

    def scaled(self, width: int, height: int) -> "CameraIntrinsics":
        """Intrinsics of the same camera with the image resized to (width, height)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5  # pixel centres, not edges, stay aligned
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraIntrinsics(width, height, K, self.dist)

    def to_dict(self) -> dict:
        return {"width": int(self.width), "height": int(self.height),
                "K": self.K.tolist(), "dist": self.dist.tolist()}

    @classmethod
    def from_dict(cls, data: dict, source: str = "intrinsics") -> "CameraIntrinsics":
        try:
            return cls(int(data["width"]), int(data["height"]), np.asarray(data["K"], dtype=np.float64),
                       np.asarray(data.get("dist", np.zeros(5)), dtype=np.float64))
        except KeyError as exc:
            raise ValueError(f"{source}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{source}: {exc}") from None

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2))

    @classmethod
    def load(cls, path: str | Path) -> "CameraIntrinsics":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: cannot read intrinsics: {exc}") from None
        return cls.from_dict(data, source=str(path))

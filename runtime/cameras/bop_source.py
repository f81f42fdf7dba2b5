"""Play a BOP dataset (`bop:DIR`), e.g. one written by `pallet6d sim`, as a frame source."""
from __future__ import annotations

import logging
from pathlib import Path

from .base import FrameSource
from .errors import CameraError, CameraNotFound, FrameReadError
from .frame import RGBDFrame
from .replay import check_on_error

__all__ = ["BopSource"]

log = logging.getLogger(__name__)


class BopSource(FrameSource):
    """Frames of a BOP dataset in order, as fast as read.

    Frames are read by `pallet6d.runtime.bop.BopDataset` (paths, K, depth scale, ground truth); depth is handed
    out as stored, in the dataset's own units (`depth_scale_mm` mm per unit), so no value changes.
    BOP frames carry no capture time: `timestamp_s` is `frame_number / fps`, and `frame_number` is the frame's
    index in the dataset (plus its length per earlier pass when looping). The ground truth of the frame just
    read is `last_gts` (a list of `BopGT`; None after an unreadable frame).

    :param root: what `pallet6d.runtime.bop.BopDataset` opens.
    :param fps: nominal rate for the synthetic timestamps.
    :param on_error: "skip" unreadable frames with a warning, or "raise" `FrameReadError` with its
        `frame_number`; the next `read()` goes on with the next frame.
    """

    def __init__(self, root: str | Path, fps: float = 30.0, on_error: str = "skip", loop: bool = False) -> None:
        check_on_error(on_error)
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.root = Path(root)
        super().__init__(f"bop:{self.root}")
        self.fps, self.on_error, self.loop = float(fps), on_error, bool(loop)
        self.skipped = 0
        self.last_gts: list | None = None
        self._ds = None

    def __len__(self) -> int:
        return 0 if self._ds is None else len(self._ds)

    @property
    def dataset(self):
        """The open `BopDataset` (its models, for evaluation), None before start."""
        return self._ds

    def _start(self) -> None:
        from pallet6d.runtime.bop import BopDataset  # the house BOP reader
        if not self.root.exists():
            raise CameraNotFound(f"BOP dataset {self.root} does not exist")
        try:
            self._ds = BopDataset(self.root)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise CameraError(f"{self.root}: cannot open BOP dataset: {exc}") from None
        if len(self._ds) == 0:
            raise CameraError(f"{self.root}: BOP dataset holds no frames")
        self._i = 0
        self._pass = 0
        self.last_gts = None
        # intrinsics and depth units before the first read(): those of the first readable frame
        for i in range(len(self._ds)):
            try:
                first = self._frame_at(i)
            except FrameReadError:
                continue
            self._K, self._depth_scale_m = first.K, first.depth_scale_m
            return
        raise CameraError(f"{self.root}: no readable frame in the whole dataset")

    def _stop(self) -> None:
        self._ds = None

    def _frame_at(self, i: int) -> RGBDFrame:
        """Frame `i` of the dataset, numbered `i` (plus the dataset's length per earlier pass of a loop);
        its ground truth goes to `last_gts`."""
        number = i + self._pass * len(self._ds)
        self.last_gts = None
        try:
            f = self._ds[i]
            frame = RGBDFrame(f.rgb, f.depth_units, f.K, float(f.depth_scale_mm) * 1e-3, number / self.fps, number,
                              self.name)
        except (OSError, ValueError, TypeError, KeyError) as exc:
            raise FrameReadError(f"{self.name}: frame {i}: {exc}", number) from exc
        self.last_gts = f.gts
        return frame

    def _read(self) -> RGBDFrame | None:
        n = len(self._ds)
        misses = 0
        while True:
            if self._i >= n:
                if not self.loop:
                    return None
                self._i, self._pass = 0, self._pass + 1
            i = self._i
            self._i += 1
            try:
                return self._frame_at(i)
            except FrameReadError as exc:
                if self.on_error == "raise":
                    raise
                self.skipped += 1
                misses += 1
                log.warning("%s: skipping frame %d: %s", self.name, i, exc)
                if misses >= n:   # a whole pass unreadable: looping would never end
                    raise FrameReadError(f"{self.name}: no readable frame in the whole dataset") from None

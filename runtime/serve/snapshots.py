"""The ring of recent frames kept in memory, written as a replay recording on request, so that a field failure
can be replayed on a desk (`pallet6d run --source replay:DIR`)."""
from __future__ import annotations

import collections
import logging
import threading
import time
from pathlib import Path

from ..cameras import RGBDFrame, ReplayWriter

__all__ = ["FrameRing"]

log = logging.getLogger(__name__)


class FrameRing:
    """The last `capacity` frames. `push` is called by the camera loop, `write` by API workers: a lock guards
    the deque only for the moment of appending or copying it, never while files are written.

    :param capacity: frames kept (>= 1).
    """

    def __init__(self, capacity: int) -> None:
        if int(capacity) < 1:
            raise ValueError(f"FrameRing capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self._frames: collections.deque[RGBDFrame] = collections.deque(maxlen=self.capacity)
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)

    def push(self, frame: RGBDFrame) -> None:
        with self._lock:
            self._frames.append(frame)

    def recent(self, n: int) -> list[RGBDFrame]:
        """The last `n` frames (fewer when fewer are held), oldest first, all of the newest frame's camera
        setting (image size, K, depth scale): a recording holds one setting."""
        with self._lock:
            frames = list(self._frames)[-int(n):] if n > 0 else []
        if not frames:
            return []
        last = frames[-1]
        i = len(frames)
        while i > 0 and _same_setting(frames[i - 1], last):
            i -= 1
        return frames[i:]

    def write(self, out_root: Path, n: int) -> tuple[Path, int]:
        """Write the last `n` frames as a replay folder under `out_root`, named by the UTC time.

        :return: (folder, frames written). :raises LookupError: no frame held yet. :raises OSError: cannot write.
        """
        frames = self.recent(n)
        if not frames:
            raise LookupError("no frame received yet")
        with self._write_lock:   # one writer at a time: names stay unique, the disk is not thrashed
            out_root.mkdir(parents=True, exist_ok=True)
            stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
            out, k = out_root / f"snapshot-{stamp}", 1
            while out.exists():
                k += 1
                out = out_root / f"snapshot-{stamp}-{k}"
            with ReplayWriter(out, flush_every=len(frames)) as writer:
                for frame in frames:
                    writer.write(frame)
        log.info("snapshot: %d frames written to %s", len(frames), out)
        return out, len(frames)


def _same_setting(a: RGBDFrame, b: RGBDFrame) -> bool:
    return a.rgb.shape == b.rgb.shape and a.depth_scale_m == b.depth_scale_m and bool((a.K == b.K).all())

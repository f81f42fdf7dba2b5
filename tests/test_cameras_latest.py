"""LatestFrame grabber: drops stale frames, propagates errors, stops cleanly (events, never timing)."""
from __future__ import annotations

import queue
import threading

import pytest

from pallet6d.runtime.cameras import CameraDisconnected, CameraError, CameraTimeout, FrameSource, LatestFrame
from camera_fixtures import K_SMALL, box_frame

END = object()


class FakeLiveSource(FrameSource):
    """read() hands out what the test puts in its queue; `waiting[n]` is set when read call n starts."""

    live = True

    def __init__(self):
        super().__init__("fake")
        self.q: queue.Queue = queue.Queue()
        self.calls = 0
        self.waiting = [threading.Event() for _ in range(64)]
        self.stopped = threading.Event()

    def _start(self):
        self._K, self._depth_scale_m = K_SMALL, 0.001

    def _read(self):
        self.waiting[self.calls].set()
        self.calls += 1
        while True:
            try:
                item = self.q.get(timeout=0.05)
                break
            except queue.Empty:
                if self.stopped.is_set():
                    return None
        if item is END:
            return None
        if isinstance(item, BaseException):
            raise item
        return item

    def _stop(self):
        self.stopped.set()


WAIT = 10.0  # generous bound for events; never asserted as a timing


def test_keeps_only_newest_and_counts_drops():
    src = FakeLiveSource()
    with LatestFrame(src) as grab:
        assert grab.K.shape == (3, 3)
        for i in range(3):
            src.q.put(box_frame(i))
        assert src.waiting[3].wait(WAIT)  # frames 0..2 consumed by the reader, which now waits for more
        frame = grab.get(timeout_s=WAIT)
        assert frame.frame_number == 102
        assert (grab.received, grab.dropped) == (3, 2)
        src.q.put(box_frame(3))
        assert grab.get(timeout_s=WAIT).frame_number == 103
        assert grab.dropped == 2
    assert src.stopped.is_set() and not src.running


def test_get_times_out_without_new_frame():
    src = FakeLiveSource()
    with LatestFrame(src) as grab:
        src.q.put(box_frame(0))
        assert grab.get(timeout_s=WAIT).frame_number == 100
        with pytest.raises(CameraTimeout):
            grab.get(timeout_s=0.01)  # the same frame is never handed out twice


def test_source_error_reaches_consumer_after_last_frame():
    src = FakeLiveSource()
    with LatestFrame(src) as grab:
        src.q.put(box_frame(0))
        src.q.put(CameraDisconnected("fake: unplugged"))
        assert src.waiting[1].wait(WAIT)
        assert grab.get(timeout_s=WAIT).frame_number == 100
        with pytest.raises(CameraDisconnected, match="unplugged"):
            grab.get(timeout_s=WAIT)


def test_foreign_error_is_wrapped():
    src = FakeLiveSource()
    with LatestFrame(src) as grab:
        src.q.put(RuntimeError("SDK exploded"))
        with pytest.raises(CameraError, match="SDK exploded"):
            grab.get(timeout_s=WAIT)


def test_end_of_recording_ends_iteration():
    src = FakeLiveSource()
    with LatestFrame(src) as grab:
        src.q.put(box_frame(0))
        assert src.waiting[1].wait(WAIT)
        src.q.put(END)
        assert [f.frame_number for f in grab] == [100]


def test_stop_unblocks_waiting_reader_and_get():
    src = FakeLiveSource()
    grab = LatestFrame(src).start()
    assert src.waiting[0].wait(WAIT)
    grab.stop()
    assert src.stopped.is_set()
    assert grab.get(timeout_s=WAIT) is None
    grab.stop()  # twice is fine


def test_get_before_start():
    with pytest.raises(CameraError, match="before start"):
        LatestFrame(FakeLiveSource()).get(timeout_s=0.01)

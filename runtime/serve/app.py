"""The daemon's HTTP API (FastAPI). Handlers only read what `CameraLoop` publishes: none of them waits on the
camera loop except `POST /v1/detect`, which runs the estimator on the newest frame (at most `DETECT_SLOTS` at a
time; more get 429).

Handlers that never block are `async` (no thread hop per request); those that compute or write run in the
framework's thread pool.

Open endpoints: `GET /healthz`, `GET /readyz`, `GET /openapi.json`. With a bearer token configured every other
endpoint needs `Authorization: Bearer TOKEN`.
"""
from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Annotated

import anyio
import cv2
from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..results import FrameResult
from .config import ServeConfig
from .limits import RequestLimits
from .loop import CameraLoop, NoFrameError, Published, RegionHint
from .metrics import CONTENT_TYPE_LATEST, Metrics, RequestTimer
from .schema import PalletsResponse, ReadyResponse
from .snapshots import FrameRing

__all__ = ["create_app", "result_payload"]

log = logging.getLogger(__name__)

DETECT_SLOTS = 2          # POST /v1/detect requests estimating or waiting for the estimator at once
KEEPALIVE_S = 15.0        # a comment line on idle streams, so proxies and clients see the connection alive
MJPEG_BOUNDARY = "pallet6d-frame"
OVERLAY_JPEG_QUALITY = 80
# routes whose handling time goes to pallet6d_http_request_seconds (the streams last as long as the client wants)
TIMED_ROUTES = ("/healthz", "/readyz", "/metrics", "/v1/pallets", "/v1/detect", "/v1/overlay.jpg", "/v1/snapshot")

Coord = Annotated[float, Field(ge=-100000, le=100000, allow_inf_nan=False)]


class DetectRequest(BaseModel):
    """Where the wanted pallet is expected; every field is optional."""

    model_config = ConfigDict(extra="forbid")
    box_xyxy: tuple[Coord, Coord, Coord, Coord] | None = Field(
        None, description="image region (x1, y1, x2, y2) in pixels: a pallet's box centre must lie inside")
    distance_m: float | None = Field(None, gt=0, le=50, allow_inf_nan=False,
                                     description="expected camera depth of the pallet's centre, metres")
    tolerance_m: float = Field(0.5, gt=0, le=10, allow_inf_nan=False, description="half-width of the depth window")

    @model_validator(mode="after")
    def _box_ordered(self) -> "DetectRequest":
        b = self.box_xyxy
        if b is not None and not (b[2] > b[0] and b[3] > b[1]):
            raise ValueError("box_xyxy must have x2 > x1 and y2 > y1")
        return self


class SnapshotRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frames: int | None = Field(None, ge=1, le=10000,
                               description="how many of the most recent frames (default: all the ring holds)")


class Problem(BaseModel):
    detail: str


def result_payload(pub: Published, output_frame: str = "camera") -> dict:
    """The JSON body of a published result, without `age_s` (added per request): the pallets as
    `FrameResult.to_dict()` gives them (in the vehicle frame: with `t_vehicle_m`, `forklift`, ...)."""
    d = pub.result.to_dict() if pub.result is not None else FrameResult.empty(pub.frame.rgb.shape[:2]).to_dict()
    rest = {k: v for k, v in d.items() if k not in ("poses", "rejected", "timings_ms", "image_hw")}
    return {"seq": pub.seq, "frame": pub.frame.frame_number, "capture_timestamp_s": pub.frame.timestamp_s,
            "received_unix_s": round(pub.received_unix_s, 4), "trigger": pub.trigger, "output_frame": output_frame,
            "source": pub.frame.source, "image_hw": d["image_hw"], "latency_ms": d["timings_ms"],
            "pallets": d["poses"], "rejected": d["rejected"], "n_outside_hint": pub.n_outside_hint,
            "error": pub.error or None, **rest}


class _Hub:
    """Wakes the stream handlers (event-loop side) when the camera loop (its own thread) publishes."""

    def __init__(self) -> None:
        self.aio: asyncio.AbstractEventLoop | None = None
        self.event: asyncio.Event | None = None
        self.closing = False

    def bind(self) -> None:
        self.aio, self.event, self.closing = asyncio.get_running_loop(), asyncio.Event(), False

    def notify(self, _pub: Published | None = None) -> None:
        aio = self.aio
        if aio is not None and not aio.is_closed():
            with contextlib.suppress(RuntimeError):   # the event loop closed in between
                aio.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        if self.event is not None:
            old, self.event = self.event, asyncio.Event()
            old.set()

    def close(self) -> None:
        self.closing = True
        self._wake()


class _Payloads:
    """JSON text and overlay JPEG of the newest published record, each computed once per record."""

    def __init__(self, loop: CameraLoop, output_frame: str) -> None:
        self.loop, self.output_frame = loop, output_frame
        self._json: tuple[int, dict] = (-1, {})
        self._jpeg: tuple[int, int, bytes] = (-1, -1, b"")
        self._jpeg_lock = threading.Lock()

    def body(self, pub: Published) -> bytes:
        seq, payload = self._json
        if seq != pub.seq:
            payload = result_payload(pub, self.output_frame)
            self._json = (pub.seq, payload)
        age = time.monotonic() - pub.received_monotonic
        return json.dumps({**payload, "age_s": round(age, 4)}).encode()

    def overlay_jpeg(self) -> bytes | None:
        """The newest frame with the newest result's pallets drawn (the result only if it is of that frame)."""
        from ..draw import draw_result

        frame_pub, pub = self.loop.latest_frame, self.loop.latest
        if frame_pub is None:
            return None
        if pub is not None and pub.received_monotonic >= frame_pub.received_monotonic:
            frame_pub = pub
        key = (frame_pub.seq, id(frame_pub.frame))
        with self._jpeg_lock:
            if self._jpeg[:2] == key:
                return self._jpeg[2]
            frame = frame_pub.frame
            result = frame_pub.result or FrameResult.empty(frame.rgb.shape[:2])
            img = draw_result(frame.rgb, result, frame.K, self.loop.estimator.model_size_m)
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, OVERLAY_JPEG_QUALITY])
            if not ok:
                raise RuntimeError("JPEG encoding of the overlay failed")
            self._jpeg = (*key, buf.tobytes())
            return self._jpeg[2]


def _json_safe(value):
    """`value` with NaN and infinities (which JSON cannot carry) written as strings, containers walked."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


async def _invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with what was wrong, as FastAPI answers, also where the input held a NaN (Python's JSON reads one, and
    FastAPI's own answer would then fail as a 500)."""
    return JSONResponse({"detail": _json_safe(jsonable_encoder(exc.errors()))}, status_code=422)


def create_app(config: ServeConfig, loop: CameraLoop, metrics: Metrics, ring: FrameRing,
               model_info: dict | None = None) -> FastAPI:
    """The API over a running (or about to run) `CameraLoop`."""
    hub = _Hub()
    payloads = _Payloads(loop, config.output.frame)
    loop.subscribe(hub.notify)
    detect_slots = threading.BoundedSemaphore(DETECT_SLOTS)
    token = config.api.token.encode()
    ticks = {"event_loop": time.monotonic()}

    @contextlib.asynccontextmanager
    async def lifespan(_app: FastAPI):
        hub.bind()

        async def tick() -> None:   # proves the event loop runs (the systemd watchdog reads it)
            while True:
                ticks["event_loop"] = time.monotonic()
                await asyncio.sleep(1.0)

        task = asyncio.create_task(tick())
        try:
            yield
        finally:
            hub.close()
            task.cancel()

    app = FastAPI(title="pallet6d daemon", version=str((model_info or {}).get("version", "")),
                  description="Pallet 6D poses from the forklift's RGB-D camera.", lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.add_middleware(RequestLimits, max_body_bytes=config.api.max_body_bytes)
    app.add_middleware(RequestTimer, histogram=metrics.http_latency, routes=TIMED_ROUTES)
    app.state.ticks = ticks
    app.state.hub = hub

    async def authorized(request: Request) -> None:
        if not token:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), token):
            raise HTTPException(401, "a valid bearer token is required", headers={"WWW-Authenticate": "Bearer"})

    auth = [Depends(authorized)]
    unauthorized = {401: {"model": Problem, "description": "missing or wrong bearer token (when one is set)"}}
    no_result = {503: {"model": Problem, "description": "no result yet, or the camera is down"}}

    @app.get("/healthz", tags=["health"], summary="the process is alive")
    async def healthz() -> dict:
        return {"status": "ok"}

    @app.get("/readyz", tags=["health"],
             summary="model loaded, camera streaming, results fresh, calibration consistent with the floor",
             responses={200: {"model": ReadyResponse},
                        503: {"model": ReadyResponse, "description": "not ready; `checks` and `reasons` say why"}})
    async def readyz() -> JSONResponse:
        body = _readiness(config, loop)
        return JSONResponse(body, status_code=200 if body["ready"] else 503)

    @app.get("/metrics", tags=["health"], dependencies=auth, responses=unauthorized,
             summary="Prometheus metrics", response_class=Response)
    async def metrics_endpoint() -> Response:
        return Response(metrics.exposition(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/pallets", tags=["pallets"], dependencies=auth, summary="the latest result",
             responses={200: {"model": PalletsResponse}, **unauthorized, **no_result})
    async def pallets() -> Response:
        pub = loop.latest
        if pub is None:
            raise HTTPException(503, "no result yet" + (f": {loop.last_error}" if loop.last_error else ""))
        return Response(payloads.body(pub), media_type="application/json")

    @app.post("/v1/detect", tags=["pallets"], dependencies=auth,
              summary="estimate on the newest frame now, optionally only in a region",
              responses={200: {"model": PalletsResponse}, 429: {"model": Problem, "description": "busy"},
                         **unauthorized, **no_result})
    def detect(request: DetectRequest | None = None) -> Response:
        hint = None
        if request is not None and (request.box_xyxy is not None or request.distance_m is not None):
            hint = RegionHint(request.box_xyxy, request.distance_m, request.tolerance_m)
        if not detect_slots.acquire(blocking=False):
            raise HTTPException(429, f"{DETECT_SLOTS} detect requests are already running")
        try:
            pub = loop.detect(hint)
        except NoFrameError as exc:
            raise HTTPException(503, str(exc)) from None
        except ValueError as exc:
            raise HTTPException(503, str(exc)) from None
        finally:
            detect_slots.release()
        age_s = round(time.monotonic() - pub.received_monotonic, 4)
        body = {**result_payload(pub, config.output.frame), "age_s": age_s}
        return Response(json.dumps(body).encode(), media_type="application/json")

    @app.get("/v1/stream", tags=["pallets"], dependencies=auth, response_class=StreamingResponse,
             summary="Server-Sent Events: each new result as an `event: result` with the JSON of /v1/pallets",
             responses={200: {"content": {"text/event-stream": {}}}, **unauthorized})
    async def stream(max_events: Annotated[int, Query(ge=0, le=1_000_000,
                                                      description="end after this many (0: never)")] = 0):
        async def events():
            last, sent = -1, 0
            while not hub.closing:
                wake = hub.event
                pub = loop.latest
                if pub is not None and pub.seq != last:
                    last, sent = pub.seq, sent + 1
                    yield b"id: %d\nevent: result\ndata: %s\n\n" % (pub.seq, payloads.body(pub))
                    if max_events and sent >= max_events:
                        return
                    continue
                try:
                    await asyncio.wait_for(wake.wait(), KEEPALIVE_S)
                except TimeoutError:
                    yield b": keep-alive\n\n"

        return StreamingResponse(events(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    @app.get("/v1/overlay.jpg", tags=["operator"], dependencies=auth, response_class=Response,
             summary="the newest frame with the posed pallets drawn",
             responses={200: {"content": {"image/jpeg": {}}}, **unauthorized, **no_result})
    async def overlay() -> Response:
        jpeg = await anyio.to_thread.run_sync(payloads.overlay_jpeg)
        if jpeg is None:
            raise HTTPException(503, "no frame yet")
        return Response(jpeg, media_type="image/jpeg", headers={"Cache-Control": "no-store"})

    @app.get("/v1/overlay.mjpg", tags=["operator"], dependencies=auth, response_class=StreamingResponse,
             summary="MJPEG stream of the overlay (one part per new result or frame)",
             responses={200: {"content": {f"multipart/x-mixed-replace; boundary={MJPEG_BOUNDARY}": {}}},
                        **unauthorized})
    async def overlay_stream(max_frames: Annotated[int, Query(ge=0, le=1_000_000,
                                                              description="end after this many (0: never)")] = 0,
                             max_fps: Annotated[float, Query(gt=0, le=30, allow_inf_nan=False,
                                                             description="at most this many parts per second")] = 5.0):
        async def parts():
            last, sent = None, 0
            while not hub.closing:
                jpeg = await anyio.to_thread.run_sync(payloads.overlay_jpeg)
                if jpeg is not None and jpeg is not last:
                    last, sent = jpeg, sent + 1
                    yield (b"--%s\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n%s\r\n"
                           % (MJPEG_BOUNDARY.encode(), len(jpeg), jpeg))
                    if max_frames and sent >= max_frames:
                        return
                await asyncio.sleep(1.0 / max_fps)

        return StreamingResponse(parts(), media_type=f"multipart/x-mixed-replace; boundary={MJPEG_BOUNDARY}",
                                 headers={"Cache-Control": "no-store"})

    @app.post("/v1/snapshot", tags=["operator"], dependencies=auth, status_code=201,
              summary="write the most recent frames as a replay recording (pallet6d run --source replay:DIR)",
              responses={503: {"model": Problem, "description": "no frame held yet"},
                         507: {"model": Problem, "description": "the recording could not be written"},
                         **unauthorized})
    def snapshot(request: SnapshotRequest | None = None) -> dict:
        n = ring.capacity if request is None or request.frames is None else min(request.frames, ring.capacity)
        try:
            out, written = ring.write(Path(config.snapshot.dir), n)
        except LookupError as exc:
            raise HTTPException(503, str(exc)) from None
        except OSError as exc:
            log.warning("snapshot failed: %s", exc)
            raise HTTPException(507, f"cannot write the snapshot: {exc.strerror or exc}") from None
        metrics.snapshots.inc()
        return {"path": str(out), "frames": written, "source": f"replay:{out}"}

    return app


def _readiness(config: ServeConfig, loop: CameraLoop) -> dict:
    """The body of `GET /readyz`: each check, a sentence per failing one, the floor check's numbers."""
    c = config.camera
    camera_age, result_age = loop.camera_age_s(), loop.result_age_s()
    watch = loop.floor_watch
    checks = {"model": bool(getattr(loop.estimator, "alive", loop.estimator is not None)),
              "camera": loop.camera_fresh(),
              "results": (c.mode == "triggered") or (math.isfinite(result_age) and result_age <= 2 * c.frame_timeout_s),
              "calibration": watch is None or watch.ready()}
    if watch is None:
        floor = {"state": "not_configured", "detail": "no calibration: camera-frame output"}
    else:
        floor = {**watch.to_dict(), "file": config.output.calibration}
    why = {"model": "the estimator process is not running",
           "camera": f"no camera frame within {c.frame_timeout_s} s" + (f": {loop.last_error}" if loop.last_error
                                                                        else ""),
           "results": f"no result within {2 * c.frame_timeout_s} s",
           "calibration": f"calibration {floor['state']}: {floor['detail']}"}
    return {"ready": all(checks.values()), "checks": checks, "reasons": [why[k] for k, ok in checks.items() if not ok],
            "mode": c.mode, "output_frame": config.output.frame, "calibration": floor,
            "camera_frame_age_s": _finite(camera_age), "result_age_s": _finite(result_age),
            "camera_error": loop.last_error or None}


def _finite(x: float) -> float | None:
    return round(x, 4) if math.isfinite(x) else None

"""Soak and load of the daemon: `pallet6d serve` on a replay at camera rate, polled and streamed over loopback.

Phases (fractions of --minutes): warm-up (no clients, not scored), quiet (no clients), load (--clients polling
`GET /v1/pallets` at --poll-hz each, plus one SSE stream client), quiet again. Reports:
- the camera loop's rate (estimated frames per second, from /metrics) per phase: load vs the quiet phases;
- `GET /v1/pallets` latency p50/p99/max seen by the pollers, and errors, and the daemon's own handling time
  (bucket bounds of pallet6d_http_request_seconds);
- the daemon's RSS every --rss-every-s seconds, API process and estimator process (growth after the warm-up;
  the snapshot ring fills first: `snapshot.frames` frames of about 2.3 MB at 1224x370);
- tracebacks and ERROR lines in the daemon's log.

    python benchmarks/serve_soak.py --minutes 10 --out runs/serve-soak
    python benchmarks/serve_soak.py --minutes 1 --clients 5 --out /tmp/soak     # a quick look

The recording defaults to 8 generated frames (virtual-occluded, seed 7) turned into a replay folder; `--cpus
0,1` pins the daemon to those cores (the forklift computer's two), the clients then run on the others.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]


def make_replay(work: Path) -> Path:
    replay = work / "replay"
    if (replay / "camera.json").exists():
        return replay
    bop = work / "bop"
    cli = [sys.executable, "-m", "pallet6d.runtime.cli"]
    subprocess.run(cli + ["sim", "--preset", "virtual-occluded", "--frames", "8", "--seed", "7", "--out", str(bop)],
                   check=True, stderr=subprocess.DEVNULL)
    subprocess.run(cli + ["record", "--source", f"bop:{bop}", "--out", str(replay)], check=True,
                   stderr=subprocess.DEVNULL)
    return replay


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def children(pid: int) -> list[int]:
    """Direct children of `pid` (the estimator process, multiprocessing's resource tracker)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def frames_total(client: httpx.Client) -> float:
    for line in client.get("/metrics").text.splitlines():
        if line.startswith("pallet6d_frames_total "):
            return float(line.split()[1])
    raise RuntimeError("pallet6d_frames_total missing from /metrics")


class Load:
    """Pollers and one stream client, in a process of their own.

    The pollers speak HTTP/1.1 over asyncio streams (keep-alive, one connection each) rather than through a
    client library: a poller's own CPU per request (a library parses more than the status line and the length)
    and this process's other threads (RSS sampling, metrics scrapes) would otherwise add their wait for a core to
    every latency it reports. The stream client reads Server-Sent Events with httpx.
    """

    def __init__(self, url: str, clients: int, poll_hz: float) -> None:
        self.latencies_ms: list[float] = []
        self.errors: dict[str, int] = {}
        self.events = 0
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        self._results = ctx.Queue()
        self._proc = ctx.Process(target=_load_process, args=(url, clients, 1.0 / poll_hz, self._stop, self._results),
                                 daemon=True)

    def start(self) -> None:
        self._proc.start()

    def stop(self) -> None:
        self._stop.set()
        self.latencies_ms, self.errors, self.events = self._results.get(timeout=120)
        self._proc.join(60)


def _load_process(url: str, clients: int, period: float, stop, results) -> None:
    state = {"lat": [], "errors": {}, "events": 0}
    asyncio.run(_load_main(url, clients, period, stop, state))
    results.put((state["lat"], state["errors"], state["events"]))


async def _load_main(url: str, clients: int, period: float, stop, state: dict) -> None:
    host, port = url.split("://", 1)[1].rsplit(":", 1)
    tasks = [asyncio.create_task(_poll(host, int(port), period, i / clients, state)) for i in range(clients)]
    tasks.append(asyncio.create_task(_stream(url, state)))
    while not stop.is_set():
        await asyncio.sleep(0.2)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


def _count(errors: dict, key: str) -> None:
    errors[key] = errors.get(key, 0) + 1


async def _get(reader, writer, request: bytes) -> int:
    """One keep-alive GET; returns the status code once the whole body is read."""
    writer.write(request)
    head = await reader.readuntil(b"\r\n\r\n")
    lines = head.split(b"\r\n")
    status = int(lines[0].split()[1])
    length = next((int(x.split(b":", 1)[1]) for x in lines[1:] if x.lower().startswith(b"content-length:")), None)
    if length is None:
        raise ValueError("response without Content-Length")
    await reader.readexactly(length)
    return status


async def _poll(host: str, port: int, period: float, phase: float, state: dict) -> None:
    await asyncio.sleep(period * phase)   # spread the clients over one period
    request = f"GET /v1/pallets HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode()
    reader = writer = None
    next_t = time.perf_counter()
    while True:
        try:
            if writer is None:
                reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), 10)
            t0 = time.perf_counter()
            status = await asyncio.wait_for(_get(reader, writer, request), 10)
            if status == 200:
                state["lat"].append(1000 * (time.perf_counter() - t0))
            else:
                _count(state["errors"], str(status))
        except asyncio.CancelledError:
            raise
        except (OSError, ValueError, asyncio.TimeoutError, asyncio.IncompleteReadError) as exc:
            _count(state["errors"], type(exc).__name__)
            if writer is not None:
                writer.close()
            reader = writer = None
        next_t += period
        await asyncio.sleep(max(0.0, next_t - time.perf_counter()))


async def _stream(url: str, state: dict) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=None) as client:
        async with client.stream("GET", "/v1/stream") as r:
            async for line in r.aiter_lines():
                if line.startswith("data: "):
                    state["events"] += 1


def server_buckets(client: httpx.Client, route: str = "/v1/pallets") -> dict[float, float]:
    """Cumulative bucket counts of the daemon's own handling time of `route` (pallet6d_http_request_seconds)."""
    out = {}
    for line in client.get("/metrics").text.splitlines():
        if line.startswith("pallet6d_http_request_seconds_bucket{") and f'route="{route}"' in line:
            le = line.split('le="')[1].split('"')[0]
            out[float("inf") if le == "+Inf" else float(le)] = float(line.split()[-1])
    return out


def bucket_quantile(before: dict[float, float], after: dict[float, float], q: float) -> float | None:
    """Upper bound (s) of the bucket holding quantile q of the requests between two scrapes."""
    counts = sorted((le, after[le] - before.get(le, 0.0)) for le in after)
    if not counts or counts[-1][1] <= 0:
        return None
    for le, c in counts:
        if c >= q * counts[-1][1]:
            return le
    return None


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(round(q / 100 * (len(s) - 1))))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="work folder: recording, config, log, results.json")
    ap.add_argument("--replay", type=Path, help="replay folder (default: generated in --out)")
    ap.add_argument("--bundle", default=str(REPO / "models" / "epal-default"))
    ap.add_argument("--precision", default="int8", choices=("int8", "fp32"))
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--poll-hz", type=float, default=2.0, help="requests per second per polling client")
    ap.add_argument("--rss-every-s", type=float, default=10.0)
    ap.add_argument("--port", type=int, default=18600)
    ap.add_argument("--cpus", default="", help="pin the daemon to these cores, e.g. 0,1 (taskset)")
    ap.add_argument("--max-rate-hz", type=float, default=0.0,
                    help="the daemon's camera.max_rate_hz (0: every frame it keeps up with)")
    args = ap.parse_args()

    args.out.mkdir(parents=True, exist_ok=True)
    replay = args.replay or make_replay(args.out)
    config = args.out / "serve.toml"
    # camera-frame poses: the replay has no calibration (the vehicle frame costs the API nothing more)
    config.write_text(f'[camera]\nsource = "replay:{replay}"\nmax_rate_hz = {args.max_rate_hz}\n'
                      f'[model]\nbundle = "{args.bundle}"\n'
                      f'precision = "{args.precision}"\n[api]\nport = {args.port}\n'
                      f'[output]\nframe = "camera"\n[snapshot]\ndir = "{args.out / "snapshots"}"\n')
    cmd = [sys.executable, "-m", "pallet6d.runtime.cli", "serve", "--config", str(config)]
    if args.cpus:
        cmd = ["taskset", "-c", args.cpus] + cmd
    log_path = args.out / "serve.log"
    total_s = 60 * args.minutes
    phases = [("warmup", 0.1), ("quiet", 0.2), ("load", 0.5), ("quiet_after", 0.2)]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    client = httpx.Client(base_url=f"http://127.0.0.1:{args.port}", timeout=30)
    t_start = time.monotonic()
    while True:
        try:
            if client.get("/readyz").status_code == 200:
                break
        except httpx.TransportError:
            pass
        if proc.poll() is not None or time.monotonic() - t_start > 300:
            print(log_path.read_text()[-3000:], file=sys.stderr)
            raise SystemExit("the daemon did not become ready")
        time.sleep(0.5)
    print(f"ready after {time.monotonic() - t_start:.1f} s; pid {proc.pid}", flush=True)

    rss: list[tuple[float, float, float]] = []   # (s, API process MB, its children MB)
    stop_rss = threading.Event()

    def sample_rss() -> None:
        t0 = time.monotonic()
        while not stop_rss.is_set():
            kids = sum(rss_mb(c) for c in children(proc.pid))
            rss.append((round(time.monotonic() - t0, 1), round(rss_mb(proc.pid), 1), round(kids, 1)))
            stop_rss.wait(args.rss_every_s)

    threading.Thread(target=sample_rss, daemon=True).start()
    results: dict = {"phases": {}, "config": vars(args) | {"out": str(args.out), "replay": str(replay)}}
    load = None
    try:
        for name, frac in phases:
            if name == "load":
                load = Load(client.base_url.__str__().rstrip("/"), args.clients, args.poll_hz)
                load.start()
            f0, t0, b0 = frames_total(client), time.monotonic(), server_buckets(client)
            time.sleep(frac * total_s)
            f1, t1, b1 = frames_total(client), time.monotonic(), server_buckets(client)
            if name == "load":
                load.stop()
                results["server_side_pallets_get"] = {
                    "p50_le_ms": 1000 * (bucket_quantile(b0, b1, 0.5) or float("nan")),
                    "p99_le_ms": 1000 * (bucket_quantile(b0, b1, 0.99) or float("nan"))}
            results["phases"][name] = {"seconds": round(t1 - t0, 1), "frames": f1 - f0,
                                       "loop_fps": round((f1 - f0) / (t1 - t0), 4)}
            print(f"{name}: {results['phases'][name]}", flush=True)
    finally:
        stop_rss.set()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(60)
    lat = load.latencies_ms if load else []
    quiet = [results["phases"][p]["loop_fps"] for p in ("quiet", "quiet_after")]
    warm_rss = [m + k for t, m, k in rss if t >= phases[0][1] * total_s]
    text = log_path.read_text(errors="replace")
    results.update({
        "pallets_get": {"requests": len(lat), "p50_ms": round(pct(lat, 50), 2), "p99_ms": round(pct(lat, 99), 2),
                        "max_ms": round(max(lat), 2) if lat else None,
                        "mean_ms": round(statistics.fmean(lat), 2) if lat else None,
                        "errors": load.errors if load else {}, "stream_events": load.events if load else 0},
        "loop_rate_change_under_load": round(results["phases"]["load"]["loop_fps"] / statistics.fmean(quiet) - 1, 4)
        if statistics.fmean(quiet) > 0 else None,
        "rss_mb": rss,
        "rss_after_warmup_mb_total": {"first": warm_rss[0] if warm_rss else None,
                                      "last": warm_rss[-1] if warm_rss else None,
                                      "max": max(warm_rss) if warm_rss else None},
        "tracebacks": text.count("Traceback"),
        "error_lines": sum(1 for x in text.splitlines() if x.startswith("ERROR")),
        "exit_status": rc, "load_average": os.getloadavg(),
    })
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(json.dumps({k: v for k, v in results.items() if k != "rss_mb"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

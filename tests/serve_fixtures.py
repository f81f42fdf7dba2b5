"""Helpers of the daemon tests: a replay recording made by the generator, a config file, and the real
`pallet6d serve` process on 127.0.0.1 (a free port), talked to with httpx."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

STARTUP_S = 120.0   # a loaded 2-core machine: imports, bundle, first frame


def make_replay(bop_root: Path, out: Path) -> Path:
    """The BOP dataset's frames as a replay folder (timestamps 1/30 s apart: camera rate)."""
    from pallet6d.runtime.cameras import ReplayWriter, open_source

    with open_source(f"bop:{bop_root}") as src, ReplayWriter(out) as writer:
        for frame in src:
            writer.write(frame)
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(path: Path, source: str, bundle: Path, port: int, mode: str = "continuous",
                 extra: str = "", output: str = 'frame = "camera"') -> Path:
    """A daemon config for the tests; `output`: the [output] section's lines."""
    path.write_text(f"""
[camera]
source = "{source}"
mode = "{mode}"
frame_timeout_s = 2.0
reconnect_min_s = 0.2
reconnect_max_s = 0.5

[model]
bundle = "{bundle}"
precision = "fp32"
threads = 1

[estimator]
score_threshold = 0.0
min_fit = 0.0
refine = false

[output]
{output}

[api]
port = {port}

[snapshot]
frames = 4
dir = "{path.parent / 'snapshots'}"
{extra}
""")
    return path


class Daemon:
    """A running `pallet6d serve` process. `stop()` sends SIGTERM and returns the exit status."""

    def __init__(self, config: Path, port: int, env: dict | None = None) -> None:
        self.port = port
        self.url = f"http://127.0.0.1:{port}"
        self.log_path = config.parent / f"serve-{port}.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "pallet6d.runtime.cli", "serve", "--config", str(config)],
                                     stdout=self._log, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})
        self.client = httpx.Client(base_url=self.url, timeout=30.0)

    def wait_healthy(self) -> "Daemon":
        self.wait(lambda: self.client.get("/healthz").status_code == 200, "healthz")
        return self

    def wait(self, predicate, what: str, timeout_s: float = STARTUP_S) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise AssertionError(f"pallet6d serve exited ({self.proc.returncode}) waiting for {what}:\n"
                                     f"{self.log()}")
            try:
                if predicate():
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {what}:\n{self.log()}")

    def metric(self, name: str, headers: dict | None = None) -> float:
        """The value of one sample of GET /metrics (e.g. 'pallet6d_frames_total')."""
        text = self.client.get("/metrics", headers=headers).text
        for line in text.splitlines():
            if line.startswith(name + " "):
                return float(line.split()[-1])
        raise AssertionError(f"{name} not in /metrics")

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")[-5000:]

    def stop(self, timeout_s: float = 30.0) -> int:
        self.client.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self._log.close()
        return rc

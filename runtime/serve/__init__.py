"""`pallet6d serve`: the forklift daemon.

One process: a camera loop thread (frame source -> `PalletEstimator` -> the latest result) and an HTTP API
(FastAPI on uvicorn) that reads what the loop publishes and never waits on it. Modules, one concern each:

- `config`: the TOML configuration, validated at start (`ServeConfig.load`).
- `loop`: `CameraLoop`, the thread that owns the source and the estimator (continuous and triggered modes,
  reconnects, latest-frame semantics).
- `floor_watch`: with a calibration, the check beside the loop that the floor still lies where it says.
- `snapshots`: the in-memory ring of recent frames, written as a replay recording on request.
- `metrics`: the Prometheus metrics (one registry per daemon, no global state).
- `app`: the HTTP API; `schema`: its response bodies as they appear in the OpenAPI description.
- `cli`: the `serve` subcommand (signals, systemd notification and watchdog).

Needs the `serve` extra: `pip install 'pallet6d[serve]'`.
"""

# Edge image: the forklift runtime (numpy + onnxruntime + OpenCV + camera SDKs + the daemon's HTTP stack) and
# the default model (pallet6d-models); no torch, no tests, results or training data. It installs the same two
# wheels that `make wheel-check` builds and checks, and its build runs the same checks: .ci/wheel_contents.py on
# the wheels, .ci/smoke-installed (bundle check, a short run and the daemon on a generated recording).
# Two targets: `daemon` (the default, the last stage) runs `pallet6d serve`; `edge` runs any subcommand.
#   docker build -t pallet6d .
#   docker run -d --restart=on-failure --network host --privileged -v /dev/bus/usb:/dev/bus/usb pallet6d
#   docker build --target edge -t pallet6d-edge .
#   docker run --rm --privileged -v /dev/bus/usb:/dev/bus/usb pallet6d-edge run --source realsense --int8
# docs/packaging.md: camera access for the non-root user, another bundle ($PALLET6D_BUNDLE); docs/daemon.md: the
# daemon's configuration (/etc/pallet6d/serve.toml, mount your own), its API and its bearer token.

# --- the wheels, built and checked as `make wheels` does -------------------------------------------------
FROM python:3.11-slim-bookworm AS wheels
# a C compiler for the runtime's kernels (runtime/kernels.c); the edge image gets the built wheel only
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY runtime runtime
COPY sim sim
COPY calib calib
COPY export export
COPY models models
COPY .ci/wheel_contents.py .ci/
RUN pip wheel --no-cache-dir --no-deps -w /wheels . ./models \
    && python .ci/wheel_contents.py /wheels

# --- the runtime image -----------------------------------------------------------------------------------
FROM python:3.11-slim-bookworm AS edge

# libusb: pyrealsense2 and depthai talk to the cameras over USB.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --create-home --uid 10001 --groups plugdev pallet6d \
    && mkdir -p /var/lib/pallet6d/snapshots && chown -R pallet6d /var/lib/pallet6d

# The wheels as `make wheel-check` installs them (with the serve extra), plus the camera SDKs as extras (the
# export extra never).
# depthai is about 350 MB installed: `--build-arg CAMERAS=realsense` for a RealSense-only forklift, or
# `--build-arg CAMERAS=` for an image that only replays recordings.
ARG CAMERAS=realsense,oakd
COPY --from=wheels /wheels /tmp/wheels
RUN pip install --no-cache-dir --disable-pip-version-check \
        "$(ls /tmp/wheels/pallet6d-*.whl)[serve${CAMERAS:+,$CAMERAS}]" /tmp/wheels/pallet6d_models-*.whl \
    && rm -rf /tmp/wheels

# onnxruntime sessions are built for 2 intra-op threads by default (the forklift computer's budget).
ENV OMP_NUM_THREADS=2

USER pallet6d
WORKDIR /home/pallet6d

# The build check, as CI runs it: the installed package, no torch, the default bundle, a short run, the daemon.
COPY .ci/smoke-installed /opt/pallet6d/smoke-installed
RUN /opt/pallet6d/smoke-installed /tmp/pallet6d-smoke && rm -rf /tmp/pallet6d-smoke

# Healthy while the installed runtime loads and the model bundle is intact (files, sha256, graph inputs and
# outputs). The daemon target probes its HTTP health endpoint instead.
HEALTHCHECK --interval=5m --timeout=60s --start-period=30s --retries=2 \
    CMD ["pallet6d", "bundle", "check", "--no-run"]

ENTRYPOINT ["pallet6d"]
CMD ["--help"]

# --- the daemon (default target) ---------------------------------------------------------------------------
FROM edge AS daemon

# The example configuration: RealSense, continuous mode, API on 127.0.0.1:8080 (with --network host the
# forklift's own processes reach it; another address needs a bearer token: docs/daemon.md). Mount another
# at /etc/pallet6d/serve.toml. The build checks that it is valid and that the bundle loads with it.
COPY deploy/serve.toml /etc/pallet6d/serve.toml
RUN pallet6d serve --config /etc/pallet6d/serve.toml --check

# Healthy while the daemon's HTTP server answers (GET /healthz); set PALLET6D_HEALTHZ when the config binds
# another port. Camera faults show in GET /readyz, not here: the daemon recovers from them itself.
ENV PALLET6D_HEALTHZ=http://127.0.0.1:8080/healthz
HEALTHCHECK --interval=30s --timeout=10s --start-period=120s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen(os.environ['PALLET6D_HEALTHZ'], timeout=5)"]

STOPSIGNAL SIGTERM
CMD ["serve", "--config", "/etc/pallet6d/serve.toml"]

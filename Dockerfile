# Edge image: the forklift runtime (numpy + onnxruntime + OpenCV + camera SDKs) and the default model
# (pallet6d-models); no torch, no tests, results or training data. It installs the same two wheels that
# `make wheel-check` builds and checks, and its build runs the same checks: .ci/wheel_contents.py on the wheels,
# .ci/smoke-installed (bundle check + a short run on a generated recording) in the finished image.
#   docker build -t pallet6d-edge .
#   docker run --rm --privileged -v /dev/bus/usb:/dev/bus/usb pallet6d-edge run --source realsense --int8
# docs/packaging.md: camera access for the non-root user, another bundle ($PALLET6D_BUNDLE).

# --- the wheels, built and checked as `make wheels` does -------------------------------------------------
FROM python:3.11-slim-bookworm AS wheels
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
FROM python:3.11-slim-bookworm

# libusb: pyrealsense2 and depthai talk to the cameras over USB.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --create-home --uid 10001 --groups plugdev pallet6d

# The wheels as `make wheel-check` installs them, plus the camera SDKs as extras (the export extra never).
# depthai is about 350 MB installed: `--build-arg CAMERAS=realsense` for a RealSense-only forklift, or
# `--build-arg CAMERAS=` for an image that only replays recordings.
ARG CAMERAS=realsense,oakd
COPY --from=wheels /wheels /tmp/wheels
RUN pip install --no-cache-dir --disable-pip-version-check \
        "$(ls /tmp/wheels/pallet6d-*.whl)${CAMERAS:+[$CAMERAS]}" /tmp/wheels/pallet6d_models-*.whl \
    && rm -rf /tmp/wheels

# onnxruntime sessions are built for 2 intra-op threads by default (the forklift computer's budget).
ENV OMP_NUM_THREADS=2

USER pallet6d
WORKDIR /home/pallet6d

# The build check, as CI runs it: the installed package, no torch, the default bundle, a short run.
COPY .ci/smoke-installed /opt/pallet6d/smoke-installed
RUN /opt/pallet6d/smoke-installed /tmp/pallet6d-smoke && rm -rf /tmp/pallet6d-smoke

# Healthy while the installed runtime loads and the model bundle is intact (files, sha256, graph inputs and
# outputs). A daemon image probes its HTTP health endpoint instead.
HEALTHCHECK --interval=5m --timeout=60s --start-period=30s --retries=2 \
    CMD ["pallet6d", "bundle", "check", "--no-run"]

ENTRYPOINT ["pallet6d"]
CMD ["--help"]

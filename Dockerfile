# Edge image: the forklift runtime only (numpy + onnxruntime + OpenCV + camera SDKs), no torch.
#   docker build -t pallet6d-edge .
#   docker run --rm --privileged -v /dev/bus/usb:/dev/bus/usb pallet6d-edge run --source realsense
FROM python:3.11-slim-bookworm

# libusb: pyrealsense2 and depthai talk to the cameras over USB.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/pallet6d
COPY pyproject.toml README.md ./
COPY runtime runtime
COPY sim sim
COPY calib calib
COPY export export
COPY models models
RUN pip install --no-cache-dir '.[realsense,oakd]' \
    && python -c "import pallet6d.runtime.cli"

# onnxruntime sessions are built for 2 intra-op threads by default (the forklift computer's budget).
ENV OMP_NUM_THREADS=2
ENTRYPOINT ["pallet6d"]
CMD ["--help"]

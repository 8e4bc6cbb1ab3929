# mapkit on a pinned Debian/Python base. Mirrors the README: scripts/setup.sh, then the tests.
# Build: docker build -t mapkit .   Run the tests: docker run --rm mapkit
# Mount the real data to also run the real-data tests: -v /path/to/shared:/shared:ro -e MAPKIT_SHARED_DATA=/shared/data
FROM python:3.11.7-slim-bookworm

# libusb-1.0-0 for open3d (also installed by scripts/setup.sh); libgomp1 and libgl1 for open3d's
# OpenMP kernels and its library load on a slim image
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 libgl1 libglib2.0-0 \
 && rm -rf /var/lib/apt/lists/*

# torch's CPU build (the learning extra) from PyTorch's CPU index: no CUDA packages in the image
ENV TORCH_INDEX=https://download.pytorch.org/whl/cpu

WORKDIR /src
COPY . /src
# the environment scripts/setup.sh makes (/src/.venv), first on PATH so that `mapkit` and `python` are its
RUN bash scripts/setup.sh
ENV PATH=/src/.venv/bin:$PATH

# the README's test command (the main job: docker run --rm mapkit .venv/bin/python pipelines/main.py --out /tmp/run)
CMD ["bash", "-c", "bash scripts/setup.sh && .venv/bin/python -m pytest -q"]

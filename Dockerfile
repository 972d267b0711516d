# One image for both daemons, `cuboidgen` and `cuboidtrain` (docker-compose.yml runs them).
#
#   docker build -t cuboid-fit:cpu .                                  CPU torch (the default)
#   docker build -t cuboid-fit:cuda --build-arg TORCH_VARIANT=cuda .  CUDA torch
#
# The CUDA wheels bring their own CUDA runtime (the nvidia-* pins in constraints.txt),
# so both variants build on the same slim Python; the host's NVIDIA Container Toolkit
# supplies the driver. BASE_IMAGE swaps the base (another mirror, or an nvidia/cuda
# image that has Python 3.11) without editing this file.
ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
ARG TORCH_VARIANT=cpu
ARG PYPI_INDEX=https://pypi.org/simple
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY constraints.txt ./
# torch first, in a layer of its own (gigabytes, rarely changed). The CPU index's
# 2.14.1+cpu satisfies constraints.txt's torch==2.14.1 (a local label matches) and sorts
# above PyPI's 2.14.1, so pip takes it and none of the CUDA wheels.
RUN case "$TORCH_VARIANT" in \
        cpu) torch_index=https://download.pytorch.org/whl/cpu ;; \
        cuda) torch_index=$PYPI_INDEX ;; \
        *) echo "TORCH_VARIANT=$TORCH_VARIANT: expected cpu or cuda" >&2; exit 1 ;; \
    esac \
    && pip install -c constraints.txt --index-url "$torch_index" --extra-index-url "$PYPI_INDEX" torch torchvision
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY cuboidgen ./cuboidgen
COPY cuboidtrain ./cuboidtrain
RUN pip install -c constraints.txt --index-url "$PYPI_INDEX" . \
    && cuboidgen --help > /dev/null && cuboidtrain --help > /dev/null

FROM ${BASE_IMAGE} AS runtime
ENV PATH=/opt/venv/bin:$PATH PYTHONUNBUFFERED=1
# /spool and /runs belong to the unprivileged user in the image, so the named volumes
# compose mounts there start out (empty) with that owner and the daemons can write them.
RUN useradd --create-home --uid 1000 cuboid \
    && mkdir -p /spool /runs && chown cuboid:cuboid /spool /runs
COPY --from=build /opt/venv /opt/venv
USER cuboid
WORKDIR /home/cuboid
# Where the daemons read and write unless told otherwise; every CUBOIDGEN_<OPTION> and
# CUBOIDTRAIN_<OPTION> is one option of `cuboidgen run` / `cuboidtrain run` (see --help).
ENV CUBOIDGEN_SPOOL=/spool CUBOIDTRAIN_SPOOL=/spool CUBOIDTRAIN_OUT=/runs/p1
CMD ["cuboidgen", "run"]

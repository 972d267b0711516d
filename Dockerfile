# One image for both daemons, `cuboidgen` and `cuboidtrain` (docker-compose.yml runs them).
#
#   docker build -t cuboid-fit:cpu .                                  CPU-only torch (the default)
#   docker build -t cuboid-fit:cuda --build-arg TORCH_VARIANT=cuda .  CUDA torch (PyPI's build)
#
# Build arguments (all optional; docs/operations.md: Containers):
#   BASE_IMAGE      a Debian-based image with Python 3.11 and its venv module (python:3.11-slim,
#                   or one built locally: ops/compose-smoke.sh does where no registry answers)
#   TORCH_VARIANT   cpu or cuda. cpu takes torch and torchvision from TORCH_INDEX and fails
#                   the build unless the installed torch is CPU-only (torch.version.cuda None).
#   TORCH_INDEX     where torch and torchvision come from (only those two): default PyTorch's
#                   CPU index for cpu, PYPI_INDEX for cuda. A mirror of either goes here.
#   PYPI_INDEX      the index for everything else (and torch's own dependencies)
#   BUILD_CA_CERTS  PEM text of extra CA certificates pip trusts, e.g. a TLS-intercepting
#                   proxy's: --build-arg BUILD_CA_CERTS="$(cat proxy-ca.crt)"
#   BUILD_PIP_CONF  text of a pip.conf for the build (timeouts, trusted hosts, extra options)
# The last two serve the build stage only: the runtime image holds neither.
#
# The CUDA wheels bring their own CUDA runtime (the nvidia-* wheels torch pins), so both
# variants build on the same slim Python; the host's NVIDIA Container Toolkit supplies the driver.
ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
ARG TORCH_VARIANT=cpu
ARG TORCH_INDEX=
ARG PYPI_INDEX=https://pypi.org/simple
ARG BUILD_CA_CERTS=
ARG BUILD_PIP_CONF=
# torch and torchvision as constraints.txt pins them (tests/test_compose.py keeps them equal).
ARG TORCH_VERSION=2.14.1
ARG TORCHVISION_VERSION=0.29.1
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_CERT=/opt/build/ca.pem \
    PIP_CONFIG_FILE=/opt/build/pip.conf PATH=/opt/venv/bin:$PATH
# Layer order: nothing from the build context comes before the torch layer, whose cache key
# is then this file and the arguments alone. `docker build` and `docker-compose build` (v1
# sends the context through docker-py, whose tar headers differ from the docker CLI's) hash
# copied files differently, so a COPY above the torch layer made each rebuild torch.
RUN set -e; mkdir -p /opt/build; \
    cat /etc/ssl/certs/ca-certificates.crt > /opt/build/ca.pem 2>/dev/null || true; \
    printf '%s\n' "$BUILD_CA_CERTS" >> /opt/build/ca.pem; \
    printf '%s\n' "$BUILD_PIP_CONF" > /opt/build/pip.conf; \
    python -m venv /opt/venv
# torch and torchvision alone from TORCH_INDEX (no fallback to another index: an unreachable
# CPU index fails here, in seconds, instead of bringing PyPI's CUDA build), then their
# dependencies from PYPI_INDEX (the installed +cpu build satisfies ==2.14.1 and stays).
RUN set -e; \
    case "$TORCH_VARIANT" in \
        cpu) index=${TORCH_INDEX:-https://download.pytorch.org/whl/cpu} ;; \
        cuda) index=${TORCH_INDEX:-$PYPI_INDEX} ;; \
        *) echo "TORCH_VARIANT=$TORCH_VARIANT: expected cpu or cuda" >&2; exit 1 ;; \
    esac; \
    pip install --retries 2 --no-deps --index-url "$index" \
        "torch==$TORCH_VERSION" "torchvision==$TORCHVISION_VERSION" \
    || { echo "TORCH_VARIANT=$TORCH_VARIANT: torch $TORCH_VERSION not installable from $index;" \
              "pass --build-arg TORCH_INDEX=<a reachable mirror of it>, or build TORCH_VARIANT=cuda" >&2; exit 1; }; \
    pip install --index-url "$PYPI_INDEX" "torch==$TORCH_VERSION" "torchvision==$TORCHVISION_VERSION"; \
    python -c "import sys, torch; cuda = torch.version.cuda; print('torch', torch.__version__, 'CUDA', cuda); \
sys.exit(0 if (cuda is None) == ('$TORCH_VARIANT' == 'cpu') else \
'TORCH_VARIANT=$TORCH_VARIANT but torch ' + torch.__version__ + ' has CUDA ' + str(cuda) + ': not this variant')"
WORKDIR /src
COPY constraints.txt pyproject.toml README.md ./
COPY shared ./shared
COPY cuboidgen ./cuboidgen
COPY cuboidtrain ./cuboidtrain
RUN pip install -c constraints.txt --index-url "$PYPI_INDEX" . \
    && cuboidgen --help > /dev/null && cuboidtrain --help > /dev/null \
    && python -c "import torch; assert (torch.version.cuda is None) == ('$TORCH_VARIANT' == 'cpu'), torch.__version__"

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

#!/usr/bin/env bash
# Install shadecap (editable) with its test extras into the current Python environment.
#
# torch is the one dependency that needs care: a plain `pip install torch` on Linux pulls the CUDA
# build and gigabytes of nvidia-* packages. On a machine without an NVIDIA GPU we therefore put the
# CPU build in place first — the local wheel when pip can find one (`torch==2.13.0` here), otherwise
# the PyTorch CPU index — and pip then treats the `torch>=2.2` requirement as satisfied.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
EXTRAS="${SHADECAP_EXTRAS:-test}"

if "$PY" -c "import torch" 2>/dev/null; then
    echo "[install] torch $("$PY" -c 'import torch; print(torch.__version__)') already present"
elif command -v nvidia-smi >/dev/null 2>&1; then
    echo "[install] NVIDIA GPU found: installing the default (CUDA) torch build"
    "$PY" -m pip install "torch>=2.2"
else
    echo "[install] no NVIDIA GPU: installing a CPU-only torch build"
    if ! "$PY" -m pip install "torch==${SHADECAP_TORCH_VERSION:-2.13.0}" --only-binary=:all: \
            --no-index ${PIP_FIND_LINKS:+--find-links "$PIP_FIND_LINKS"} 2>/dev/null; then
        "$PY" -m pip install torch --index-url https://download.pytorch.org/whl/cpu \
            || "$PY" -m pip install "torch==${SHADECAP_TORCH_VERSION:-2.13.0}"
    fi
fi
"$PY" -m pip install -e ".[${EXTRAS}]"

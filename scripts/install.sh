#!/usr/bin/env bash
# Install shadecap (editable) with its test extras into the current Python environment.
#
# torch is the one dependency that needs care: a plain `pip install torch` on Linux pulls the CUDA
# build and gigabytes of nvidia-* packages. On a machine without an NVIDIA GPU we therefore put a CPU
# build in place first — a local CPU wheel when pip's find-links hold one (e.g. torch-2.13.0+cpu),
# otherwise the PyTorch CPU index — and pip then treats the `torch>=2.2` requirement as satisfied.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
EXTRAS="${SHADECAP_EXTRAS:-test}"

local_cpu_wheel() {
    # Folders pip searches with --find-links: the environment variable and pip's configuration.
    local links dir
    links="${PIP_FIND_LINKS:-} $("$PY" -m pip config get global.find-links 2>/dev/null || true)"
    for dir in $links; do
        dir="${dir#file://}"
        ls "$dir"/torch-*+cpu-*.whl 2>/dev/null || true
    done | sort -V | tail -n 1
}

if "$PY" -c "import torch" 2>/dev/null; then
    echo "[install] torch $("$PY" -c 'import torch; print(torch.__version__)') already present"
elif command -v nvidia-smi >/dev/null 2>&1; then
    echo "[install] NVIDIA GPU found: installing the default (CUDA) torch build"
    "$PY" -m pip install "torch>=2.2"
else
    wheel="$(local_cpu_wheel)"
    if [ -n "$wheel" ]; then
        version="$(basename "$wheel" | cut -d- -f2)"
        version="${version%%+*}"
        echo "[install] no NVIDIA GPU: installing the local CPU wheel $(basename "$wheel")"
        "$PY" -m pip install "torch==${version}"
    else
        echo "[install] no NVIDIA GPU: installing torch from the PyTorch CPU index"
        "$PY" -m pip install torch --index-url https://download.pytorch.org/whl/cpu \
            --extra-index-url https://pypi.org/simple
    fi
fi
"$PY" -m pip install -e ".[${EXTRAS}]"
"$PY" -c "import torch; print('[install] torch', torch.__version__, '| CUDA available:', torch.cuda.is_available())"

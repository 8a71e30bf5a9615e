#!/usr/bin/env bash
# The GPU check of nirspi-pipe (issue 33) in one command, for a GPU machine that has Python but no
# network and not the project (docs/gpu.md):
#
#   bash benchmarks/gpu_check.sh fetch [DIR]   # here, with PyPI: the wheels the GPU machine lacks -> DIR
#   bash benchmarks/gpu_check.sh [DIR]         # there: install them from DIR if needed, run the check
#
# DIR defaults to .gpu/whl (carry it with the working tree). The run writes $OUT/summary.md,
# $OUT/summary.json and one log per step ($OUT defaults to ./gpu-check) within GPU_BUDGET seconds
# (default 330): `nirspi-bench gpu --write-table`. Without a GPU it runs the CPU parts and says
# which GPU parts it skipped.
set -u
here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PY=${PY:-python3}
mode=run
if [ "${1:-}" = fetch ]; then mode=fetch; shift; fi
DIR=${1:-$here/.gpu/whl}

if [ "$mode" = fetch ]; then
  # the interpreter of the GPU image (python 3.12 on the reference H200 machine:
  # shared/gpu-reference/README.md); override with GPU_PYTHON_VERSION
  pyver=${GPU_PYTHON_VERSION:-3.12}
  mkdir -p "$DIR"
  "$PY" -m pip wheel -q --no-deps -w "$DIR" "$here" || exit 1
  plats=(--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
  # what the CUDA image lacked there (it has numpy, scipy, pandas, numba, scikit-image, torch, pytest)
  # (binary wheels only: a wheel built here would be for this Python, not the GPU machine's)
  for pkg in "hydra-core>=1.3.2,<1.4" "omegaconf>=2.2,<2.4" pyopencl pytools platformdirs siphash24 miepython \
             hypothesis sortedcontainers attrs threadpoolctl typing-extensions matplotlib; do
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$pyver" "${plats[@]}" -d "$DIR" "$pkg" \
      || echo "gpu_check: no binary wheel of $pkg for Python $pyver" >&2
  done
  # sdist only: a pure-Python wheel built here works there
  "$PY" -m pip wheel -q --no-deps -w "$DIR" "antlr4-python3-runtime==4.9.3" || exit 1
  du -sh "$DIR"
  exit 0
fi

export OUT=${OUT:-$PWD/gpu-check}
mkdir -p "$OUT"
if ! "$PY" -c "import nirspi_pipe, hydra, pyopencl" 2>/dev/null; then
  site=${GPU_SITE:-/tmp/nirspi-gpu-site}
  if ! ls "$DIR"/*.whl >/dev/null 2>&1; then
    echo "gpu_check: nirspi_pipe does not import and $DIR has no wheels (run: bash $0 fetch on a machine with PyPI)" >&2
    exit 2
  fi
  # install what does not import already (the image's own numpy, torch, ... are kept)
  wheels=()
  for whl in "$DIR"/*.whl; do
    name=$(basename "$whl" | cut -d- -f1 | tr 'A-Z_.' 'a-z--')
    mod=${name//-/_}
    case $name in
      hydra-core) mod=hydra ;; antlr4-python3-runtime) mod=antlr4 ;; scikit-fmm) mod=skfmm ;;
      typing-extensions) mod=typing_extensions ;; nirspi-pipe) mod=nirspi_pipe ;;
    esac
    if [ "$mod" = nirspi_pipe ] || ! "$PY" -c "import $mod" 2>/dev/null; then wheels+=("$whl"); fi
  done
  timeout 150 "$PY" -m pip install -q --no-index --no-deps --no-compile --target "$site" "${wheels[@]}" || exit 1
  export PYTHONPATH=$site${PYTHONPATH:+:$PYTHONPATH}
  export PATH=$site/bin:$PATH
fi
cd "$here" || exit 1  # the parity tests are read from ./tests
exec timeout -k 10 $((${GPU_BUDGET:-330} + 20)) "$PY" -m nirspi_pipe.benchmarks.gpu --out "$OUT" \
  --budget "${GPU_BUDGET:-330}" --write-table

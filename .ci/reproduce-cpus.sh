#!/usr/bin/env bash
# The CI reproduction (+experiment=paper_ci, then `python -m nirspi_pipe.reproduce check`) under
# several OpenBLAS kernel sets and with numpy's dispatched SIMD paths switched off (issue 12), so a
# result that depends on the CPU's BLAS/SIMD kernels fails CI. Run from the repository root with the
# project installed in the active environment. Each kernel set is one sweep (about 1-4 min on 2
# cores) followed by its check; every set is tried, and the script fails if any check failed.
#
# A kernel set the CPU cannot execute (SkylakeX/Cooperlake need AVX-512: OpenBLAS would die of
# SIGILL) is skipped, loudly. OpenBLAS maps some names to the same kernels (Zen -> Haswell): each
# distinct set runs once.
set -uo pipefail
# NIRSPI_CI_SWEEPS: folder for the sweeps (default: a new temporary one); NIRSPI_CI_REFERENCE: the
# reference folder to check against (default: the installed experiments/reference/ci).
out=${NIRSPI_CI_SWEEPS:-$(mktemp -d -t nirspi-cpus-XXXX)}
mkdir -p "$out"
ref_args=()
if [ -n "${NIRSPI_CI_REFERENCE:-}" ]; then ref_args=(--reference "$NIRSPI_CI_REFERENCE"); fi
export OPENBLAS_NUM_THREADS=1

blas_core() {  # the kernel set OpenBLAS really uses for OPENBLAS_CORETYPE=$1 (empty: it crashed)
  local o
  o=$(OPENBLAS_VERBOSE=2 OPENBLAS_CORETYPE=$1 python -c 'import numpy as np; np.ones((64, 64)) @ np.ones((64, 64))' \
      2>&1) || return 0
  sed -n 's/^Core: //p' <<< "$o" | head -1
}

failed=() ; seen=" "
check_one() {  # name, then env assignments
  local name=$1; shift
  echo "== reproduction under $name ($*)"
  if ! env "$@" nirspi-run -m +experiment=paper_ci "hydra.sweep.dir=$out/$name" > "$out/$name.log" 2>&1; then
    echo "!!! the paper_ci sweep failed under $name: tail of $out/$name.log"; tail -5 "$out/$name.log"
    failed+=("$name"); return
  fi
  if ! env "$@" python -m nirspi_pipe.reproduce check "$out/$name" "${ref_args[@]}"; then
    failed+=("$name")
  fi
}

# NIRSPI_CI_DETECTED_CHECKED=1 (set by .ci/run): pytest's test_paper_ci already checked the kernel
# set OpenBLAS detects on this CPU, so it is not swept again.
if [ "${NIRSPI_CI_DETECTED_CHECKED:-0}" = 1 ]; then
  detected=$(blas_core "")
  if [ -n "$detected" ]; then seen="$seen$detected "; echo "== the detected $detected kernels: checked by pytest"; fi
fi

for want in Haswell SkylakeX Zen Sandybridge Prescott; do
  core=$(blas_core "$want")
  if [ -z "$core" ]; then
    echo "!!! OPENBLAS_CORETYPE=$want cannot run on this CPU ($(grep -qw avx512f /proc/cpuinfo || echo 'no AVX-512')): skipped"
    continue
  fi
  case "$seen" in *" $core "*) echo "== OPENBLAS_CORETYPE=$want uses the $core kernels, checked already"; continue;; esac
  seen="$seen$core "
  check_one "openblas-$core" "OPENBLAS_CORETYPE=$want"
done

# numpy: switch off every dispatched SIMD extension it has (AVX-512 and AVX2 paths on x86-64): the
# names must be ones this numpy dispatches, or it refuses them.
simd=$(python -c 'from numpy._core import _multiarray_umath as m; print(" ".join(getattr(m, "__cpu_dispatch__", [])))')
if [ -n "$simd" ]; then
  check_one numpy-baseline "NPY_DISABLE_CPU_FEATURES=$simd"
else
  echo "!!! numpy lists no dispatched SIMD extensions: the NPY_DISABLE_CPU_FEATURES run is skipped"
fi

if [ ${#failed[@]} -gt 0 ]; then
  echo "!!! reproduction check FAILED under: ${failed[*]} (sweeps in $out)"; exit 1
fi
echo "reproduction check passed under every other kernel set that runs here (sweeps in $out)"

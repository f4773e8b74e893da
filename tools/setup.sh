#!/usr/bin/env bash
# One-time (idempotent) set-up of physgs into the current Python environment.
# - keeps an installed torch (CPU or CUDA build): our dependency range accepts it, so pip
#   never swaps it for another build;
# - without torch, installs torch==2.13.0 first (on a machine that ships the CPU wheel locally,
#   as our CI does, this takes the CPU build; elsewhere choose your build per pytorch.org);
# - installs physgs (editable) with the test extras; gsplat is added where CUDA torch is present.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if ! "$PY" -c "import torch" 2>/dev/null; then
  "$PY" -m pip install -q "torch==2.13.0"
fi
stamp=.cache/setup.stamp
mkdir -p .cache
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || ! "$PY" -c "import physgs_steps, snakemake, taichi" 2>/dev/null; then
  "$PY" -m pip install -q -e ".[test]"
  if "$PY" -c "import torch,sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
    "$PY" -m pip install -q "gsplat>=1.4"
  fi
  touch "$stamp"
fi

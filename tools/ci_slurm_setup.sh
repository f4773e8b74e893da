#!/usr/bin/env bash
# Installs what tests/test_slurm.py needs, idempotently and quietly:
#  - SLURM and MUNGE from Debian's packages (slurmctld, slurmd, slurm-client, munge), skipped
#    when their programs are already there. Nothing is started or enabled: the test starts its
#    own throwaway one-node cluster and stops it again;
#  - the Snakemake SLURM executor plugin (pinned to a release that works with Snakemake 9).
# Usage (CI, before pytest): bash tools/ci_slurm_setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
PLUGIN="snakemake-executor-plugin-slurm==2.8.0"
export PATH="$PATH:/usr/sbin:/sbin"

missing=0
for prog in munged slurmctld slurmd sbatch srun squeue sinfo scontrol scancel; do
  command -v "$prog" >/dev/null 2>&1 || missing=1
done
if [ "$missing" -eq 1 ]; then
  if ! command -v apt-get >/dev/null 2>&1; then
    echo "ci_slurm_setup: SLURM is not installed and apt-get is not available; tests/test_slurm.py will be skipped (install slurmctld, slurmd, slurm-client and munge to run it)" >&2
    exit 0
  fi
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  log=$(mktemp)
  if ! { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq \
        --no-install-recommends slurmctld slurmd slurm-client munge; } >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    rm -f "$log"
    echo "ci_slurm_setup: apt-get failed" >&2
    exit 1
  fi
  rm -f "$log"
  echo "ci_slurm_setup: installed $(slurmctld -V 2>/dev/null || echo slurm) and munge"
fi

if ! "$PY" -c "import snakemake_executor_plugin_slurm" >/dev/null 2>&1; then
  "$PY" -m pip install -q --disable-pip-version-check "$PLUGIN"
  echo "ci_slurm_setup: installed $PLUGIN"
fi

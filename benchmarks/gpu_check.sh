#!/usr/bin/env bash
# Train and evaluate the default pipeline's policy on a CUDA device in a few minutes and print step time and latency
# per chunk (benchmarks/gpu_check.py says what runs and what is printed). Without CUDA it stops with one error line.
# Usage: benchmarks/gpu_check.sh [--workspace DIR] [--policies carp,next_token] [--epochs 5] [--num-processes 1]
set -euo pipefail
project="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
python="$project/.venv/bin/python"
if [[ ! -x "$python" ]]; then
    echo "error: gpu_check: $python not found; run \`make setup\` in $project first" >&2
    exit 1
fi
exec "$python" "$project/benchmarks/gpu_check.py" "$@"

#!/usr/bin/env bash
# The GPU check: pae-bench --only render_compare on the GPU (the tensor engine) and on the
# CPU, the PAE's and the kNN refinement's GPU times (paper Table 5), and the torch engine's
# render-and-compare answers on the GPU checked against the compiled CPU engine's on the
# same queries (pae.bench.gpu). Writes one JSON object (default outputs/bench/gpu.json);
# about 2-4 minutes on one GPU, stopped at 10. Without a CUDA device it prints
# "no CUDA device: skipped" and exits 0; exit 1: the engines disagree.
#
#   experiments/bench/gpu.sh [OUT.json]
set -euo pipefail
cd "$(dirname "$0")/../.."
python=.venv/bin/python
[ -x "$python" ] || python=python3
exec timeout 600 "$python" -m pae.bench.gpu --out "${1:-outputs/bench/gpu.json}"

#!/usr/bin/env bash
# Publish a training run's checkpoint as the shipped one and measure it (a point of the learning curve).
#
#   scripts/publish_checkpoint.sh RUN [STEPS]
#
# STEPS (default 4) is recorded in the checkpoint as its default number of DDIM steps on a CPU: choose it by
# measurement (python -m polycubenet.evaluate ... --steps S for a few S; the anchored model is best at 2-4).
#
# Writes polycubenet/checkpoints/polycubenet-cpu.pt (EMA weights in float16, the recipe, cumulative CPU-hours),
# then benchmarks/model_failures.py: held-out metrics (100 pairs of seed 2), the 10 example parts, the
# rejection reasons, docs/model_failures.png, and one line appended to benchmarks/results/learning_curve.jsonl.
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:?run folder with last.pt}
STEPS=${2:-4}
DATA=${DATA:-/work/data}
PY=${PY:-.venv/bin/python}
"$PY" -c "
from polycubenet.model.checkpoint import publish
publish('$RUN/last.pt', 'polycubenet/checkpoints/polycubenet-cpu.pt', extra={'default_steps': $STEPS})
"
ls -la polycubenet/checkpoints/polycubenet-cpu.pt
OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} "$PY" benchmarks/model_failures.py --checkpoint polycubenet/checkpoints/polycubenet-cpu.pt \
    --heldout "$DATA/heldout" --count 100 --n-out 4096 --steps "$STEPS"

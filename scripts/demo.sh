#!/usr/bin/env bash
# Set up pwm and run the main job on the embedded default (no servers): simulate a downlink
# of the `tiny` scenario and evaluate its starting model against the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-out/demo}"
.venv/bin/pwm simulate "$out" --scenario tiny --seed 1
.venv/bin/pwm evaluate "$out/downlink/start_model.obj" --truth "$out/truth" --json "$out/evaluation/start.json" --plots "$out/evaluation"

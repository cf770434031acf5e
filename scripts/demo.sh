#!/usr/bin/env bash
# Set up pwm and run the main job on the embedded default (no servers): simulate a downlink of
# the `tiny` scenario, ingest it into the SQLite catalog, refine the start model with its images,
# and measure the start and refined models against the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-out/demo}"
export PWM_DATA_DIR="$out/pwm-data"
.venv/bin/pwm simulate "$out" --scenario tiny --seed 1
.venv/bin/pwm ingest "$out/downlink"
.venv/bin/pwm refine "$out/downlink" --start "$out/downlink/start_model.obj" --out "$out/refined"
for model in downlink/start_model.obj refined/refined.ply; do
  name=$(basename "$(dirname "$model")")
  .venv/bin/pwm evaluate "$out/$model" --truth "$out/truth" --json "$out/evaluation/$name.json" --plots "$out/evaluation/$name"
done

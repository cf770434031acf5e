#!/usr/bin/env bash
# Set up pwm and run the main job on the embedded default (no servers): simulate a downlink of
# the `tiny` scenario, run it through the SQLite catalog in-process (ingest, refinement of the
# maplets its images see, fusion into a new model version on top of the start model), export
# the published version, and measure the start and refined models against the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-out/demo}"
export PWM_DATA_DIR="$out/pwm-data"
export PWM_DATABASE_URL=""  # the SQLite catalog in PWM_DATA_DIR, whatever the environment says
rm -rf "$out/pwm-data"  # a fresh catalog: the simulated products are new each time
# tiny is one small site: too small a footprint for photogrammetry to start from the PCK
# ellipsoid, so the downlink brings a start model, as a site campaign would have one
.venv/bin/pwm simulate "$out" --scenario tiny --seed 1 --with-start-model
.venv/bin/pwm run "$out/downlink" --workers 2
.venv/bin/pwm versions
.venv/bin/pwm diff 1 latest --png "$out/evaluation/diff.png"
mkdir -p "$out/refined"
.venv/bin/pwm export latest --format ply --out "$out/refined/refined.ply"
for model in downlink/start_model.obj refined/refined.ply; do
  name=$(basename "$(dirname "$model")")
  .venv/bin/pwm evaluate "$out/$model" --truth "$out/truth" --json "$out/evaluation/$name.json" --plots "$out/evaluation/$name"
done

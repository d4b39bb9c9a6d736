#!/usr/bin/env bash
# Copy the finished cells of a sweep (those with the sweep's done marker) into results/<name>/runs/:
# config.toml, progress.csv and sweep-done.json, so figures and tables redraw from the repository alone.
# Cells still running or stopped midway are left out (experiments/collect.sh copies those too).
#   experiments/collect-done.sh /work/study/runs/ten-seeds results/ten-seeds
set -euo pipefail
src=${1:?usage: collect-done.sh RUNS_DIR RESULTS_DIR}
dst=${2:?usage: collect-done.sh RUNS_DIR RESULTS_DIR}
for run in "$src"/*/; do
    [ -f "$run/sweep-done.json" ] || continue
    name=$(basename "$run")
    mkdir -p "$dst/runs/$name"
    cp "$run/config.toml" "$run/progress.csv" "$run/sweep-done.json" "$dst/runs/$name/"
done
echo "$(ls "$dst/runs" 2>/dev/null | wc -l) finished cells in $dst/runs"

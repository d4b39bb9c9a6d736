#!/usr/bin/env bash
# Copy a sweep's run records (config.toml, progress.csv, the sweep's done marker) into
# results/<name>/runs/, so the figures and tables can be redrawn from the repository alone.
#   experiments/collect.sh runs/tau-study results/tau-study
set -euo pipefail
src=${1:?usage: collect.sh RUNS_DIR RESULTS_DIR}
dst=${2:?usage: collect.sh RUNS_DIR RESULTS_DIR}
for run in "$src"/*/; do
    name=$(basename "$run")
    [ -f "$run/progress.csv" ] || continue
    mkdir -p "$dst/runs/$name"
    cp "$run/config.toml" "$run/progress.csv" "$dst/runs/$name/"
    [ -f "$run/sweep-done.json" ] && cp "$run/sweep-done.json" "$dst/runs/$name/"
done
echo "copied $(ls "$dst/runs" | wc -l) runs to $dst/runs"

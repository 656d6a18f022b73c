#!/usr/bin/env bash
# Runs the paper's 2D experiments with the command-line tool and prints a Markdown table of the JSON reports'
# per-stage timings (seconds), Dice and Jacobian range. Usage: bash scripts/benchmark-2d.sh [OUT_DIR] [THREADS]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bin="${DMR_BUILD_DIR:-$root/build}/bin"
out="${1:-$root/benchmark-output}"
threads="${2:-2}"
mkdir -p "$out"
"$bin/dmrGenerateShapes" --case epsilon --output-dir "$out/epsilon" >/dev/null
"$bin/dmrGenerateShapes" --case leaf --output-dir "$out/leaf" >/dev/null
run() { # name case iterations mesh
  "$bin/itkDynamicMeshRegistration" --fixed "$out/$2/fixed.nii.gz" --moving "$out/$2/moving.nii.gz" \
    --output-dir "$out/$1" --nodes 100 --iterations "$3" --mesh "$4" --regular-size 10 --threads "$threads" >/dev/null
  local dice
  dice=$("$bin/dmrImageDice" "$out/$1/warped.nii.gz" "$out/$2/fixed.nii.gz")
  # one table row from the report (no JSON tool needed: the report's keys are on known lines)
  awk -v name="$1" -v dice="$dice" '
    /"timing_s"/ { gsub(/[{},:"]/, " "); for (i = 1; i <= NF; ++i) t[$i] = $(i + 1) }
    /"jacobian_min"/ { gsub(/[,]/, ""); jmin = $2 } /"jacobian_max"/ { gsub(/[,]/, ""); jmax = $2 }
    END { printf "| %s | %.3f | [%.3g, %.3g] | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f |\n", name, dice, jmin, jmax,
          t["total"], t["registration"], t["initial_tessellation"], t["tessellation_optimization"],
          t["mesh_construction"], t["barycentric"] }' "$out/$1/report.json"
}
echo "| run | Dice | det J | total | registration | initial tessellation | tessellation optimisation | mesh construction | barycentric |"
echo "|---|---|---|---|---|---|---|---|---|"
run leaf-dynamic leaf 160 dynamic
run epsilon-dynamic epsilon 400 dynamic
run epsilon-regular epsilon 400 regular
run epsilon-fidelity epsilon 400 "$out/epsilon/fidelity_mesh.vtk"

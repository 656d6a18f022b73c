#!/usr/bin/env bash
# The 3D experiments of issue 3 with the command-line tools, on the real data in ../shared/data (see its README).
# Usage: bash scripts/benchmark-3d.sh [OUT_DIR] [THREADS] [ITERATIONS] [CASES...]
#   CASES: thorax256 (the CT resampled to 256x256x132 with a known breathing deformation: the paper's Table 1/2 size),
#          thorax (the full 512x512x141 CT, same deformation), copd2 (DIR-Lab copd2 lung masks, 300 landmarks,
#          dynamic mesh and a regular mesh of the same node count). Default: all three.
# Environment: DMR_REG_ARGS (extra options for every registration; default "--cvt-max-sweeps 20"),
#   DMR_ENERGY_RATIO (default 0.02, the paper's; the thorax runs of docs/benchmarks.md also use 0.2).
# Prints one Markdown table row per run from the JSON reports: per-stage times (s), peak RSS, dense error or TRE
# (mean / p95, mm, before -> after), Dice of the warped mask (copd2), det J range.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bin="${DMR_BUILD_DIR:-$root/build}/bin"
data="${DMR_SHARED_DATA_DIR:-$root/../shared/data}"
out="${1:-$root/benchmark-output/3d}"
threads="${2:-2}"
iterations="${3:-100}"
shift $(($# < 3 ? $# : 3))
cases=("$@")
[ ${#cases[@]} -gt 0 ] || cases=(thorax256 thorax copd2)
[ -d "$data" ] || { echo "no data folder $data (set DMR_SHARED_DATA_DIR)"; exit 1; }
mkdir -p "$out"
read -r -a extra <<<"${DMR_REG_ARGS:---cvt-max-sweeps 20}"
ratio="${DMR_ENERGY_RATIO:-0.02}"

row() { # name report [dice]
  awk -v name="$1" -v dice="${3:--}" '
    /"timing_s"/ { gsub(/[{},:"]/, " "); for (i = 1; i <= NF; ++i) t[$i] = $(i + 1) }
    /"(dense_error|tre)_initial_mm"/ { gsub(/[{},:"]/, " "); e0 = sprintf("%.2f / %.2f", $3, $7) }
    /"(dense_error|tre)_mm"/ { gsub(/[{},:"]/, " "); e1 = sprintf("%.2f / %.2f", $3, $7) }
    /"jacobian_min"/ { gsub(/[,]/, ""); jmin = $2 } /"jacobian_max"/ { gsub(/[,]/, ""); jmax = $2 }
    /"peak_rss_mb"/ { gsub(/[,]/, ""); rss = $2 }
    /"iterations":/ { gsub(/[,]/, ""); its = $2 } /"final_mesh_nodes"/ { gsub(/[,]/, ""); nodes = $2 }
    END { printf "| %s | %s | %s | %s -> %s | %s | [%.3g, %.3g] | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f |\n",
          name, nodes, its, e0, e1, dice, jmin, jmax, t["total"], t["initial_tessellation"],
          t["tessellation_optimization"], t["mesh_construction"], t["barycentric"], t["registration"], rss }' "$2"
}
register() { # name fixed moving [extra args...]
  local name=$1 fixed=$2 moving=$3
  shift 3
  "$bin/itkDynamicMeshRegistration" --fixed "$fixed" --moving "$moving" --output-dir "$out/$name" --nodes 3000 \
    --iterations "$iterations" --threads "$threads" --energy-ratio "$ratio" "${extra[@]}" "$@" >"$out/$name.log" 2>&1 || { cat "$out/$name.log"; exit 1; }
}

echo "| run | nodes | iterations | error mean / p95 mm (before -> after) | Dice | det J | total | initial tess. | tess. opt. | mesh | barycentric | registration | peak RSS MiB |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|---|"
for c in "${cases[@]}"; do
  case $c in
  thorax256 | thorax)
    size=()
    [ "$c" = thorax256 ] && size=(--size 256,256,132)
    [ -f "$out/$c-pair/truth-displacement.nii.gz" ] ||
      "$bin/dmrGenerateBreathing" --input "$data/thorax-ct-dicom" --output-dir "$out/$c-pair" "${size[@]}" >/dev/null
    p="$out/$c-pair"
    register "$c" "$p/fixed.nii.gz" "$p/moving.nii.gz" --fixed-mask "$p/lung-mask.nii.gz" \
      --truth-displacement "$p/truth-displacement.nii.gz" --intensity-window -1000,200
    row "$c breathing (dense error in the lungs)" "$out/$c/report.json"
    ;;
  copd2)
    d="$data/copd2-lung-masks"
    for mesh in dynamic regular; do
      register "copd2-$mesh" "$d/copd2_eBHCT_lungmask.nii.gz" "$d/copd2_iBHCT_lungmask.nii.gz" --mesh "$mesh" \
        --fixed-landmarks "$d/copd2_300_eBH_xyz_r1.txt" --moving-landmarks "$d/copd2_300_iBH_xyz_r1.txt"
      dice=$("$bin/dmrImageDice" "$out/copd2-$mesh/warped.nii.gz" "$d/copd2_eBHCT_lungmask.nii.gz")
      row "copd2 $mesh (TRE, 300 landmarks)" "$out/copd2-$mesh/report.json" "$dice"
    done
    dice0=$("$bin/dmrImageDice" "$d/copd2_iBHCT_lungmask.nii.gz" "$d/copd2_eBHCT_lungmask.nii.gz")
    echo "copd2 Dice of the masks before registration: $dice0"
    ;;
  *)
    echo "unknown case $c"; exit 2 ;;
  esac
done

#!/usr/bin/env bash
# GPU benchmarks of issue 4 (run on the GPU machine): the 2D paper pairs and the 3D thorax pairs with --backend cuda.
# Usage: bash scripts/benchmark-gpu.sh BIN_DIR DICOM_DIR OUT_DIR
#   BIN_DIR: itkDynamicMeshRegistration, dmrGenerateShapes, dmrGenerateBreathing, dmrImageDice (a CUDA build);
#   DICOM_DIR: ../shared/data/thorax-ct-dicom. Prints the report's backend, timing_s (paper breakdown + fem_solve),
#   gpu_memory_mb, det J range, dense error and peak RSS of every run, and the Dice of the 2D runs.
# The figures in docs/benchmarks.md were taken with the executables packed by ../shared/tools/device-pack and this
# script's steps (see the GPU section there).
set -uo pipefail
B=${1:?bin dir}
dicom=${2:?DICOM dir}
out=${3:?output dir}
mkdir -p "$out"
row() { grep -E '"backend"|"total"|"jacobian_m|gpu_memory|dense_error|"iterations"|peak_rss' "$1" | tr -d '\n' | tr -s ' '; echo; }
"$B/dmrGenerateShapes" --case epsilon --output-dir "$out/epsilon" >/dev/null
"$B/dmrGenerateShapes" --case leaf --output-dir "$out/leaf" >/dev/null
for c in "epsilon 400" "leaf 160"; do
  set -- $c
  "$B/itkDynamicMeshRegistration" --fixed "$out/$1/fixed.nii.gz" --moving "$out/$1/moving.nii.gz" --output-dir "$out/$1-cuda" \
    --nodes 100 --iterations "$2" --backend cuda >/dev/null || echo "FAIL $1"
  echo "$1 Dice $("$B/dmrImageDice" "$out/$1-cuda/warped.nii.gz" "$out/$1/fixed.nii.gz")"
  row "$out/$1-cuda/report.json"
done
three_d() { # name pair-dir [extra...]
  local name=$1 pair=$2
  shift 2
  "$B/itkDynamicMeshRegistration" --fixed "$pair/fixed.nii.gz" --moving "$pair/moving.nii.gz" --output-dir "$out/$name" \
    --nodes 3000 --iterations 100 --backend cuda --cvt-max-sweeps 20 --intensity-window -1000,200 \
    --fixed-mask "$pair/lung-mask.nii.gz" --truth-displacement "$pair/truth-displacement.nii.gz" "$@" >"$out/$name.log" 2>&1 ||
    { echo "FAIL $name"; tail -3 "$out/$name.log"; }
  echo "$name"
  row "$out/$name/report.json"
}
"$B/dmrGenerateBreathing" --input "$dicom" --output-dir "$out/t256" --size 256,256,132 >/dev/null
three_d thorax256 "$out/t256"
three_d thorax256-ratio0.2 "$out/t256" --energy-ratio 0.2
"$B/dmrGenerateBreathing" --input "$dicom" --output-dir "$out/full" >/dev/null
three_d thorax "$out/full"

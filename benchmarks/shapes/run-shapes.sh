#!/usr/bin/env bash
# Registers every pair of make-shapes.py with the tool's defaults (100 or 400 iterations, dynamic and regular mesh) and
# prints one line per run: exit code, the tool's summary and the Dice of the warped moving image with the fixed image.
# Usage: run-shapes.sh BIN_DIR OUT_DIR [extra tool options...]; DMR_SHAPES="case ..." runs only those cases
set -u -o pipefail
B=$1 O=$2; shift 2
here=$(cd "$(dirname "$0")" && pwd)
python3 "$here/make-shapes.py" "$O/data" || exit 1
for c in ${DMR_SHAPES:-star cshape ellipse aniso blobs sphere3d leaf3d rotsquare twodisks shrink dumbbell small oblique3d}; do
  threed=0; case $c in sphere3d | leaf3d | oblique3d) threed=1 ;; esac
  threshold=127.5; [ $threed = 1 ] && threshold=50
  for m in dynamic regular; do
    for it in 100 400; do
      [ $threed = 1 ] && [ "$it" = 400 ] && continue
      o=$O/$c-$m-$it
      "$B/itkDynamicMeshRegistration" --fixed "$O/data/$c/fixed.mha" --moving "$O/data/$c/moving.mha" --output-dir "$o" \
        --iterations "$it" --mesh "$m" "$@" >"$o.log" 2>&1
      rc=$?
      echo "$c $m $it rc=$rc $(grep '^registered' "$o.log" | sed -E 's/^registered .* -> [^ ]* in //') Dice before" \
        "$("$B/dmrImageDice" "$O/data/$c/fixed.mha" "$O/data/$c/moving.mha" $threshold 2>&1)" \
        "after $("$B/dmrImageDice" "$O/data/$c/fixed.mha" "$o/warped.nii.gz" $threshold 2>&1)"
    done
  done
done

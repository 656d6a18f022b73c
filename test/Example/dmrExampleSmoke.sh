#!/usr/bin/env bash
#
#
#  DynamicMeshRegistration
#
#  Licensed under the Apache License, Version 2.0 (the "License");
#  you may not use this file except in compliance with the License.
#  You may obtain a copy of the License at
#
#         http://www.apache.org/licenses/LICENSE-2.0.txt
#
#  Unless required by applicable law or agreed to in writing, software
#  distributed under the License is distributed on an "AS IS" BASIS,
#  WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
#  See the License for the specific language governing permissions and
#  limitations under the License.
#
#
# Command-line smoke tests of the example tools (STYLE.md section 6, last bullet). Run by ctest, one case per test:
#   dmrExampleSmoke.sh CASE WORKDIR REG GEN DICE CHECK VERSION [DATADIR]
# REG/GEN/DICE: itkDynamicMeshRegistration, dmrGenerateShapes, dmrImageDice; CHECK: dmrExampleCheck (test/Example);
# VERSION: the project version --version must print; DATADIR: the epsilon pair made by the "generate" case.
set -u -o pipefail

CASE=$1 W=$2 REG=$3 GEN=$4 DICE=$5 CHECK=$6 VERSION=$7 DATA=${8:-}
PREFIX="itkDynamicMeshRegistration: error:"
FAILURES=0

fail() { echo "FAIL: $*"; FAILURES=$((FAILURES + 1)); }
pass() { echo "ok: $*"; }
check() { # check "description" command...: the command must exit 0
  local what=$1; shift
  if "$@"; then pass "$what"; else fail "$what"; fi
}
finish() {
  if [ "$FAILURES" -ne 0 ]; then echo "$CASE: $FAILURES check(s) failed"; exit 1; fi
  echo "$CASE: all checks passed"; exit 0
}
nonempty() { [ -f "$1" ] && [ -s "$1" ]; }
# a JSON number of a top-level key of report.json (the tool writes one key per line)
json_number() { sed -n "s/^ *\"$2\": *\(-\{0,1\}[0-9][0-9.eE+-]*\) *,\{0,1\}$/\1/p" "$1"; }
json_string() { sed -n "s/^ *\"$2\": *\"\([^\"]*\)\" *,\{0,1\}$/\1/p" "$1"; }
is_number() { [[ $1 =~ ^-?[0-9]+(\.[0-9]*)?([eE][-+]?[0-9]+)?$ ]]; }
awk_true() { awk "BEGIN { exit !($1) }"; }
# listing (names, sizes, checksums) of a directory tree, hidden files included
snapshot() { (cd "$1" && find . -mindepth 1 -printf '%y %p %s\n' | sort && find . -type f -exec md5sum {} + | sort); }
# disk_mha PATH SHIFT HEADER_LINE: a 16 x 16 MetaImage of a disk (200 on 20) shifted by SHIFT pixels in x, with one
# more header line (e.g. its offset or spacing)
disk_mha() {
  { printf 'ObjectType = Image\nNDims = 2\nDimSize = 16 16\n%s\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n' "$3"
    awk -v s="$2" 'BEGIN { for (y = 0; y < 16; y++) for (x = 0; x < 16; x++)
      printf "%c", ((x - 7.5 - s) ^ 2 + (y - 7.5) ^ 2 < 20) ? 200 : 20 }'; } >"$1"
}
# end_within PID TRIES STEP: wait up to TRIES x STEP seconds for PID to end; ended=1 if it did, else it is killed
end_within() {
  ended=0
  for _ in $(seq "$2"); do
    kill -0 "$1" 2>/dev/null || { ended=1; return; }
    sleep "$3"
  done
  kill -s KILL "$1"
}

for tool in "$REG" "$GEN" "$DICE" "$CHECK"; do
  [ -x "$tool" ] || { echo "not an executable: $tool"; exit 1; }
done
rm -rf "$W" && mkdir -p "$W" || { echo "cannot create $W"; exit 1; }
cd "$W" || exit 1
export ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS=2

# run REG with the given arguments; stdout/stderr/exit code in $W/{stdout,stderr} and $RC
# (under `timeout` where available, so that a hang fails the test with a message instead of the ctest TIMEOUT)
run_reg() {
  # REG_PRELOAD: a library preloaded into REG only (not into `timeout`)
  local preload=()
  [ -z "${REG_PRELOAD:-}" ] || preload=(env "LD_PRELOAD=$REG_PRELOAD")
  # REG_LIMITS: shell commands (ulimit) that limit the tool only
  local limited=()
  [ -z "${REG_LIMITS:-}" ] || limited=(bash -c "$REG_LIMITS && exec \"\$@\"" limited)
  if command -v timeout >/dev/null; then
    timeout 90 "${preload[@]}" "${limited[@]}" "$REG" "$@" >"$W/stdout" 2>"$W/stderr"
    RC=$?
    [ "$RC" -ne 124 ] || echo "itkDynamicMeshRegistration did not finish within 90 s: $*"
  else
    "${preload[@]}" "${limited[@]}" "$REG" "$@" >"$W/stdout" 2>"$W/stderr"
    RC=$?
  fi
}

# expect_bad_input NAME ARGS...: the arguments (which must not include --output-dir) are bad input. Checked twice:
# into an output directory that does not exist (it must not be created) and into an existing directory holding a
# previous file (it must stay byte-for-byte unchanged). Each time: exit code != 0, nothing on stdout is required,
# exactly one line on stderr, starting with the error prefix.
expect_bad_input() {
  local name=$1; shift
  local fresh="$W/out-$name" existing="$W/existing-$name"
  local before after
  mkdir -p "$existing" && echo "previous run" >"$existing/previous.txt" && echo "stale" >"$existing/warped.nii.gz"
  before=$(snapshot "$existing")
  local parent_before parent_after
  parent_before=$(ls -A "$W")
  for dir in "$fresh" "$existing"; do
    run_reg "$@" --output-dir "$dir"
    local lines
    lines=$(wc -l <"$W/stderr")
    echo "[$name -> $(basename "$dir")] exit $RC, stderr: $(cat "$W/stderr")"
    if [ "$RC" -ne 0 ]; then pass "$name: non-zero exit ($RC)"; else fail "$name: exit code 0 on bad input"; fi
    if [ "$lines" -eq 1 ] && [ "$(tail -c 1 "$W/stderr" | od -An -c | tr -d ' ')" = '\n' ]; then
      pass "$name: exactly one line on stderr"
    else
      fail "$name: expected exactly one line on stderr, got $lines:"; sed 's/^/    | /' "$W/stderr"
    fi
    if [[ "$(head -n 1 "$W/stderr")" == "$PREFIX"* ]]; then
      pass "$name: stderr starts with '$PREFIX'"
    else
      fail "$name: stderr does not start with '$PREFIX'"
    fi
  done
  if [ ! -e "$fresh" ]; then pass "$name: output dir not created"; else fail "$name: output dir $fresh was created:"; ls -lA "$fresh"; fi
  after=$(snapshot "$existing")
  if [ "$before" = "$after" ]; then
    pass "$name: existing output dir unchanged"
  else
    fail "$name: existing output dir changed:"; diff <(echo "$before") <(echo "$after") | sed 's/^/    /'
  fi
  rm -f "$W/stdout" "$W/stderr"
  parent_after=$(ls -A "$W")
  if [ "$parent_before" = "$parent_after" ]; then
    pass "$name: nothing else written next to the output dir"
  else
    fail "$name: files appeared in $W:"; diff <(echo "$parent_before") <(echo "$parent_after") | sed 's/^/    /'
  fi
}

# check_run_outputs OUT ITERATIONS MESH_MODE NODES: the common checks on a successful run's output directory
check_run_outputs() {
  local out=$1 iterations=$2 mode=$3 nodes=$4 dimension=${5:-2} fixed=${6:-$DATA/fixed.nii.gz} report="$1/report.json"
  for f in warped.nii.gz displacement.nii.gz jacobian.nii.gz energy.csv mesh.pvd report.json; do
    check "$f exists and is non-empty" nonempty "$out/$f"
  done
  local vtus
  vtus=$(cd "$out" && ls mesh_[0-9][0-9][0-9][0-9].vtu 2>/dev/null)
  check "at least one mesh_NNNN.vtu written" test -n "$vtus"
  if compgen -G "$out/.dmr-partial-*" >/dev/null; then fail "staging folder left in $out"; else pass "no staging folder left"; fi

  # report.json
  if command -v jq >/dev/null; then check "report.json is valid JSON (jq)" jq -e . "$report" >/dev/null; fi
  for key in dimension nodes iterations ssd_initial ssd_final jacobian_min jacobian_max; do
    local v
    v=$(json_number "$report" "$key")
    if is_number "$v"; then pass "report: $key = $v"; else fail "report: numeric key '$key' missing or not a number ('$v')"; fi
  done
  for key in mesh_mode backend; do
    grep -Eq "^ *\"$key\": *\"[^\"]+\"" "$report" && pass "report: $key present" || fail "report: key '$key' missing"
  done
  local timing
  timing=$(sed -n 's/^ *"timing_s": *{\(.*\)} *,\{0,1\}$/\1/p' "$report")
  check "report: timing_s is an object" test -n "$timing"
  for key in total initial_tessellation tessellation_optimization mesh_construction barycentric registration \
             fem_solve registration_force registration_gather registration_update device_warm_up; do
    local v
    v=$(echo "$timing" | sed -n "s/.*\"$key\": *\([-0-9.eE+]*\).*/\1/p")
    if is_number "$v" && awk_true "$v >= 0"; then pass "report: timing_s.$key = $v"; else fail "report: timing_s.$key missing or negative ('$v')"; fi
  done
  check "report: dimension is $dimension" test "$(json_number "$report" dimension)" = "$dimension"
  check "report: nodes is $nodes" test "$(json_number "$report" nodes)" = "$nodes"
  check "report: iterations is $iterations" test "$(json_number "$report" iterations)" = "$iterations"
  check "report: stop_condition says the run completed its iterations" \
    test "$(json_string "$report" stop_condition)" = "completed the $iterations iterations"
  check "report: mesh_mode is $mode" test "$(json_string "$report" mesh_mode)" = "$mode"
  # solves factorised (small systems) take no conjugate-gradient products
  local direct products
  direct=$(json_number "$report" direct_solves); products=$(json_number "$report" cg_products)
  if is_number "$direct" && is_number "$products" && awk_true "$direct >= 0 && $direct <= $iterations" &&
     { [ "$direct" != "$iterations" ] || [ "$products" = 0 ]; }; then
    pass "report: direct_solves $direct of $iterations, cg_products $products"
  else
    fail "report: direct_solves ($direct) and cg_products ($products) do not fit $iterations iterations"
  fi
  local backend
  backend=$(json_string "$report" backend)
  check "report: backend is cpu or cuda ('$backend')" test "$backend" = cpu -o "$backend" = cuda
  local ssd0 ssd1 jmin jmax
  ssd0=$(json_number "$report" ssd_initial); ssd1=$(json_number "$report" ssd_final)
  jmin=$(json_number "$report" jacobian_min); jmax=$(json_number "$report" jacobian_max)
  if is_number "$ssd0" && is_number "$ssd1" && awk_true "$ssd1 < $ssd0"; then pass "ssd_final $ssd1 < ssd_initial $ssd0"; else fail "ssd_final ($ssd1) not < ssd_initial ($ssd0)"; fi
  if is_number "$jmin" && awk_true "$jmin > 0"; then pass "jacobian_min $jmin > 0"; else fail "jacobian_min ($jmin) not > 0"; fi
  if is_number "$jmin" && is_number "$jmax" && awk_true "$jmax >= $jmin"; then pass "jacobian_max >= jacobian_min"; else fail "jacobian_max ($jmax) < jacobian_min ($jmin)"; fi

  # energy.csv: a header and one row per iteration, numbered 1..K, every row as wide as the header
  local header rows
  header=$(head -n 1 "$out/energy.csv")
  check "energy.csv header starts with 'iteration,'" test "${header#iteration,}" != "$header"
  rows=$(tail -n +2 "$out/energy.csv" | grep -c .)
  check "energy.csv has $iterations data rows (got $rows)" test "$rows" = "$iterations"
  if awk -F, -v n="$iterations" 'NR == 1 { w = NF; next }
        NF != w || $1 != NR - 1 { bad = 1 }
        { for (i = 2; i <= NF; ++i) if ($i !~ /^-?[0-9.]+([eE][-+]?[0-9]+)?$/) bad = 1 }
        END { exit bad || NR - 1 != n }' "$out/energy.csv"; then
    pass "energy.csv rows are numbered 1..$iterations, numeric and as wide as the header"
  else
    fail "energy.csv rows malformed:"; sed 's/^/    | /' "$out/energy.csv"
  fi

  # mesh.pvd references existing, non-empty .vtu files, and every written .vtu is referenced
  local refs
  refs=$(grep -o 'file="[^"]*"' "$out/mesh.pvd" | sed 's/^file="//; s/"$//')
  check "mesh.pvd references at least one file" test -n "$refs"
  for r in $refs; do
    if nonempty "$out/$r" && grep -q '<VTKFile type="UnstructuredGrid"' "$out/$r"; then pass "mesh.pvd -> $r exists (UnstructuredGrid)"; else fail "mesh.pvd -> $r missing, empty or not a .vtu"; fi
  done
  for v in $vtus; do
    echo "$refs" | grep -qx "$v" && pass "$v is referenced by mesh.pvd" || fail "$v is not referenced by mesh.pvd"
  done
  check "mesh_0001.vtu (first iteration) written" nonempty "$out/mesh_0001.vtu"
  check "mesh_$(printf %04d "$iterations").vtu (last iteration) written" nonempty "$out/mesh_$(printf %04d "$iterations").vtu"

  # output images on the fixed image's grid
  for f in warped displacement jacobian; do
    check "$f.nii.gz has the fixed image's size/spacing/origin/direction" "$CHECK" same-grid "$fixed" "$out/$f.nii.gz"
  done
  check "warped.nii.gz is scalar" "$CHECK" components "$out/warped.nii.gz" 1
  check "jacobian.nii.gz is scalar" "$CHECK" components "$out/jacobian.nii.gz" 1
  check "displacement.nii.gz has $dimension components" "$CHECK" components "$out/displacement.nii.gz" "$dimension"
  check "jacobian.nii.gz: det J > 0 in every pixel" "$CHECK" min-above "$out/jacobian.nii.gz" 0
}

case "$CASE" in
help)
  for flag in --help -h; do
    run_reg $flag
    check "$flag exits 0" test "$RC" = 0
    check "$flag prints nothing on stderr" test ! -s "$W/stderr"
    check "$flag prints the usage line" grep -q '^usage: itkDynamicMeshRegistration --fixed F --moving M --output-dir D' "$W/stdout"
    for opt in --nodes --iterations --levels --mesh --lambda --mu --threads --save-mesh-every --report \
               --energy-ratio --alpha-factor --backend --version; do
      grep -q -- "$opt" "$W/stdout" && pass "$flag documents $opt" || fail "$flag does not document $opt"
    done
    check "$flag lists the outputs" grep -q 'warped.nii.gz.*displacement.nii.gz' "$W/stdout"
  done
  # --help wins even after other (valid or invalid) arguments, and writes nothing
  run_reg --fixed nowhere.nii.gz --output-dir "$W/out" --help
  check "--help after other options exits 0" test "$RC" = 0
  check "--help creates no output dir" test ! -e "$W/out"
  ;;
version)
  run_reg --version
  check "--version exits 0" test "$RC" = 0
  check "--version prints nothing on stderr" test ! -s "$W/stderr"
  check "--version prints one line" test "$(wc -l <"$W/stdout")" = 1
  echo "version: $(cat "$W/stdout")"
  check "--version prints 'itkDynamicMeshRegistration $VERSION (ITK x.y...'" \
    grep -Eq "^itkDynamicMeshRegistration ${VERSION//./\\.} \(ITK [0-9]+\.[0-9]+" "$W/stdout"
  ;;
generate)
  # the shared epsilon pair (a ctest fixture for the other cases)
  rm -rf "$DATA"
  "$GEN" --case epsilon --output-dir "$DATA"
  check "dmrGenerateShapes exits 0" test $? = 0
  for f in fixed.nii.gz moving.nii.gz fidelity_mesh.vtk; do check "$f written" nonempty "$DATA/$f"; done
  check "fixed and moving share a grid" "$CHECK" same-grid "$DATA/fixed.nii.gz" "$DATA/moving.nii.gz"
  check "fixed is 512x512" bash -c "'$CHECK' same-grid '$DATA/fixed.nii.gz' '$DATA/fixed.nii.gz' | grep -q '\[512, 512\]'"
  d_self=$("$DICE" "$DATA/fixed.nii.gz" "$DATA/fixed.nii.gz")
  d_pair=$("$DICE" "$DATA/fixed.nii.gz" "$DATA/moving.nii.gz")
  echo "Dice(fixed, fixed) = $d_self, Dice(fixed, moving) = $d_pair"
  check "dmrImageDice: Dice of an image with itself is 1" awk_true "$d_self == 1"
  check "dmrImageDice: circle vs epsilon overlap in (0, 1)" awk_true "$d_pair > 0 && $d_pair < 1"
  # dmrGenerateShapes into a path that is a file: ITK's NIfTI writer only printed that it could not open the files,
  # and the tool said it wrote them
  echo "a file" >"$W/not-a-directory"
  "$GEN" --case epsilon --output-dir "$W/not-a-directory" >"$W/stdout" 2>"$W/stderr"
  rc=$?
  check "dmrGenerateShapes into a file: exit 2 ($rc), one line on stderr ($(cat "$W/stderr")), nothing on stdout" \
    bash -c "test $rc = 2 && test \$(wc -l <'$W/stderr') = 1 && test ! -s '$W/stdout'"
  # the two pairs beyond the paper's; an unknown case is refused with one line and writes nothing
  for c in c star; do
    "$GEN" --case "$c" --output-dir "$W/$c" >/dev/null
    check "dmrGenerateShapes --case $c exits 0" test $? = 0
    check "$c: fixed and moving share a 256x256 grid" \
      bash -c "'$CHECK' same-grid '$W/$c/fixed.nii.gz' '$W/$c/moving.nii.gz' | grep -q '\[256, 256\]'"
    d_pair=$("$DICE" "$W/$c/fixed.nii.gz" "$W/$c/moving.nii.gz")
    check "$c: Dice(fixed, moving) = $d_pair in (0, 1)" awk_true "$d_pair > 0 && $d_pair < 1"
  done
  "$GEN" --case spiral --output-dir "$W/spiral" >"$W/stdout" 2>"$W/stderr"
  rc=$?
  check "dmrGenerateShapes --case spiral: exit 2 ($rc), one line on stderr ($(cat "$W/stderr")), no output" \
    bash -c "test $rc = 2 && test \$(wc -l <'$W/stderr') = 1 && test ! -e '$W/spiral'"
  # bad input to dmrImageDice: one line, exit 2 (a NaN threshold gave 1, images on different grids a Dice, a missing
  # file three lines, a NaN voxel was counted as outside)
  "$CHECK" make-2d "$W/other-grid.nii.gz"
  "$CHECK" make-nonfinite "$W/nonfinite.mha"
  for args in "$DATA/fixed.nii.gz $DATA/moving.nii.gz nan" "$DATA/fixed.nii.gz $DATA/moving.nii.gz 0.5x" \
              "$DATA/fixed.nii.gz $W/other-grid.nii.gz" "$DATA/fixed.nii.gz $W/missing.nii.gz" "$DATA/fixed.nii.gz" \
              "$W/other-grid.nii.gz $W/nonfinite.mha"; do
    # shellcheck disable=SC2086
    "$DICE" $args >"$W/stdout" 2>"$W/stderr"
    rc=$?
    check "dmrImageDice $(basename "${args##* }"): exit 2 ($rc), one line on stderr ($(cat "$W/stderr"))" \
      bash -c "test $rc = 2 && test \$(wc -l <'$W/stderr') = 1 && grep -q '^dmrImageDice: error: ' '$W/stderr'"
  done
  ;;
run-dynamic)
  out="$W/out"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" \
    --nodes 30 --iterations 5 --threads 2 --report "$W/copy-of-report.json"
  cat "$W/stdout" "$W/stderr"
  check "registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 5 dynamic 30
  check "--report FILE holds the same report as D/report.json" cmp -s "$W/copy-of-report.json" "$out/report.json"
  d_before=$("$DICE" "$DATA/fixed.nii.gz" "$DATA/moving.nii.gz")
  d_after=$("$DICE" "$DATA/fixed.nii.gz" "$out/warped.nii.gz")
  echo "Dice(fixed, moving) = $d_before, Dice(fixed, warped) = $d_after"
  check "Dice(fixed, warped) > Dice(fixed, moving)" awk_true "$d_after > $d_before"
  ;;
run-regular)
  out="$W/out"
  # --report inside the output directory, which the tool creates
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" \
    --nodes 30 --iterations 5 --threads 2 --mesh regular --report "$out/summary.json"
  cat "$W/stdout" "$W/stderr"
  check "registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 5 regular 30
  check "--report in the new output directory is written" cmp "$out/summary.json" "$out/report.json"
  # --report into a pipe through a link, as /dev/stdout is (a link to /proc/self/fd/1): the report is written into the
  # pipe, and neither the link nor the pipe is replaced by a file (as root, the tool replaced /dev/stdout itself)
  mkfifo "$W/report-pipe" && ln -s report-pipe "$W/report-link"
  cat "$W/report-pipe" >"$W/piped-report.json" &
  reader=$!
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-piped" \
    --nodes 30 --iterations 5 --threads 2 --mesh regular --report "$W/report-link"
  check "a report into a pipe: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
  sleep 0.5
  if kill -0 "$reader" 2>/dev/null; then # the tool never opened the pipe: release the reader
    timeout 5 bash -c ": >'$W/report-pipe'"
  fi
  wait "$reader"
  check "the pipe got the report" cmp "$W/piped-report.json" "$W/out-piped/report.json"
  check "the link is still a link" test -L "$W/report-link"
  check "the pipe is still a pipe" test -p "$W/report-pipe"
  ;;
run-initial-transform)
  # a translation as ITK's text transform file: the run starts from it, the report names it, and the border of the
  # displacement (where the mesh's nodes are fixed) keeps it exactly
  printf '#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_2_2\nParameters: 4 -3\nFixedParameters:\n' \
    >"$W/translation.tfm"
  out="$W/out"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" \
    --nodes 30 --iterations 5 --threads 2 --initial-transform "$W/translation.tfm"
  cat "$W/stdout" "$W/stderr"
  check "registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 5 dynamic 30
  check "report: initial_transform names the file and its kind" \
    grep -q '"initial_transform": {"file": "[^"]*translation.tfm", "kind": "transform TranslationTransform_double_2_2"}' \
    "$out/report.json"
  check "the displacement's border is the translation" "$CHECK" border-equals "$out/displacement.nii.gz" 4,-3
  # an earlier run's displacement as the start of another: it goes on where the first one ended
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/again" \
    --nodes 30 --iterations 3 --threads 2 --initial-transform "$out/displacement.nii.gz"
  check "a run from the first run's displacement exits 0" test "$RC" = 0
  first_final=$(json_number "$out/report.json" ssd_final)
  second_initial=$(json_number "$W/again/report.json" ssd_initial)
  check "it starts at the SSD the first run ended with ($first_final vs $second_initial)" \
    awk_true "$first_final > 0 && ($second_initial - $first_final)^2 <= (1e-6 * $first_final)^2"
  check "report: the kind is a displacement field" \
    grep -q '"kind": "displacement field"' "$W/again/report.json"
  # --inverse: the inverse transformation starts from the translation's inverse, lies on the fixed grid and undoes the
  # forward field (report: about 0.005 mm here; an inverse started from the identity would be off by the
  # translation, 5 mm), and the forward field is that of the run without it
  inv="$W/inverse"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$inv" \
    --nodes 30 --iterations 5 --threads 2 --initial-transform "$W/translation.tfm" --inverse
  cat "$W/stdout" "$W/stderr"
  check "--inverse: registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$inv" 5 dynamic 30
  check "--inverse: inverse-displacement.nii.gz lies on the fixed grid" \
    "$CHECK" same-grid "$DATA/fixed.nii.gz" "$inv/inverse-displacement.nii.gz"
  check "--inverse: the forward field is the one of the run without --inverse" \
    cmp <(zcat "$out/displacement.nii.gz") <(zcat "$inv/displacement.nii.gz")
  check "--inverse: stdout names the inverse" grep -q 'inverse-displacement.nii.gz' "$W/stdout"
  consistency=$(sed -n 's/.*"forward_then_inverse": {"mean": \([-0-9.eE+]*\),.*"inverse_then_forward": {"mean": \([-0-9.eE+]*\),.*/\1 \2/p' \
    "$inv/report.json")
  echo "inverse consistency means (mm): $consistency"
  check "report: inverse_consistency_mm means ($consistency) below 0.05 mm both ways" \
    awk -v c="${consistency:-x}" 'BEGIN { if (split(c, m, " ") != 2) exit 1; exit !(m[1] < 0.05 && m[2] < 0.05) }'
  # a later run into the same directory without --inverse does not leave the earlier run's inverse behind
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$inv" --nodes 30 --iterations 2 \
    --threads 2
  check "a run without --inverse into that directory exits 0" test "$RC" = 0
  check "and removes the earlier run's inverse-displacement.nii.gz" test ! -e "$inv/inverse-displacement.nii.gz"
  check "its report has no inverse_consistency_mm" bash -c "! grep -q inverse_consistency_mm '$inv/report.json'"
  # a displacement field as the initial transformation: the inverse starts from its fixed-point inverse, so the run
  # from the first run's field undoes its forward field as the run from the translation does
  finv="$W/field-inverse"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$finv" --nodes 30 \
    --iterations 3 --threads 2 --initial-transform "$out/displacement.nii.gz" --inverse
  cat "$W/stdout" "$W/stderr"
  check "--inverse from a displacement field: registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check "--inverse from a displacement field: its forward field is the one of the run without --inverse" \
    cmp <(zcat "$W/again/displacement.nii.gz") <(zcat "$finv/displacement.nii.gz")
  consistency=$(sed -n 's/.*"forward_then_inverse": {"mean": \([-0-9.eE+]*\),.*"inverse_then_forward": {"mean": \([-0-9.eE+]*\),.*/\1 \2/p' \
    "$finv/report.json")
  echo "inverse consistency means from the field (mm): $consistency"
  check "report: inverse_consistency_mm means from the field ($consistency) below 0.05 mm both ways" \
    awk -v c="${consistency:-x}" 'BEGIN { if (split(c, m, " ") != 2) exit 1; exit !(m[1] < 0.05 && m[2] < 0.05) }'
  # a folded displacement field has no inverse: refused with --inverse
  check "a folded field is written" "$CHECK" make-folded-field "$W/folded.nii.gz" "$DATA/fixed.nii.gz"
  rm -f "$W/stdout" "$W/stderr"
  expect_bad_input inverse-of-folded-field --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 \
    --iterations 2 --initial-transform "$W/folded.nii.gz" --inverse
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 \
    --initial-transform "$W/folded.nii.gz" --inverse --output-dir "$W/out-folded-message"
  check "the refusal says that the field is folded" grep -q 'displacement field is folded' "$W/stderr"
  rm -f "$W/stdout" "$W/stderr"
  ;;
bad-initial-transform)
  printf '#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_3_3\nParameters: 4 -3 1\nFixedParameters:\n' \
    >"$W/translation3d.tfm"
  printf '#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_2_2\nParameters: 4\nFixedParameters:\n' \
    >"$W/short.tfm"
  printf '#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_2_2\nParameters: 4000 0\nFixedParameters:\n' \
    >"$W/far.tfm"
  rm -f "$W/stdout" "$W/stderr" # (expect_bad_input compares the directory's listing)
  A=(--fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2)
  expect_bad_input initial-3d-transform "${A[@]}" --initial-transform "$W/translation3d.tfm"
  expect_bad_input initial-short-parameters "${A[@]}" --initial-transform "$W/short.tfm"
  expect_bad_input initial-maps-outside "${A[@]}" --initial-transform "$W/far.tfm"
  expect_bad_input initial-missing "${A[@]}" --initial-transform "$W/none.tfm"
  expect_bad_input initial-scalar-image "${A[@]}" --initial-transform "$DATA/fixed.nii.gz"
  ;;
run-fidelity)
  out="$W/out"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" \
    --nodes 30 --iterations 5 --threads 2 --mesh "$DATA/fidelity_mesh.vtk"
  cat "$W/stdout" "$W/stderr"
  check "registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 5 static 30
  ;;
run-unstructured-grid-mesh)
  # VTK unstructured grids as static meshes: the tool's own .vtu mesh of an earlier run (2D), a legacy .vtk of tetrahedra
  first="$W/first"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$first" --nodes 30 --iterations 3 \
    --threads 2
  check "first run exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  points=$(sed -n 's/.*NumberOfPoints="\([0-9]*\)".*/\1/p' "$first/mesh_0003.vtu" | head -n 1)
  out="$W/out"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" --nodes 30 --iterations 5 \
    --threads 2 --mesh "$first/mesh_0003.vtu"
  cat "$W/stdout" "$W/stderr"
  check "registration on the .vtu mesh exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 5 static 30
  check "the static mesh has the .vtu's $points nodes ($(json_number "$out/report.json" final_mesh_nodes))" \
    test "$(json_number "$out/report.json" final_mesh_nodes)" = "$points"
  check "make a 16x12x10 fixed volume" "$CHECK" make-3d "$W/f3.nii.gz"
  check "make a moving volume" "$CHECK" make-3d "$W/m3.nii.gz" 1
  # the box [0,15] x [0,11] x [0,9] mm: 12 tetrahedra from the faces' triangles to one inner node
  {
    printf '%s\n' "# vtk DataFile Version 3.0" "box" "ASCII" "DATASET UNSTRUCTURED_GRID" "POINTS 9 double"
    printf '%s\n' "0 0 0" "15 0 0" "0 11 0" "15 11 0" "0 0 9" "15 0 9" "0 11 9" "15 11 9" "7.8 5.3 4.6"
    printf '%s\n' "CELLS 12 60" "4 0 1 3 8" "4 0 3 2 8" "4 4 7 5 8" "4 4 6 7 8" "4 0 5 1 8" "4 0 4 5 8" \
      "4 2 3 7 8" "4 2 7 6 8" "4 0 2 6 8" "4 0 6 4 8" "4 1 5 7 8" "4 1 7 3 8" "CELL_TYPES 12"
    for _ in $(seq 12); do echo 10; done
  } >"$W/box.vtk"
  out3="$W/out3"
  run_reg --fixed "$W/f3.nii.gz" --moving "$W/m3.nii.gz" --output-dir "$out3" --iterations 5 --threads 2 \
    --mesh "$W/box.vtk"
  cat "$W/stdout" "$W/stderr"
  check "registration on the legacy .vtk tetrahedra exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check "the static mesh has the file's 9 nodes" test "$(json_number "$out3/report.json" final_mesh_nodes)" = 9
  ssd0=$(json_number "$out3/report.json" ssd_initial); ssd1=$(json_number "$out3/report.json" ssd_final)
  check "SSD falls ($ssd0 -> $ssd1)" awk_true "$ssd1 < $ssd0"
  ;;
run-png)
  # 2D PNG inputs (unsigned char): the tools read PNG, JPEG, TIFF, BMP, NRRD, ... besides NIfTI and MetaImage
  check "make a PNG fixed image" "$CHECK" make-2d-byte "$W/fixed.png"
  check "make a PNG moving image (square 2 pixels further along x)" "$CHECK" make-2d-byte "$W/moving.png" 2
  out="$W/out"
  run_reg --fixed "$W/fixed.png" --moving "$W/moving.png" --output-dir "$out" --nodes 12 --iterations 10 --threads 2
  cat "$W/stdout" "$W/stderr"
  check "registration of PNG images exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 10 dynamic 12 2 "$W/fixed.png"
  ssd0=$(json_number "$out/report.json" ssd_initial)
  ssd1=$(json_number "$out/report.json" ssd_final)
  check "SSD falls ($ssd0 -> $ssd1)" awk_true "${ssd1:-1e300} < ${ssd0:-0}"
  ;;
run-3d-default-nodes)
  # without --nodes a small volume gets one node per 8 voxels instead of the 3D default 3000 (16 x 12 x 10 = 1920
  # voxels: 240 nodes)
  check "make a 3D fixed image" "$CHECK" make-3d "$W/fixed3d.nii.gz"
  check "make a 3D moving image" "$CHECK" make-3d "$W/moving3d.nii.gz" 1
  out="$W/out"
  run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$out" --iterations 2 --threads 2
  cat "$W/stdout" "$W/stderr"
  check "registration without --nodes exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 2 dynamic 240 3 "$W/fixed3d.nii.gz"
  check "report: the GPU-order solve is the default" grep -Eq '^ *"gpu_order_solve": true,?$' "$out/report.json"
  # every system by conjugate gradients, in the GPU's order and on the assembled matrix: both register alike
  for solve in --gpu-order-solve --assembled-solve; do
    run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$W/cg$solve" --iterations 2 \
      --threads 2 --direct-solve-max-dofs 0 $solve
    check "$solve exits 0" test "$RC" = 0
    [ "$RC" = 0 ] || finish
    check "$solve: conjugate gradients ran ($(json_number "$W/cg$solve/report.json" cg_products) products)" \
      awk_true "$(json_number "$W/cg$solve/report.json" cg_products) > 0"
  done
  check "report: --assembled-solve says so" grep -Eq '^ *"gpu_order_solve": false,?$' "$W/cg--assembled-solve/report.json"
  check "report: --gpu-order-solve says so" grep -Eq '^ *"gpu_order_solve": true,?$' "$W/cg--gpu-order-solve/report.json"
  ssdA=$(json_number "$W/cg--gpu-order-solve/report.json" ssd_final)
  ssdB=$(json_number "$W/cg--assembled-solve/report.json" ssd_final)
  ssd0=$(json_number "$out/report.json" ssd_initial)
  check "both solves register alike (SSD $ssd0 -> $ssdA and $ssdB)" \
    awk_true "$ssdA < 0.95 * $ssd0 && $ssdB < 0.95 * $ssd0 && ($ssdA - $ssdB)^2 < (1e-4 * $ssdA)^2"
  ;;
run-itk-globals)
  # every ITK global is created on the main thread, also when the tool reads its inputs side by side on threads (ITK
  # 5.2 registers its globals in an unlocked std::map: a race there crashed or hung runs at exit). The watch library
  # (dmrItkGlobalsWatch.cxx, preloaded; its path in ITK_GLOBALS_WATCH) ends the tool with exit code 97 otherwise.
  [ -n "${ITK_GLOBALS_WATCH:-}" ] && [ -f "$ITK_GLOBALS_WATCH" ] || { fail "ITK_GLOBALS_WATCH is not a file"; finish; }
  check "make a 3D fixed image (MetaImage)" "$CHECK" make-3d "$W/fixed3d.mha"
  check "make a 3D moving image (MetaImage)" "$CHECK" make-3d "$W/moving3d.mha" 1
  check "make a 3D mask on a coarser grid" "$CHECK" make-3d-mask "$W/mask3d.nii.gz"
  run_reg --fixed "$W/fixed3d.mha" --moving "$W/moving3d.mha" --output-dir "$W/out1" --nodes 20 --iterations 2
  check "a first run for a displacement field exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  # four inputs read side by side: fixed, moving, mask and truth field
  REG_PRELOAD=$ITK_GLOBALS_WATCH run_reg --fixed "$W/fixed3d.mha" --moving "$W/moving3d.mha" --output-dir "$W/out" \
    --nodes 20 --iterations 2 --fixed-mask "$W/mask3d.nii.gz" --truth-displacement "$W/out1/displacement.nii.gz"
  cat "$W/stdout" "$W/stderr"
  check "the watched run exits 0 (97: a global created on another thread)" test "$RC" = 0
  check "the watch library was active and saw globals created" \
    grep -Eq '^itk-globals-watch: [1-9][0-9]* globals, all on the main thread$' "$W/stderr"
  [ "$RC" = 0 ] && check_run_outputs "$W/out" 2 dynamic 20 3 "$W/fixed3d.mha"
  ;;
run-thread-watch)
  # VTK writes the meshes on its sequential back-end: TBB (Debian VTK's default) starts no worker, since one that cannot
  # start ends the process by std::terminate with no message. The watch library (dmrThreadWatch.cxx, preloaded; its path
  # in THREAD_WATCH) counts the threads started, and those started by TBB.
  [ -n "${THREAD_WATCH:-}" ] && [ -f "$THREAD_WATCH" ] || { fail "THREAD_WATCH is not a file"; finish; }
  REG_PRELOAD=$THREAD_WATCH run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out" \
    --nodes 30 --iterations 3 --save-mesh-every 1
  cat "$W/stdout" "$W/stderr"
  check "the watched run exits 0" test "$RC" = 0
  check "it wrote a mesh per iteration" test -s "$W/out/mesh_0003.vtu"
  check "the watch library was active and saw threads started" \
    grep -Eq '^thread-watch: [1-9][0-9]* threads, [0-9]+ by TBB$' "$W/stderr"
  check "TBB started no thread" grep -Eq '^thread-watch: [0-9]+ threads, 0 by TBB$' "$W/stderr"
  ;;
run-3d)
  # a 3D pair with a mask on a coarser grid (resampled onto the fixed grid) and two landmark pairs
  check "make a 3D fixed image" "$CHECK" make-3d "$W/fixed3d.nii.gz"
  check "make a 3D moving image (cube 1 voxel further along x)" "$CHECK" make-3d "$W/moving3d.nii.gz" 1
  check "make a 3D mask on a coarser grid" "$CHECK" make-3d-mask "$W/mask3d.nii.gz"
  printf '6 5 4\n9 7 6\n' >"$W/fixed.txt"
  printf '7 5 4\n10 7 6\n' >"$W/moving.txt"
  out="$W/out"
  run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$out" --nodes 20 --iterations 5 \
    --threads 2 --fixed-mask "$W/mask3d.nii.gz" --fixed-landmarks "$W/fixed.txt" --moving-landmarks "$W/moving.txt"
  cat "$W/stdout" "$W/stderr"
  check "registration exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check_run_outputs "$out" 5 dynamic 20 3 "$W/fixed3d.nii.gz"
  check "a run that registers prints no 'hardly moved' note" bash -c "! grep -q 'hardly moved' '$W/stdout'"
  check "report: fixed_mask recorded" grep -q '"fixed_mask": "' "$out/report.json"
  # non-zero = inside, whatever the value: a soft mask's 0.5 and a label 256 were cast to 0 (outside) when the mask
  # was read as unsigned char, and a NaN was undefined
  for inside in 0.5 256; do
    check "make a mask that is $inside inside" "$CHECK" make-3d-mask "$W/mask-$inside.nii.gz" "$inside"
    run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$W/out-mask-$inside" --nodes 20 \
      --iterations 5 --threads 2 --fixed-mask "$W/mask-$inside.nii.gz"
    check "mask $inside inside: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
    check "mask $inside inside: the energies of the 0/1 mask's run" \
      cmp "$out/energy.csv" "$W/out-mask-$inside/energy.csv"
  done
  # a mask whose header differs from the fixed image's by a rounding (origin 2e-4 mm off, as float headers written by
  # other tools do) is taken: the run equals the one with the mask on the exact grid
  check "make a mask on the fixed grid" "$CHECK" make-3d-mask-fine "$W/mask-exact.nii.gz" 0
  check "make the same mask, its origin 2e-4 mm off" "$CHECK" make-3d-mask-fine "$W/mask-rounded.nii.gz" 0.0002
  for m in exact rounded; do
    run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$W/out-mask-$m" --nodes 20 \
      --iterations 5 --threads 2 --fixed-mask "$W/mask-$m.nii.gz"
    check "mask with the $m header: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
  done
  check "the rounded mask header: the energies of the exact mask's run" \
    cmp "$W/out-mask-exact/energy.csv" "$W/out-mask-rounded/energy.csv"
  tre0=$(sed -n 's/^ *"tre_initial_mm": {"mean": \([-0-9.eE+]*\),.*/\1/p' "$out/report.json")
  tre1=$(sed -n 's/^ *"tre_mm": {"mean": \([-0-9.eE+]*\),.*/\1/p' "$out/report.json")
  echo "TRE mean before $tre0, after $tre1"
  check "report: tre_initial_mm.mean is 1 mm (the landmarks are 1 voxel apart)" awk_true "${tre0:-0} == 1"
  check "report: tre_mm.mean is a number below the initial one" awk_true "${tre1:-99} < 1"
  check "report: the landmarks' shared offset, moving = fixed + 1 voxel along x" \
    grep -q '"tre_initial_mean_residual_mm": \[-1, 0, 0\],' "$out/report.json"
  res=$(sed -n 's/^ *"tre_mean_residual_mm": \[\([^]]*\)\],$/\1/p' "$out/report.json" | tr -d ,)
  check "report: tre_mean_residual_mm ($res) is no longer than tre_mm.mean" \
    awk -v t="${tre1:-0}" -v r="${res:-x}" 'BEGIN { if (split(r, v, " ") != 3) exit 1; exit !(sqrt(v[1]^2 + v[2]^2 + v[3]^2) <= t * (1 + 1e-5)) }'
  rss=$(json_number "$out/report.json" peak_rss_mb)
  check "report: peak_rss_mb is positive ('$rss')" awk_true "${rss:-0} > 0"
  check "report: moving_resampled is false for images on one grid" grep -q '"moving_resampled": false' "$out/report.json"
  # a moving image on another grid (the coarse mask grid) is resampled onto the fixed grid, not rejected (100 nodes:
  # with 20 every cell of this 16 x 12 x 10 volume touches the border, and a mesh without a free node is an error)
  run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/mask3d.nii.gz" --output-dir "$W/out-other-grid" --nodes 100 \
    --iterations 2 --threads 2
  check "moving image on another grid: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
  check "report: moving_resampled is true" grep -q '"moving_resampled": true' "$W/out-other-grid/report.json"
  check "report: moving_overlap is 1 (the coarse grid covers the fixed image)" \
    grep -q '"moving_overlap": 1,' "$W/out-other-grid/report.json"
  check "warped.nii.gz lies on the fixed grid" "$CHECK" same-grid "$W/fixed3d.nii.gz" "$W/out-other-grid/warped.nii.gz"
  # --intensity-window registers windowed copies; warped.nii.gz keeps the moving image's intensities (cube ~1.04-1.09)
  run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$W/out-window" --nodes 100 \
    --iterations 2 --threads 2 --intensity-window 0,0.5
  check "--intensity-window run: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
  dw=$("$DICE" "$W/out-window/warped.nii.gz" "$W/fixed3d.nii.gz" 1.05)
  check "warped.nii.gz keeps intensities above the window (Dice of {> 1.05} is $dw)" awk_true "${dw:-0} > 0.3"
  # an --energy-ratio far from the data: the safeguard rejects every step, the run "completes" and moved nothing; the
  # tool says so (the summary line alone looked like a registration)
  run_reg --fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --output-dir "$W/out-still" --nodes 100 \
    --iterations 2 --threads 2 --energy-ratio 1e6
  check "--energy-ratio 1e6: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
  check "--energy-ratio 1e6: the note says nothing moved ($(grep note "$W/stdout"))" \
    grep -q "note: the registration hardly moved anything: .* 2 of 2 steps were rejected" "$W/stdout"
  ;;
bad-3d-options)
  check "make a 3D fixed image" "$CHECK" make-3d "$W/fixed3d.nii.gz"
  check "make a 3D moving image" "$CHECK" make-3d "$W/moving3d.nii.gz" 1
  F3=(--fixed "$W/fixed3d.nii.gz" --moving "$W/moving3d.nii.gz" --nodes 20 --iterations 2)
  expect_bad_input window-reversed "${F3[@]}" --intensity-window 5,1
  expect_bad_input window-one-value "${F3[@]}" --intensity-window 5
  expect_bad_input window-constant "${F3[@]}" --intensity-window 2,3
  run_reg "${F3[@]}" --intensity-window 2,3 --output-dir "$W/out-window-constant"
  check "the message blames the window, not the image ($(cat "$W/stderr"))" \
    grep -q "the fixed image is constant inside --intensity-window 2,3 (its intensities lie in \[" "$W/stderr"
  rm -f "$W/stdout" "$W/stderr" # (expect_bad_input compares the directory's listing)
  printf '6 5 4\n9 7 6\n' >"$W/two.txt"
  printf '6 5 4\n' >"$W/one.txt"
  printf '6 5\n' >"$W/short.txt"
  printf '100 100 100\n' >"$W/far.txt"
  expect_bad_input landmarks-count "${F3[@]}" --fixed-landmarks "$W/two.txt" --moving-landmarks "$W/one.txt"
  expect_bad_input landmarks-malformed "${F3[@]}" --fixed-landmarks "$W/short.txt" --moving-landmarks "$W/one.txt"
  expect_bad_input landmarks-alone "${F3[@]}" --fixed-landmarks "$W/two.txt"
  expect_bad_input landmarks-outside "${F3[@]}" --fixed-landmarks "$W/far.txt" --moving-landmarks "$W/far.txt"
  "$CHECK" make-constant "$W/mask2d.nii.gz"
  expect_bad_input mask-2d "${F3[@]}" --fixed-mask "$W/mask2d.nii.gz"
  expect_bad_input mask-missing "${F3[@]}" --fixed-mask "$W/no-mask.nii.gz"
  expect_bad_input truth-2d "${F3[@]}" --truth-displacement "$W/mask2d.nii.gz"
  ;;
bad-missing-fixed)
  expect_bad_input missing-fixed --fixed "$W/does-not-exist.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2
  ;;
bad-dimension-mismatch)
  check "make a 3D image" "$CHECK" make-3d "$W/image3d.nii.gz"
  expect_bad_input fixed2d-moving3d --fixed "$DATA/fixed.nii.gz" --moving "$W/image3d.nii.gz" --nodes 30 --iterations 2
  ;;
bad-nodes-too-few)
  expect_bad_input nodes-3 --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 3 --iterations 2
  ;;
bad-nodes-too-many)
  # 512 x 512 = 262144 pixels
  expect_bad_input nodes-262145 --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 262145 --iterations 2
  ;;
bad-non-finite)
  check "make an image with a NaN pixel" "$CHECK" make-nonfinite "$W/nan.mha"
  check "make a 32x32 finite partner" "$CHECK" make-2d "$W/image2d.nii.gz"
  expect_bad_input nan-fixed --fixed "$W/nan.mha" --moving "$W/image2d.nii.gz" --nodes 10 --iterations 2
  expect_bad_input nan-moving --fixed "$W/image2d.nii.gz" --moving "$W/nan.mha" --nodes 10 --iterations 2
  expect_bad_input nan-mask --fixed "$W/image2d.nii.gz" --moving "$W/image2d.nii.gz" --fixed-mask "$W/nan.mha" \
    --nodes 10 --iterations 2
  run_reg --fixed "$W/nan.mha" --moving "$W/image2d.nii.gz" --output-dir "$W/out-nan" --nodes 10 --iterations 2
  check "the message names the image and the voxel ($(cat "$W/stderr"))" \
    grep -q "the fixed image has a non-finite intensity (nan) at voxel \[5, 3\]" "$W/stderr"
  run_reg --fixed "$W/image2d.nii.gz" --moving "$W/image2d.nii.gz" --fixed-mask "$W/nan.mha" --output-dir "$W/out-nan"
  check "the message names the mask and the voxel ($(cat "$W/stderr"))" \
    grep -q -- "--fixed-mask has a non-finite value at voxel \[5, 3\]" "$W/stderr"
  ;;
bad-thin-image)
  check "make a 16x12x3 fixed image" "$CHECK" make-3d-thin "$W/thin.nii.gz"
  check "make a 16x12x10 moving image" "$CHECK" make-3d "$W/image3d.nii.gz"
  expect_bad_input thin-fixed --fixed "$W/thin.nii.gz" --moving "$W/image3d.nii.gz" --nodes 10 --iterations 2
  run_reg --fixed "$W/thin.nii.gz" --moving "$W/image3d.nii.gz" --output-dir "$W/out-thin" --nodes 10 --iterations 2
  check "a usage error: exit code 2 (got $RC)" test "$RC" -eq 2
  check "the message names the axis ($(cat "$W/stderr"))" \
    grep -q "error: FEMRegistrationMethod: the fixed image needs at least 4 pixels along every axis; axis 2 has 3" "$W/stderr"
  ;;
bad-mesh-not-vtk-xml)
  echo "<VTKFile type=\"UnstructuredGrid\"><Piece" >"$W/broken.vtu"
  expect_bad_input broken-vtu --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --iterations 2 \
    --mesh "$W/broken.vtu"
  ;;
bad-mesh-without-free-node)
  # border nodes are fixed: a regular mesh of 2 nodes per axis, a static mesh with only border nodes or a dynamic mesh
  # of a few nodes (every cell on the border) moves nothing
  printf '%s\n' "# vtk DataFile Version 3.0" "corners" "ASCII" "DATASET POLYDATA" "POINTS 4 double" "0 0 0" "511 0 0" \
    "511 511 0" "0 511 0" "POLYGONS 2 8" "3 0 1 2" "3 0 2 3" >"$W/corners.vtk"
  expect_bad_input regular-size-2 --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --mesh regular \
    --regular-size 2 --iterations 2
  expect_bad_input corner-mesh --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --mesh "$W/corners.vtk" \
    --iterations 2
  # a dynamic mesh of 4 nodes: every cell touches the border (seen at the first mesh, after the outputs are staged)
  expect_bad_input dynamic-4-nodes --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 4 --iterations 2
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-regular" --mesh regular \
    --regular-size 2 --iterations 2
  check "regular size 2: a usage error, exit code 2 (got $RC)" test "$RC" -eq 2
  check "the message says why ($(cat "$W/stderr"))" \
    grep -q "RegularGridSize (2) must be 0 (from NumberOfNodes) or at least 3" "$W/stderr"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-corners" \
    --mesh "$W/corners.vtk" --iterations 2
  check "corner mesh: a usage error, exit code 2 (got $RC)" test "$RC" -eq 2
  check "the message says why ($(cat "$W/stderr"))" \
    grep -q "the static mesh has no free node: all its 4 nodes lie on the border" "$W/stderr"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-4-nodes" --nodes 4 \
    --iterations 2
  check "the message says why ($(cat "$W/stderr"))" \
    grep -q "the dynamic mesh has no free node: all 4 cells of the tessellation touch the border" "$W/stderr"
  ;;
bad-constant-image)
  check "make a constant image" "$CHECK" make-constant "$W/constant.nii.gz"
  check "make a 32x32 non-constant partner" "$CHECK" make-2d "$W/image2d.nii.gz"
  expect_bad_input constant-fixed --fixed "$W/constant.nii.gz" --moving "$W/image2d.nii.gz" --nodes 10 --iterations 2
  expect_bad_input constant-moving --fixed "$W/image2d.nii.gz" --moving "$W/constant.nii.gz" --nodes 10 --iterations 2
  ;;
bad-unknown-option)
  expect_bad_input unknown-option --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --no-such-option 1
  expect_bad_input unknown-last --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --frobnicate
  ;;
bad-iterations)
  expect_bad_input iterations-abc --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --iterations abc
  expect_bad_input iterations-5x --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --iterations 5x
  expect_bad_input iterations-empty --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --iterations ""
  # values beyond what the registration takes (unsigned int) would wrap around (4294967296 -> 0, 99999999999 -> over a
  # billion iterations), and beyond long they were clamped
  expect_bad_input iterations-2-32 --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --iterations 4294967296
  expect_bad_input iterations-huge --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" \
    --iterations 99999999999999999999999
  expect_bad_input regular-size-2-32 --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --mesh regular \
    --regular-size 4294967299
  # beyond 1e30 the products of the elastic constants, beta and the forces were not finite (--mu 1e308 ended with "the
  # images already match", --alpha-factor 1e300 with an infinite density)
  for flag in --lambda --mu --energy-ratio --alpha-factor; do
    expect_bad_input "${flag#--}-1e31" --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" "$flag" 1e31
  done
  expect_bad_input direct-solve-negative --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" \
    --direct-solve-max-dofs -1
  ;;
bad-missing-mesh)
  expect_bad_input missing-mesh --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 \
    --mesh "$W/no-such-mesh.vtk"
  ;;
bad-missing-argument)
  expect_bad_input no-moving --fixed "$DATA/fixed.nii.gz" --nodes 30 --iterations 2
  expect_bad_input no-value --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --iterations 2 --nodes
  ;;
bad-not-an-image)
  echo "not an image" >"$W/text.nii.gz"
  expect_bad_input text-as-image --fixed "$W/text.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2
  ;;
bad-output-is-a-file)
  echo "a file" >"$W/afile"
  before=$(md5sum "$W/afile")
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 --output-dir "$W/afile"
  echo "exit $RC, stderr: $(cat "$W/stderr")"
  check "non-zero exit" test "$RC" != 0
  check "one line on stderr" test "$(wc -l <"$W/stderr")" = 1
  check "stderr starts with '$PREFIX'" grep -q "^$PREFIX" "$W/stderr"
  check "the file is unchanged" test "$(md5sum "$W/afile")" = "$before"
  ;;
bad-output-replaces-input)
  # the run reads its inputs first, so an output named like an input went through and destroyed it: a --report naming
  # the fixed image overwrote it with the JSON, D/warped.nii.gz given as the moving image was replaced
  first="$W/first"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$first" --nodes 30 --iterations 3
  check "first run exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  cp "$DATA/fixed.nii.gz" "$W/fixed-copy.nii.gz"
  ln -s first "$W/link-to-first"
  rm -f "$W/stdout" "$W/stderr"
  kept=$(snapshot "$W")
  for args in \
    "moving-is-warped|--fixed $DATA/fixed.nii.gz --moving $first/warped.nii.gz --output-dir $first" \
    "moving-through-a-link|--fixed $DATA/fixed.nii.gz --moving $W/link-to-first/warped.nii.gz --output-dir $first/." \
    "out-dir-through-a-link|--fixed $DATA/fixed.nii.gz --moving $first/warped.nii.gz --output-dir $W/link-to-first" \
    "report-is-fixed|--fixed $W/fixed-copy.nii.gz --moving $DATA/moving.nii.gz --output-dir $W/out --report $W/fixed-copy.nii.gz" \
    "mesh-of-the-earlier-run|--fixed $DATA/fixed.nii.gz --moving $DATA/moving.nii.gz --output-dir $first --mesh $first/mesh_0003.vtu" \
    "mask-is-jacobian|--fixed $DATA/fixed.nii.gz --moving $DATA/moving.nii.gz --output-dir $first/../first --fixed-mask $first/jacobian.nii.gz" \
    "report-over-an-output|--fixed $DATA/fixed.nii.gz --moving $DATA/moving.nii.gz --output-dir $first --report $first/energy.csv"; do
    name=${args%%|*}
    read -r -a argv <<<"${args#*|}"
    run_reg --nodes 30 --iterations 3 "${argv[@]}"
    echo "[$name] exit $RC, stderr: $(cat "$W/stderr")"
    check "$name: refused as a usage error (exit 2)" test "$RC" = 2
    check "$name: one line saying what would be replaced" \
      bash -c "test \$(wc -l <'$W/stderr') = 1 && grep -q '^$PREFIX .*would replace' '$W/stderr'"
    rm -f "$W/stdout" "$W/stderr"
    check "$name: nothing in $W changed" test "$(snapshot "$W")" = "$kept"
  done
  ;;
run-again-in-the-same-directory)
  # the outputs of a second run in D replace the first run's; the first run's other numbered meshes went unremoved
  # beside the new mesh.pvd and passed for the second run's, and a killed run's staging folder stayed for good
  out="$W/out"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" --nodes 30 --iterations 6 \
    --save-mesh-every 2
  check "first run exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check "first run: meshes 1, 2, 4, 6" test "$(cd "$out" && echo mesh_*.vtu)" = \
    "mesh_0001.vtu mesh_0002.vtu mesh_0004.vtu mesh_0006.vtu"
  echo "the user's" >"$out/notes.txt" && echo "the user's" >"$out/mesh_final.vtu" && echo "x" >"$out/mesh_12.vtu"
  # a staging folder of a run that was killed (SIGKILL, the out-of-memory killer) and one of a run still going on
  sleep 0 & dead=$!
  wait "$dead"
  # (named .dmr-partial-HOST-PID: another host's folder on shared storage cannot be checked, and is kept)
  host=$(uname -n | tr -c 'A-Za-z0-9.\n' '_')
  mkdir -p "$out/.dmr-partial-$host-$dead" "$out/.dmr-partial-$host-$$" "$out/.dmr-partial-otherhost-$dead"
  echo "x" >"$out/.dmr-partial-$host-$dead/mesh_0001.vtu"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" --nodes 30 --iterations 3
  cat "$W/stdout" "$W/stderr"
  check "second run exits 0" test "$RC" = 0
  [ "$RC" = 0 ] || finish
  check "the staging folder of the ended run ($dead) is removed" test ! -e "$out/.dmr-partial-$host-$dead"
  check "the staging folder of the live process ($$) is kept" test -d "$out/.dmr-partial-$host-$$"
  check "another host's staging folder is kept" test -d "$out/.dmr-partial-otherhost-$dead"
  rmdir "$out/.dmr-partial-$host-$$" "$out/.dmr-partial-otherhost-$dead"
  check_run_outputs "$out" 3 dynamic 30
  check "only the second run's numbered meshes are left" test "$(cd "$out" && echo mesh_[0-9][0-9][0-9][0-9]*.vtu)" = \
    "mesh_0001.vtu mesh_0003.vtu"
  check "mesh.pvd names them" test "$(grep -o 'file="[^"]*"' "$out/mesh.pvd" | tr '\n' ' ')" = \
    'file="mesh_0001.vtu" file="mesh_0003.vtu" '
  check "files the tool does not write are kept" test -f "$out/notes.txt" -a -f "$out/mesh_final.vtu" -a -f "$out/mesh_12.vtu"
  ;;
concurrent-commit)
  # runs into the same D move their outputs in under an exclusive flock(2) on D, one after the other: two runs that
  # ended together renamed their files in turn (a mix of both could be left) and one's removal of stale numbered meshes
  # could take the other's. While another process holds D's lock, a finished run waits, then commits all its outputs.
  out="$W/out"
  mkdir -p "$out"
  command -v flock >/dev/null || { echo "flock(1) (util-linux) is missing"; exit 1; }
  # the holder: flock -o keeps the lock in the flock process only (its command does not inherit it)
  flock -o "$out" sh -c 'touch "$1/held"; while [ ! -e "$1/release" ]; do sleep 0.05; done' holder "$W" &
  holder=$!
  for _ in $(seq 200); do [ -e "$W/held" ] && break; sleep 0.05; done
  check "the holder has the lock" test -e "$W/held"
  "$REG" --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" --nodes 30 --iterations 3 \
    --save-mesh-every 1 >"$W/stdout" 2>"$W/stderr" &
  run=$!
  # its staging folder holds report.json, the last file written before the commit
  for _ in $(seq 1200); do
    if compgen -G "$out/.dmr-partial-*/report.json" >/dev/null || [ -e "$out/report.json" ] ||
      ! kill -0 "$run" 2>/dev/null; then break; fi
    sleep 0.05
  done
  check "the run staged its report" compgen -G "$out/.dmr-partial-*/report.json"
  sleep 1
  check "while D is locked, the finished run has committed nothing ($(cd "$out" && echo *))" \
    test ! -e "$out/warped.nii.gz" -a ! -e "$out/mesh_0001.vtu" -a ! -e "$out/report.json"
  check "and waits (still running)" kill -0 "$run"
  touch "$W/release"
  wait "$holder"
  wait "$run"
  RC=$?
  cat "$W/stdout" "$W/stderr"
  check "after the lock is released the run exits 0 (got $RC)" test "$RC" = 0
  check_run_outputs "$out" 3 dynamic 30
  check "all its meshes are there" test "$(cd "$out" && echo mesh_[0-9][0-9][0-9][0-9]*.vtu)" = \
    "mesh_0001.vtu mesh_0002.vtu mesh_0003.vtu"
  check "no staging folder is left" test -z "$(cd "$out" && compgen -G '.dmr-partial-*')"
  # SIGTERM while a run waits for the lock: it ends by the signal and D keeps the earlier run's outputs
  kept=$(snapshot "$out")
  rm -f "$W/held" "$W/release"
  flock -o "$out" sh -c 'touch "$1/held"; while [ ! -e "$1/release" ]; do sleep 0.05; done' holder "$W" &
  holder=$!
  for _ in $(seq 200); do [ -e "$W/held" ] && break; sleep 0.05; done
  "$REG" --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" --nodes 30 --iterations 2 \
    >"$W/stdout" 2>"$W/stderr" &
  run=$!
  for _ in $(seq 1200); do
    if compgen -G "$out/.dmr-partial-*/report.json" >/dev/null || ! kill -0 "$run" 2>/dev/null; then break; fi
    sleep 0.05
  done
  kill -s TERM "$run"
  end_within "$run" 200 0.05 # at most 10 s
  wait "$run"
  rc=$?
  touch "$W/release"
  wait "$holder"
  check "SIGTERM while waiting for the lock: ended within 10 s by the signal (status $rc)" test "$ended$rc" = 1143
  check "D keeps the earlier run's outputs, nothing staged is left" test "$(snapshot "$out")" = "$kept"
  ;;
interrupted)
  # Ctrl-C (SIGINT), SIGTERM (a scheduler's time limit) or SIGHUP during a run: the tool stops at its next step, removes
  # its staged outputs and ends by the signal. Before, the process died at once and left D/.dmr-partial-PID (with the
  # first mesh in it), and a D that it had created.
  previous="$W/previous"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$previous" --nodes 30 --iterations 2
  check "an earlier run exits 0" test "$RC" = 0
  rm -f "$W/stdout" "$W/stderr"
  kept=$(snapshot "$previous")
  set -m # job control: a background job keeps SIGINT (a non-interactive shell would start it with SIGINT ignored)
  for sig in INT TERM HUP; do
    for out in "$W/new-$sig" "$previous"; do
      "$REG" --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$out" --nodes 30 \
        --iterations 1000000 --threads 2 >"$W/stdout" 2>"$W/stderr" &
      pid=$!
      # never leave the run behind (it has its own process group), also when ctest stops this script at its timeout
      trap 'kill -s KILL "$pid" 2>/dev/null' EXIT
      trap 'kill -s KILL "$pid" 2>/dev/null; exit 1' TERM INT HUP
      # wait until the registration runs (its first mesh is staged), at most 60 s
      for _ in $(seq 600); do
        compgen -G "$out/.dmr-partial-*-$pid/mesh_0001.vtu" >/dev/null && break
        sleep 0.1
      done
      check "SIG$sig into $(basename "$out"): the registration was running" compgen -G "$out/.dmr-partial-*-$pid/mesh_0001.vtu"
      kill -s "$sig" "$pid"
      # the same request delivered twice at once (as `timeout` does, to the process and to its process group): before,
      # the second one ended the process by the default action and left its staged outputs behind
      kill -s "$sig" "$pid" 2>/dev/null
      end_within "$pid" 300 0.1 # at most 30 s
      wait "$pid"
      rc=$?
      echo "[SIG$sig into $(basename "$out")] exit $rc, stderr: $(cat "$W/stderr")"
      check "SIG$sig: the tool ended within 30 s" test "$ended" = 1
      check "SIG$sig: it ended by the signal (status $rc = 128 + $(kill -l "$sig"))" test "$rc" = $((128 + $(kill -l "$sig")))
      check "SIG$sig: one line on stderr saying so" \
        bash -c "test \$(wc -l <'$W/stderr') = 1 && grep -q '^itkDynamicMeshRegistration: interrupted (SIG$sig)' '$W/stderr'"
      if [ "$out" = "$previous" ]; then
        check "SIG$sig: the earlier run's outputs are unchanged, nothing staged is left" test "$(snapshot "$previous")" = "$kept"
      else
        check "SIG$sig: the output directory was not created" test ! -e "$out"
      fi
    done
  done
  set +m
  trap - EXIT TERM INT HUP
  rm -f "$W/stdout" "$W/stderr"
  ;;
# bug reproducers (disabled in CMakeLists.txt until the tool is fixed)
bad-report-path)
  expect_bad_input report-path --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 \
    --report "$W/no-such-dir/report.json"
  ;;
bad-mesh-not-a-mesh)
  expect_bad_input mesh-is-an-image --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 \
    --iterations 2 --mesh "$DATA/fixed.nii.gz"
  ;;
bad-truncated-image)
  head -c 3000 "$DATA/fixed.nii.gz" >"$W/truncated.nii.gz"
  expect_bad_input truncated-fixed --fixed "$W/truncated.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 \
    --iterations 2
  # found while ITK reads the file (the check runs beside the read): also for the mask
  expect_bad_input truncated-mask --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 \
    --iterations 2 --fixed-mask "$W/truncated.nii.gz"
  # uncompressed files that end early (ITK read them as far as they went) and a PNG cut in its first chunks (libpng
  # aborted the process)
  gzip -dc "$DATA/fixed.nii.gz" | head -c 200000 >"$W/truncated.nii"
  expect_bad_input truncated-nii --fixed "$W/truncated.nii" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2
  check "make a PNG image" "$CHECK" make-2d-byte "$W/whole.png"
  head -c 40 "$W/whole.png" >"$W/truncated.png"
  rm -f "$W/whole.png"
  expect_bad_input truncated-png --fixed "$W/truncated.png" --moving "$W/truncated.png" --nodes 30 --iterations 2
  ;;
bad-corrupt-header)
  # headers the image libraries refuse with lines of their own on stderr (NIfTI: "** ERROR: nifti_convert_nhdr2nim:
  # bad dim[0]"; MetaIO: four lines) before ITK throws: one line still, theirs inside ours
  gzip -dc "$DATA/fixed.nii.gz" >"$W/bad-dim.nii"
  printf '\011\000' | dd of="$W/bad-dim.nii" bs=1 seek=40 conv=notrunc 2>/dev/null # dim[0] = 9
  gzip -dc "$DATA/fixed.nii.gz" >"$W/bad-type.nii"
  printf '\011\003' | dd of="$W/bad-type.nii" bs=1 seek=70 conv=notrunc 2>/dev/null # datatype 777
  printf 'ObjectType = Image\nNDims = 2\nDimSize = 8 8\nElementSpacing = nan 1\nElementType = MET_UCHAR\n' >"$W/bad.mha"
  printf 'ElementDataFile = LOCAL\n' >>"$W/bad.mha"
  head -c 64 /dev/zero >>"$W/bad.mha"
  expect_bad_input nifti-dim --fixed "$W/bad-dim.nii" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2
  expect_bad_input nifti-datatype --fixed "$DATA/fixed.nii.gz" --moving "$W/bad-type.nii" --nodes 30 --iterations 2
  expect_bad_input nifti-mask --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 \
    --fixed-mask "$W/bad-dim.nii"
  expect_bad_input metaimage --fixed "$W/bad.mha" --moving "$W/bad.mha" --nodes 30 --iterations 2
  run_reg --fixed "$W/bad-dim.nii" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-dim" --nodes 30 --iterations 2
  check "the message holds the reader's reason ($(cat "$W/stderr"))" grep -q "bad dim\[0\]" "$W/stderr"
  ;;
bad-far-origin)
  # a header whose coordinates cannot tell the pixels apart (origin 1e16 mm, 1 mm pixels): the run reported a
  # "registration" with a folded field (det J down to -5.8) and exit 0; now a usage error that says why. An origin far
  # out but still fine (1e9 mm) registers.
  for o in 1e16 1e9; do
    disk_mha "$W/fixed-$o.mha" 0 "Offset = $o -$o"
    disk_mha "$W/moving-$o.mha" 1 "Offset = $o -$o"
  done
  expect_bad_input far-origin --fixed "$W/fixed-1e16.mha" --moving "$W/moving-1e9.mha" --nodes 8 --iterations 2
  run_reg --fixed "$W/fixed-1e16.mha" --moving "$W/moving-1e16.mha" --output-dir "$W/out-far" --nodes 8 --iterations 2
  check "far origin: a usage error, exit code 2 (got $RC)" test "$RC" -eq 2
  check "the message says why ($(cat "$W/stderr"))" \
    grep -q "the fixed image's physical coordinates reach 1e+16 mm, where double precision resolves only 2 mm" \
    "$W/stderr"
  run_reg --fixed "$W/fixed-1e9.mha" --moving "$W/moving-1e9.mha" --output-dir "$W/out-1e9" --nodes 24 --iterations 2
  check "origin 1e9 mm: registers ($(cat "$W/stderr"))" test "$RC" = 0
  ;;
bad-spacing)
  # a spacing whose fields a float cannot hold: 1e-45 mm "registered" with exit 0 and moved nothing (det J 1), 3e38 mm
  # ended in "alpha is -nan"; now a usage error that names the spacing. 1e-30 mm registers.
  for sp in 1e-45 3e38 1e-30; do
    disk_mha "$W/fixed-$sp.mha" 0 "ElementSpacing = $sp $sp"
    disk_mha "$W/moving-$sp.mha" 1 "ElementSpacing = $sp $sp"
  done
  expect_bad_input spacing --fixed "$W/fixed-1e-45.mha" --moving "$W/moving-1e-45.mha" --nodes 24 --iterations 2
  for sp in 1e-45:1e-45 3e38:3e+38; do
    run_reg --fixed "$W/fixed-${sp%:*}.mha" --moving "$W/moving-${sp%:*}.mha" --output-dir "$W/out-${sp%:*}" \
      --nodes 24 --iterations 2
    check "spacing ${sp%:*} mm: a usage error, exit code 2 (got $RC)" test "$RC" -eq 2
    check "the message names the spacing ($(cat "$W/stderr"))" grep -q \
      "the fixed image's spacing \[${sp#*:}, ${sp#*:}\] mm .* outside what the registration's single-precision fields" \
      "$W/stderr"
  done
  run_reg --fixed "$W/fixed-1e-30.mha" --moving "$W/moving-1e-30.mha" --output-dir "$W/out-1e-30" --nodes 24 \
    --iterations 2
  check "spacing 1e-30 mm: registers ($(cat "$W/stderr"))" test "$RC" = 0
  ;;
bad-thread-limit)
  # a process that may not start the threads it is asked for (here a virtual memory limit below the stacks of 128
  # threads, 8 MiB each; also a container's pids limit or ulimit -u): one line that says so and exit 1. ITK 5.2's thread
  # pool ended such a run by std::terminate with no message (exit 134), or crashed at exit after the message (139).
  export REG_LIMITS="ulimit -s 8192 && ulimit -v 400000"
  expect_bad_input thread-limit --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 \
    --iterations 2 --threads 128
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 --threads 128 \
    --output-dir "$W/out-limit"
  check "thread limit: exit code 1 (got $RC)" test "$RC" -eq 1
  check "the message says why ($(cat "$W/stderr"))" grep -q "cannot start 128 threads" "$W/stderr"
  unset REG_LIMITS
  ;;
bad-no-overlap)
  # a moving image that lies elsewhere in physical space (e.g. flipped, or another origin): an error, not a
  # registration to its background; a small overlap registers with a note
  { printf 'ObjectType = Image\nNDims = 2\nDimSize = 8 8\nOffset = 1000 1000\nElementType = MET_UCHAR\n'
    printf 'ElementDataFile = LOCAL\n'; awk 'BEGIN { for (i = 0; i < 64; i++) printf "%c", 65 + (i * 7) % 50 }'; } \
    >"$W/far.mha"
  expect_bad_input no-overlap --fixed "$DATA/fixed.nii.gz" --moving "$W/far.mha" --nodes 30 --iterations 2
  disk_mha "$W/disk.mha" 0 "Offset = 0 0"
  disk_mha "$W/disk-corner.mha" 0 "Offset = 14 14"
  expect_bad_input constant-overlap --fixed "$W/disk.mha" --moving "$W/disk-corner.mha" --nodes 8 --iterations 2
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$W/far.mha" --output-dir "$W/out-far" --nodes 30 --iterations 2
  check "no overlap: a usage error, exit code 2 (got $RC)" test "$RC" -eq 2
  check "the message says why ($(cat "$W/stderr"))" \
    grep -q "the moving image does not overlap the fixed image in physical space" "$W/stderr"
  # an overlap where the moving image is constant: the message said "the moving image has constant intensity 20",
  # which the image as read is not
  run_reg --fixed "$W/disk.mha" --moving "$W/disk-corner.mha" --output-dir "$W/out-constant" --nodes 8 --iterations 2
  check "the message says where the moving image is constant ($(cat "$W/stderr"))" grep -q \
    "the moving image has constant intensity 20 where it lies on the fixed image's grid (it covers 2 % of it)" \
    "$W/stderr"
  sed 's/^Offset = 1000 1000$/Offset = 508 508/' "$W/far.mha" >"$W/corner.mha"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$W/corner.mha" --output-dir "$W/out-corner" --nodes 30 --iterations 2
  check "small overlap: exit 0 ($(cat "$W/stderr"))" test "$RC" = 0
  check "small overlap: a note says how much of the fixed image the moving image covers" \
    grep -q "^note: the moving image covers only less than 1 % of the fixed image in physical space" "$W/stdout"
  overlap=$(json_number "$W/out-corner/report.json" moving_overlap)
  check "report: moving_overlap is small but positive ($overlap)" awk_true "${overlap:-0} > 0 && ${overlap:-1} < 0.01"
  ;;
bad-components)
  # images to register are scalar (or colour), a mask scalar, a truth field a vector of the dimension: ITK would
  # convert the others silently (a displacement field to one of its components, a scalar into both components)
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/field-run" --nodes 30 \
    --iterations 2
  check "a run for a 2D displacement field exits 0" test "$RC" = 0
  field="$W/field-run/displacement.nii.gz"
  rm -f "$W/stdout" "$W/stderr" # expect_bad_input checks that nothing appears beside its output directories
  expect_bad_input vector-moving --fixed "$DATA/fixed.nii.gz" --moving "$field" --nodes 30 --iterations 2
  expect_bad_input vector-mask --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2 \
    --fixed-mask "$field"
  expect_bad_input scalar-truth --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --nodes 30 \
    --iterations 2 --truth-displacement "$DATA/fixed.nii.gz"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-truth" --nodes 30 \
    --iterations 2 --truth-displacement "$DATA/fixed.nii.gz"
  check "the message says why ($(cat "$W/stderr"))" \
    grep -q -- "--truth-displacement must have 2 components per voxel (a displacement field)" "$W/stderr"
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$field" --output-dir "$W/out-vector" --nodes 30 --iterations 2
  check "the message says why ($(cat "$W/stderr"))" grep -q \
    "the moving image has 2 components per pixel and is not an RGB or RGBA colour image" "$W/stderr"
  # the run's own field is a valid truth field
  run_reg --fixed "$DATA/fixed.nii.gz" --moving "$DATA/moving.nii.gz" --output-dir "$W/out-own-truth" --nodes 30 \
    --iterations 2 --truth-displacement "$field"
  check "a 2-component truth field is taken ($(cat "$W/stderr"))" test "$RC" = 0
  ;;
bad-empty-directory)
  mkdir -p "$W/empty-dicom-dir"
  expect_bad_input empty-dicom-dir --fixed "$W/empty-dicom-dir" --moving "$DATA/moving.nii.gz" --nodes 30 --iterations 2
  ;;
*)
  echo "unknown case $CASE"; exit 2 ;;
esac
finish

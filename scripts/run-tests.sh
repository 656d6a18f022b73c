#!/usr/bin/env bash
# README command 2: set up, build, and run the whole test suite with ctest (unit + e2e; cuda tests skip without a GPU).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bash "$root/scripts/setup.sh"
bash "$root/scripts/build.sh" -DBUILD_TESTING=ON
cd "${DMR_BUILD_DIR:-$root/build}"
ctest --output-on-failure -j "$(nproc)" "$@"

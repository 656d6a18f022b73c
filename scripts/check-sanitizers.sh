#!/usr/bin/env bash
# Builds the project with AddressSanitizer and UndefinedBehaviorSanitizer (CPU only) and runs the CPU tests under
# them. Not part of CI (the build takes about 30 min on 2 cores); run it after changes to memory handling.
# Usage: scripts/check-sanitizers.sh [BUILD_DIR]   (default: build-sanitizers next to build/)
# Four tests cannot run in such a build and are left out: ExampleItkGlobalsOnMainThread and ExampleNoTbbThreads preload
# a library into the tool (the sanitizer runtime must come first), ExampleBadInputThreadLimit limits the tool's virtual
# memory (the sanitizers reserve terabytes of it) and InstalledPackageBuildsAndRunsAConsumer builds a consumer without
# the sanitizer runtime.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build="${1:-$root/build-sanitizers}"
flags="-fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=undefined"
launcher=()
command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
cmake -S "$root" -B "$build" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DDMR_USE_CUDA=OFF -DBUILD_TESTING=ON \
  "${launcher[@]}" -DCMAKE_CXX_FLAGS="$flags" -DCMAKE_C_FLAGS="-fsanitize=address,undefined" \
  -DCMAKE_EXE_LINKER_FLAGS="-fsanitize=address,undefined" -DCMAKE_SHARED_LINKER_FLAGS="-fsanitize=address,undefined" \
  -DCMAKE_MODULE_LINKER_FLAGS="-fsanitize=address,undefined"
cmake --build "$build" -j "$(nproc)"
export ASAN_OPTIONS=detect_leaks=0:halt_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
ctest --test-dir "$build" -j "$(nproc)" -LE cuda --timeout 600 --output-on-failure \
  -E '^(ExampleItkGlobalsOnMainThread|ExampleNoTbbThreads|ExampleBadInputThreadLimit|InstalledPackageBuildsAndRunsAConsumer)$'

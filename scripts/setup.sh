#!/usr/bin/env bash
# Installs every build and test dependency from Debian 12's packages (idempotent: skips what is installed).
set -euo pipefail
packages=(cmake g++ make ccache pkg-config
  libinsighttoolkit5-dev libvtk9-dev libcgal-dev libtet1.5-dev
  libgtest-dev libbenchmark-dev libgdcm-tools zlib1g-dev clang-format
  libpng-dev libjpeg-dev libtiff-dev) # the system libraries behind the tools' PNG, JPEG and TIFF readers
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing ${missing[*]}"
  sudo_cmd=""
  if [ "$(id -u)" -ne 0 ]; then sudo_cmd="sudo"; fi
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

#!/usr/bin/env bash
# Install the Debian packages listed in .ci/apt-packages.txt when they are missing.
set -euo pipefail
pkgs=$(grep -v '^\s*#' "$(dirname "$0")/apt-packages.txt" | xargs)
missing=$(for p in $pkgs; do dpkg -s "$p" >/dev/null 2>&1 || echo "$p"; done | xargs)
[ -z "$missing" ] && exit 0
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
echo "installing Debian packages: $missing"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing >/dev/null

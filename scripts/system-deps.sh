#!/usr/bin/env bash
# Installs the Debian packages the test suite needs, where they are missing.
#   libblas3, liblapack3 — OpenSeesPy's Linux wheel links libblas.so.3 / liblapack.so.3
#   chromium             — the live view's browser tests (headless)
# Called by the Makefile before the first install; runs `apt-get update` once, only when
# something is missing. Needs root (or sudo) on Debian/Ubuntu; elsewhere it says what to install.
set -euo pipefail
PACKAGES=(libblas3 liblapack3 chromium)
missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "error: missing system packages: ${missing[*]} (install them with your package manager)" >&2
  exit 1
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
echo "installing system packages: ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null

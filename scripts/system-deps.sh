#!/usr/bin/env bash
# Install the Debian packages canopy-kit needs, only where missing (fast when all present).
#   libusb-1.0-0      open3d's import needs it
#   chromium(+driver) the HTML report is checked in headless Chromium
#   gdal-bin          GDAL's ogrinfo checks trees.gpkg and the GeoJSON files (tests/test_ogr_validity.py)
set -euo pipefail
needed=(libusb-1.0-0 chromium chromium-driver gdal-bin)
missing=()
for pkg in "${needed[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
[ ${#missing[@]} -eq 0 ] && exit 0
echo "installing Debian packages: ${missing[*]}"
SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null

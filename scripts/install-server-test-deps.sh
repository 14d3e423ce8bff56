#!/usr/bin/env bash
# System packages for the benchmark server's slow tests (tests/server, marker `slow`):
#   chromium    - the browser test drives Debian's /usr/bin/chromium through Playwright
#                 (Playwright never downloads a browser here);
#   postgresql  - the PostgreSQL test starts a throwaway cluster with initdb/pg_ctl.
# Debian/Ubuntu, as root (CI) or through sudo. Tests skip cleanly when these are absent.
set -euo pipefail

packages=(chromium postgresql)
missing=()
for package in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" \
    || missing+=("$package")
done
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then
  sudo="sudo"
fi
export DEBIAN_FRONTEND=noninteractive
$sudo apt-get update -qq
$sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
# The Debian package starts a cluster of its own; the tests do not need it.
$sudo service postgresql stop >/dev/null 2>&1 || true

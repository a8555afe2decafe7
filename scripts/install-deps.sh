#!/usr/bin/env bash
# Installs what trn needs on Debian 12: GDAL (with its headers for the gdal
# crate), PROJ's data (the EGM96 geoid grid), SQLite, pkg-config, Python's venv,
# the DejaVu font (text of the `trn evaluate` plots).
# Skips apt entirely when everything is already there. Needs a Rust toolchain
# (cargo >= 1.85, e.g. from rustup) on the PATH.
set -euo pipefail
pkgs=(libgdal-dev gdal-bin proj-data libsqlite3-dev pkg-config python3-venv python3-pip fonts-dejavu-core time)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  echo "installing: ${missing[*]}" >&2
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
if ! command -v cargo >/dev/null 2>&1; then
  echo "error: cargo not found: install a Rust toolchain (rustup, Rust >= 1.85) and retry" >&2
  exit 1
fi

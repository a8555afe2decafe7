#!/usr/bin/env bash
# Create (or reuse) the Python virtual environment at <repo>/.venv with the
# pinned packages of scripts/requirements.txt. Idempotent and quick when the
# environment already matches: a stamp file holds the hash of the requirement
# list (and of the interpreter), so pip only runs when either changes.
#
# Usage: scripts/venv.sh            # then: .venv/bin/python scripts/fixtures/...
#        source "$(scripts/venv.sh --print)"   # prints the activate script path
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$repo/.venv"
req="$repo/scripts/requirements.txt"
stamp="$venv/.requirements.stamp"
python="${PYTHON:-python3}"

if [[ ! -x "$venv/bin/python" ]]; then
    echo "venv.sh: creating $venv" >&2
    "$python" -m venv "$venv"
fi

# The stamp covers the requirement list and the venv's interpreter version.
want="$( { cat "$req"; "$venv/bin/python" -c 'import sys; print(sys.version)'; } | sha256sum | cut -d' ' -f1)"
if [[ ! -f "$stamp" || "$(cat "$stamp")" != "$want" ]]; then
    echo "venv.sh: installing $(grep -vc '^\s*\(#\|$\)' "$req") pinned packages" >&2
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req"
    echo "$want" >"$stamp"
fi

if [[ "${1:-}" == "--print" ]]; then
    echo "$venv/bin/activate"
fi

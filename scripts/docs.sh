#!/usr/bin/env bash
# Builds kinema's documentation (docs/: user guide, numerics notes, API reference from the
# docstrings of the installed package) into build/docs/html, with warnings as errors.
# Installs what it needs first (scripts/setup.sh, the `docs` extra).
set -euo pipefail
cd "$(dirname "$0")/.."
[ "${KINEMA_SKIP_SETUP:-}" = 1 ] || bash scripts/setup.sh
out="${1:-build/docs}"
.venv/bin/python -m sphinx -q -W --keep-going -b html -d "$out/doctrees" docs "$out/html"
echo "[docs] $out/html/index.html"

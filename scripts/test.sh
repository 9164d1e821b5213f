#!/usr/bin/env bash
# Runs kinema's whole test suite: pytest, the documentation build (docs/, warnings as errors),
# then the C++ GoogleTest suite through CTest.
# Installs what it needs first (scripts/setup.sh). Options:
#   --slow   also run the tests marked slow (refinement sweeps, big grids)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh

marker=(-m "not slow")
[ "${1:-}" = "--slow" ] && marker=()

status=0
echo "== pytest"
# Run from tests/ against the installed package, not the source tree.
.venv/bin/python -m pytest "${marker[@]}" tests || status=$?

echo "== documentation (Sphinx, warnings as errors)"
KINEMA_SKIP_SETUP=1 bash scripts/docs.sh || status=$?

echo "== C++ tests (GoogleTest via CTest); the Google Benchmark programs are compiled too, so they cannot rot"
cmake -S . -B build/ctest -DCMAKE_BUILD_TYPE=Release -DKINEMA_BUILD_PYTHON=OFF \
  -DKINEMA_BUILD_TESTS=ON -DKINEMA_BUILD_BENCH=ON >/dev/null
cmake --build build/ctest -j 2
(cd build/ctest && ctest --output-on-failure -j 2) || status=$?

exit $status

#!/usr/bin/env bash
# kinema's main job: installs what it needs (scripts/setup.sh), then runs the demonstration
# (a Poisson solve around an obstacle, a heat-diffusion video, a work-precision study) and
# leaves its images, video and data files in the folder given (default: demo_output).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-demo_output}"
shift || true
.venv/bin/python -m kinema.demo --out "$out" "$@"

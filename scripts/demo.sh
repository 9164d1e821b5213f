#!/usr/bin/env bash
# kinema's main job: installs what it needs (scripts/setup.sh), then runs the shipped example
# scene "smoke_plume" end to end with the `kinema` command (frames, video, VTK image data,
# checkpoint) and the numerical demonstration (a Poisson solve around an obstacle, a
# heat-diffusion video, a work-precision study), leaving everything in the folder given
# (default: demo_output). Extra arguments go to `kinema run` (e.g. --frames 30).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-demo_output}"
shift || true
.venv/bin/kinema run smoke_plume --out "$out/smoke_plume" "$@"
.venv/bin/python examples/poisson_heat.py --out "$out/numerics"
echo "[kinema demo] the scene's video: $out/smoke_plume/video.mp4; numerics: $out/numerics"

#!/usr/bin/env bash
# Installs everything kinema needs on a Debian machine, idempotently: the system libraries
# (apt), a virtual environment in .venv, the Python build and test tools, and kinema itself.
# Quick when all is in place: each step is skipped when its inputs have not changed.
# Usage: source-free; call as `bash scripts/setup.sh [extra ...]` (extras from pyproject.toml).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
venv="$root/.venv"

apt_packages=(cmake g++ libeigen3-dev libsuitesparse-dev libopenblas-dev libgtest-dev libbenchmark-dev ffmpeg
  xvfb xauth libgl1 libgl1-mesa-dri libegl1 libglx-mesa0 libx11-6 libxcursor1 libxi6 libxinerama1 libxrandr2
  libxrender1)  # the viewer and its tests: a virtual display, Mesa's OpenGL, the X libraries GLFW opens
missing=()
for p in "${apt_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "[setup] apt-get install ${missing[*]}"
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment $venv"
  python3 -m venv "$venv"
fi
py="$venv/bin/python"

extras="test,demo,sweep,docs,viewer,surface,torch${1:+,$1}"
dep_stamp="$venv/.kinema-deps-$(echo "$extras" | tr ',' '-')"
dep_hash=$(sha1sum pyproject.toml | cut -d' ' -f1)
if [ ! -f "$dep_stamp" ] || [ "$(cat "$dep_stamp")" != "$dep_hash" ]; then
  echo "[setup] installing Python dependencies (extras: $extras)"
  "$py" -m pip install -q --upgrade pip >/dev/null
  "$py" -m pip install -q "scikit-build-core>=0.10" "pybind11>=2.12"
  # Install the extras' requirements without building kinema yet.
  reqs=$("$py" - "$extras" <<'PY'
import sys, tomllib
meta = tomllib.load(open("pyproject.toml", "rb"))["project"]
reqs = list(meta["dependencies"])
for extra in sys.argv[1].split(","):
    reqs += meta["optional-dependencies"].get(extra, [])
print("\n".join(reqs))
PY
)
  echo "$reqs" | "$py" -m pip install -q -r /dev/stdin
  echo "$dep_hash" > "$dep_stamp"
fi

# bench: fmm3dpy's PyPI wheel has no OpenMP; the same release's source (PyPI sdist) is built a
# second time with OpenMP and FMM3D's own makefile flags into .venv/peers (bench/fmm/fmm3d_bench.py).
fmm3d_omp="$venv/peers/fmm3dpy_openmp"
if [[ ",$extras," == *",bench,"* ]] && [ ! -f "$fmm3d_omp/.built" ]; then
  if ! command -v gfortran >/dev/null; then
    [ "$(id -u)" -eq 0 ] && sudo_cmd="" || sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq gfortran >/dev/null
  fi
  echo "[setup] building fmm3dpy 2.1.0 from its source release with OpenMP (about 5 minutes)"
  rm -rf "$fmm3d_omp"
  "$py" -m pip install -q --no-deps --no-binary fmm3dpy --target "$fmm3d_omp" "fmm3dpy==2.1.0" \
    "-Csetup-args=-Dfortran_args=-fopenmp -march=native -funroll-loops" "-Csetup-args=-Dc_link_args=-fopenmp"
  touch "$fmm3d_omp/.built"
fi

src_hash=$(find CMakeLists.txt pyproject.toml cmake cpp python -type f \( -name '*.py' -o -name '*.h' \
  -o -name '*.cpp' -o -name '*.txt' -o -name '*.cmake' -o -name '*.toml' -o -name '*.toml.in' \) \
  -not -path '*/__pycache__/*' | sort | xargs sha1sum | sha1sum | cut -d' ' -f1)
src_stamp="$venv/.kinema-src"
if [ ! -f "$src_stamp" ] || [ "$(cat "$src_stamp")" != "$src_hash" ]; then
  echo "[setup] building and installing kinema (C++ core, 1-2 minutes on first build)"
  # One wheel, built incrementally in build/, installed here and reused by tests/test_install.py
  # (a plain virtual environment with the base dependencies only).
  rm -rf build/dist
  "$py" -m pip wheel -q --no-build-isolation --no-deps -C build-dir="build/{wheel_tag}" -w build/dist .
  "$py" -m pip install -q --no-deps --force-reinstall build/dist/kinema-*.whl
  echo "$src_hash" > "$src_stamp"
fi

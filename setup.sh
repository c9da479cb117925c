#!/usr/bin/env bash
# Install everything visfly-dist needs on a Debian machine with Python 3.11, then run the main job
# (PPO on the navigation task: local scene workers spawned automatically, generated scenes).
#   bash setup.sh              install + train
#   VISFLY_SETUP_ONLY=1 bash setup.sh   install only (used by test.sh)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
PY="${PYTHON:-python3}"
export PIP_ROOT_USER_ACTION=ignore

# Headless OpenGL (EGL) for the pyrender backend: Mesa's llvmpipe on CPU, the vendor's EGL on a GPU.
egl_pkgs="libegl1 libegl-mesa0 libgl1-mesa-dri libgl1"
if ! dpkg -s $egl_pkgs >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $egl_pkgs >/dev/null
  else
    echo "setup.sh: please install the Debian packages: $egl_pkgs (needs root)" >&2
    exit 1
  fi
fi

# torch first and pinned: resolving stable-baselines3 first would pull a multi-GB CUDA build.
"$PY" -m pip install -q --disable-pip-version-check "torch==2.13.0"
"$PY" -m pip install -q --disable-pip-version-check -e ".[bench,dev,deploy]"

# The native packet tracer (raycast backend) against Debian's Embree 3. Optional: without it the
# raycast backend uses embreex, slower; set-up goes on and says so.
build_tracer() {
  if ! command -v g++ >/dev/null || ! command -v make >/dev/null || [ ! -e /usr/include/embree3/rtcore.h ]; then
    [ "$(id -u)" = 0 ] || return 1
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq g++ make libembree-dev >/dev/null
  fi
  make -s -C visfly_dist/scene_worker/native
}
if ! build_tracer >/dev/null 2>&1; then
  echo "setup.sh: native tracer not built (needs g++, make and libembree-dev, installed as root); raycast uses embreex and obstacle queries use FCL (slower)" >&2
fi
# Small native kernels of the training path (the image trunk's first pooling). Optional: without
# them the same functions run as torch operations, slower.
if ! make -s -C visfly_dist/training/native >/dev/null 2>&1; then
  echo "setup.sh: native training kernels not built (needs g++ and make); the image trunk uses torch's operations (slower)" >&2
fi
if ! make -s -C visfly_dist/dynamics/native >/dev/null 2>&1; then  # the CTBR step without gradients
  echo "setup.sh: native dynamics step not built (needs g++ and make); steps without gradients run in NumPy (slower)" >&2
fi
if ! make -s -C visfly_dist/tasks/native >/dev/null 2>&1; then  # navigation's per-step terms without gradients
  echo "setup.sh: native task terms not built (needs g++ and make); navigation's hooks run as torch operations (slower)" >&2
fi

if [ "${VISFLY_SETUP_ONLY:-0}" != "1" ]; then
  exec "$PY" -m visfly_dist.cli train navigation "$@"
fi

# For the test suite only: a single-node Slurm (the Slurm launcher's test starts its own daemons).
# Optional: without it that test is skipped with its reason.
slurm_pkgs="slurmctld slurmd slurm-client munge"
if [ "$(id -u)" = 0 ] && ! dpkg -s $slurm_pkgs >/dev/null 2>&1; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $slurm_pkgs >/dev/null) \
    || echo "setup.sh: Slurm packages not installed; the Slurm launcher test will be skipped" >&2
fi

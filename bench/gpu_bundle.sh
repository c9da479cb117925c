#!/usr/bin/env bash
# Carry visfly-dist to a GPU machine that reaches no package registry (Python 3.12, CUDA torch,
# numpy, scipy, matplotlib, msgpack ... already there), from a machine where setup.sh ran.
#   bash bench/gpu_bundle.sh prepare     here: wheels in .whl/, Embree and TBB in .gpu/, EGL loaders in .gl/
#   source bench/gpu_bundle.sh install   there: unpack them and export PYTHONPATH and the library paths
# .whl, .gl, .gpu and the built native libraries are ignored by git: name them among what travels.
set -u
mode="${1:-}"
wheels="eclipse-zenoh gymnasium farama-notifications stable_baselines3 sb3-contrib trimesh python-fcl pyrender pyglet freetype-py embreex pytest pluggy iniconfig pytest-timeout pygments"
if [ "$mode" = prepare ]; then
  mkdir -p .whl .gpu .gl
  pins=""
  for name in $wheels; do pins="$pins $name==$(python3 -m pip show "$name" | awk '/^Version/{print $2}')"; done
  # shellcheck disable=SC2086
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl $pins
  python3 -m pip wheel -q --no-deps "PyOpenGL==$(python3 -m pip show PyOpenGL | awk '/^Version/{print $2}')" -w .whl
  xz -6 -c "$(readlink -f /usr/lib/x86_64-linux-gnu/libembree3.so.3)" > .gpu/libembree3.so.3.xz
  cp -L /lib/x86_64-linux-gnu/libtbb.so.12 .gpu/
  (cd .gl && apt-get download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
  du -sh .whl .gpu .gl
elif [ "$mode" = install ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl
  xz -dc .gpu/libembree3.so.3.xz > .gpu/libembree3.so.3
  export PYTHONPATH="/tmp/site:$PWD" LD_LIBRARY_PATH="$PWD/.gpu" PYGLET_HEADLESS=1 PYTHONUNBUFFERED=1
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
else
  echo "usage: bash bench/gpu_bundle.sh prepare | source bench/gpu_bundle.sh install" >&2
fi

#!/usr/bin/env bash
# Run HERE (a machine with PyPI and apt): what the lent GPU machine's image lacks, into .whl/ (git-ignored),
# for benchmarks/gpu/check.sh to install there. The image already has torch, numpy, scipy, numba, opencv,
# msgpack, psutil, safetensors, jinja2, pytest, tqdm, tensorboard, nvidia-ml-py and typing-extensions.
#   .whl/*.whl                 Python 3.12 x86-64 wheels: the bus, gymnasium + MuJoCo, robosuite's small needs
#   .whl/robosuite-slim.tgz    robosuite 1.5.1 with the Panda's assets only (its wheel is 152 MB, over what a
#                              call carries; Lift with a Panda needs 30 MB of it)
#   .whl/gl/*.deb              the EGL/GL loaders MuJoCo's headless rendering (MUJOCO_GL=egl) needs
# About 55 MB in all: inside the 64 MiB a device call carries (the repository is ~5 MB).
set -euo pipefail
cd "$(dirname "$0")/../.."
WHEELS=(
    eclipse-zenoh==1.10.2     # the bus
    tomli-w==1.2.0            # the resolved config
    gymnasium==1.4.0 farama-notifications==0.0.6 cloudpickle==3.1.1
    mujoco==3.9.0 glfw==2.10.0 pyopengl==3.1.10 etils==1.13.0 absl-py==2.3.1   # MuJoCo tasks
    array-api-compat==1.16.0  # MuJoCo tasks: one reward for numpy and torch (ebrl/envs/mjtask.py)
    termcolor==3.1.0          # robosuite's logging
)
rm -rf .whl && mkdir -p .whl/gl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "${WHEELS[@]}"

# robosuite without the robots, grippers and mounts a Panda does not use (and without pybullet's data)
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: -d "$tmp" robosuite==1.5.1
(cd "$tmp" && python3 -m zipfile -e robosuite-1.5.1-py3-none-any.whl x)
a="$tmp/x/robosuite/models/assets"
find "$a/robots" -mindepth 1 -maxdepth 1 ! -name panda -exec rm -rf {} +
find "$a/grippers/meshes" -mindepth 1 -maxdepth 1 ! -name panda_gripper -exec rm -rf {} +
rm -rf "$a/grippers/obj_meshes" "$a/bullet_data"
find "$a/bases/meshes" -mindepth 1 -maxdepth 1 ! -name 'rethink*' -exec rm -rf {} +
rm -f "$tmp"/x/robosuite-*.dist-info/RECORD
tar czf .whl/robosuite-slim.tgz -C "$tmp/x" .

# EGL and GL loaders (x86-64 Debian packages, unpacked there with dpkg -x)
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/ebrl-amd64'
mkdir -p /tmp/ebrl-amd64/partial
apt-get $o update -qq
(cd .whl/gl && apt-get $o download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 2>/dev/null)
du -sh .whl && ls .whl .whl/gl

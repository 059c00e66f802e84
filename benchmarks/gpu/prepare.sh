#!/usr/bin/env bash
# Run HERE (a machine with PyPI): the Python 3.12 x86-64 wheels EBRL needs that the lent GPU machine's image
# lacks, into .whl/ (git-ignored), for benchmarks/gpu/check.sh to install there. The image already has torch,
# numpy, msgpack, psutil, safetensors, jinja2, pytest, nvidia-ml-py, absl-py, etils, cloudpickle and
# typing-extensions.
# ~20 MB in all: well inside the 64 MiB a device call carries.
set -euo pipefail
cd "$(dirname "$0")/../.."
WHEELS=(
    eclipse-zenoh==1.10.2     # the bus
    gymnasium==1.4.0 farama-notifications==0.0.6
    mujoco==3.3.7 glfw==2.10.0 pyopengl==3.1.10   # MuJoCo tasks (InvertedPendulum, HalfCheetah)
)
rm -rf .whl && mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "${WHEELS[@]}"
du -sh .whl && ls .whl

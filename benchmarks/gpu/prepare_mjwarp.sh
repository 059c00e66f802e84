#!/usr/bin/env bash
# Run HERE (a machine with PyPI): MuJoCo Warp and what EBRL needs beside the lent GPU machine's image, for
# `benchmarks/gpu/check.sh mjwarp` there. warp-lang's wheel alone is 167 MB, more than a device call carries
# (64 MiB with the repository), so the packages are installed here for the GPU machine's Python 3.12 (pip
# --target with its platform tags), compressed with xz (112 MB: xz packs warp's 389 MB library far tighter
# than the wheel's zip) and cut into parts of at most 56 MB:
#   .whl-mjw/1/ .. .whl-mjw/N/   part-K of the site.tar.xz, and MANIFEST (each part's name and sha256)
#   .whl-mjw/cache/              warp-cache.tgz, Warp's compiled kernels, when an earlier GPU run brought them
#                                back (check.sh writes it to $OUT): carry it and the kernels load instead of
#                                compiling (absent the first time)
# On the GPU machine, in calls made back to back while it is warm (it keeps /tmp between calls; a carried
# folder is gone in the next call that does not carry it, so check.sh copies each part to /tmp/ebrl-mjw):
#   device run, carry [".whl-mjw/1"]:                    bash benchmarks/gpu/check.sh stage
#   ...                                                  (one call per part but the last)
#   device run, carry [".whl-mjw/N", ".whl-mjw/cache"]:  bash benchmarks/gpu/check.sh mjwarp
# The last call checks every part's sha256, unpacks them into /tmp/site and runs.
# The image already has torch, numpy, absl-py, etils, fsspec, zipp, msgpack, psutil, safetensors, jinja2,
# tqdm, tensorboard, scipy, imageio, pytest, nvidia-ml-py (KINDS.md in the device tool's library).
set -euo pipefail
cd "$(dirname "$0")/../.."
PART_MB=56
PACKAGES=(
    warp-lang==1.15.0 mujoco-warp==3.9.0.1 mujoco==3.9.0 glfw==2.10.0 pyopengl==3.1.10  # the simulator
    array-api-compat==1.16.0  # MuJoCo tasks: one reward for numpy and torch
    eclipse-zenoh==1.10.2 tomli-w==1.2.0  # the bus, the resolved config
    gymnasium==1.4.0 farama-notifications==0.0.6 cloudpickle==3.1.1
)
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
python3 -m pip install -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any --target "$tmp/site" "${PACKAGES[@]}"
# what no run imports: Warp's and MuJoCo Warp's own examples, tests and test models
rm -rf "$tmp/site/warp/examples" "$tmp/site/warp/tests" "$tmp/site/mujoco_warp/test_data"
find "$tmp/site" -name __pycache__ -prune -exec rm -rf {} +
tar cf - -C "$tmp/site" . | xz -9 -T0 > "$tmp/site.tar.xz"  # a few minutes on 2 cores
(cd "$tmp" && split -b "${PART_MB}M" -d -a 1 site.tar.xz part-)
cache=""
[ -d .whl-mjw/cache ] && cache=$(mktemp -d) && cp -r .whl-mjw/cache/. "$cache"/  # kept across a re-stage
rm -rf .whl-mjw
n=0
for part in "$tmp"/part-*; do
    n=$((n + 1))
    mkdir -p ".whl-mjw/$n"
    mv "$part" ".whl-mjw/$n/"
done
(cd .whl-mjw && sha256sum */part-* | sed 's| [0-9]*/| |' > MANIFEST)
for d in .whl-mjw/[0-9]*; do cp .whl-mjw/MANIFEST "$d/"; done
mkdir -p .whl-mjw/cache
[ -n "$cache" ] && cp -r "$cache"/. .whl-mjw/cache/ && rm -rf "$cache"
du -sh .whl-mjw/* && cat .whl-mjw/MANIFEST
echo "$n parts: carry .whl-mjw/1 .. .whl-mjw/$n in calls back to back, the last with .whl-mjw/cache"

#!/usr/bin/env bash
# Run HERE (a machine with PyPI): MuJoCo Warp and what EBRL needs beside the lent GPU machine's image, for
# `benchmarks/gpu/check.sh mjwarp` there. warp-lang's wheel alone is 167 MB, more than a device call carries
# (64 MiB with the repository), so the packages are installed here for the GPU machine's Python 3.12 (pip
# --target with its platform tags), packed with xz (112 MB: xz packs warp's 389 MB library far tighter than the
# wheel's zip) and cut into parts of at most 56 MB:
#   .whl-mjw/1/ .. .whl-mjw/N/   part-K of kit.tar.xz, and MANIFEST (each part's name and sha256)
#   .whl-mjw/cache/              where to put warp-cache.tgz.0, .1, ... (Warp's compiled CUDA kernels, about
#                                30 MB, cut in pieces under 16 MiB) that check.sh left in $OUT: they go into the
#                                kit, and there the kernels load instead of compiling (about 80 s on an H200)
# On the GPU machine, in calls made back to back while it is warm (it keeps /tmp between calls; a carried
# folder is gone in the next call that does not carry it, so check.sh copies each part to /tmp/ebrl-mjw):
#   device run, carry [".whl-mjw/1"]:  bash benchmarks/gpu/check.sh stage
#   ...                                (one call per part but the last)
#   device run, carry [".whl-mjw/N"]:  bash benchmarks/gpu/check.sh mjwarp
# The last call checks every part's sha256 and unpacks them into /tmp/site (and /tmp/warp-cache).
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
cache=""
if ls .whl-mjw/cache/warp-cache.tgz* >/dev/null 2>&1; then  # Warp's kernels from a GPU run: into the kit
    cache=$(mktemp -d) && cp .whl-mjw/cache/warp-cache.tgz* "$cache"/  # and kept across this re-stage
    mkdir -p "$tmp/warp-cache" && cat "$cache"/warp-cache.tgz* | tar xz -C "$tmp/warp-cache"
fi
tar cf - -C "$tmp" site $([ -n "$cache" ] && echo warp-cache) | xz -9 -T0 > "$tmp/kit.tar.xz"  # minutes on 2 cores
(cd "$tmp" && split -b "${PART_MB}M" -d -a 1 kit.tar.xz part-)
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
if [ -n "$cache" ]; then cp "$cache"/* .whl-mjw/cache/ && rm -rf "$cache"; fi
du -sh .whl-mjw/* && cat .whl-mjw/MANIFEST
echo "$n parts ($([ -d "$tmp/warp-cache" ] && echo "with" || echo "without") Warp's kernel cache): carry" \
    ".whl-mjw/1 .. .whl-mjw/$n, one a call, in calls back to back"

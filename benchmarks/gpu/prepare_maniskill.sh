#!/usr/bin/env bash
# Run HERE (a machine with PyPI and apt): ManiSkill for the lent GPU machine, in two bundles that each fit in
# what one device call carries (64 MiB with the repository), for `benchmarks/gpu/check.sh maniskill`:
#   .whl-ms/a/   SAPIEN 3.0.3 (Python 3.12) and its largest needs (lxml, networkx): ~58 MB
#   .whl-ms/b/   ManiSkill 3.0.1 slimmed to what PickCube and its kin need (the Panda's assets; no other robot,
#                no environment maps: 32 MB of its 102 MB wheel), the other packages `import mani_skill.envs`
#                needs, the bus and gymnasium (EBRL's own needs), and the Vulkan and EGL loaders: ~60 MB
# Stage them in calls made back to back while the machine is warm (it keeps ignored paths between calls):
#   device run, carry [".whl-ms/a"]:  true
#   device run, carry [".whl-ms/b"]:  bash benchmarks/gpu/check.sh maniskill ...
# The set was found by importing mani_skill.envs from exactly these packages (Python 3.11 wheels, here).
set -euo pipefail
cd "$(dirname "$0")/../.."
DL=(python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_26_x86_64
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any)
A=(sapien==3.0.3 lxml==6.1.3 networkx==3.6.1)
B=(
    eclipse-zenoh==1.10.2 tomli-w==1.2.0 gymnasium==1.4.0 farama-notifications==0.0.6 cloudpickle==3.1.1  # EBRL
    dacite==1.9.2 transforms3d==0.4.2 trimesh==5.2.0 imageio==2.38.1 defusedxml==0.7.1 pyyaml==6.0.4
    pytorch_kinematics==0.7.6 arm_pytorch_utilities==0.5.0 pytorch-seed==0.2.0 absl-py==2.5.1
    huggingface_hub==0.26.5 requests==2.34.2 charset-normalizer==3.5.2 idna==3.20 urllib3==2.8.0
    certifi==2026.10.19.post1 filelock==4.2.12 fsspec==2026.9.0 packaging==26.3 pyperclip==1.11.0
    importlib_resources==7.1.0 tabulate==0.10.0
    ipython==8.30.0 traitlets==5.16.1 jedi==0.20.1 parso==0.8.7 prompt_toolkit==3.0.53 pexpect==4.9.0
    ptyprocess==0.7.0 decorator==5.3.1 matplotlib-inline==0.2.2 pygments==2.21.0 stack_data==0.6.3
    executing==2.3.0 asttokens==3.0.2 pure_eval==0.2.4 wcwidth==0.9.4
)
rm -rf .whl-ms && mkdir -p .whl-ms/a .whl-ms/b/gl
"${DL[@]}" -d .whl-ms/a "${A[@]}"
"${DL[@]}" -d .whl-ms/b "${B[@]}"

# ManiSkill without the robots, scenes and environment maps PickCube-v1 (and the other Panda tabletop tasks)
# never load
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: -d "$tmp" mani-skill==3.0.1
(cd "$tmp" && python3 -m zipfile -e mani_skill-3.0.1-py3-none-any.whl x)
a="$tmp/x/mani_skill/assets"
find "$a/robots" -mindepth 1 -maxdepth 1 ! -name panda -exec rm -rf {} +
rm -rf "$a/environment_maps" "$a/maniskill2-scene-2.glb"
find "$tmp/x/mani_skill/utils/scene_builder/replicacad" "$tmp/x/mani_skill/examples" -type f ! -name '*.py' -delete
rm -f "$tmp"/x/mani_skill-*.dist-info/RECORD
tar czf .whl-ms/b/mani_skill-slim.tgz -C "$tmp/x" .

# the Vulkan loader SAPIEN renders through, and the EGL/GL loaders (unpacked there with dpkg -x)
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/ebrl-amd64'
mkdir -p /tmp/ebrl-amd64/partial
apt-get $o update -qq
(cd .whl-ms/b/gl && apt-get $o download -qq libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 2>/dev/null)
du -sh .whl-ms/a .whl-ms/b
for d in .whl-ms/a .whl-ms/b; do
    [ "$(du -sm "$d" | cut -f1)" -lt 61 ] || { echo "$d is over 60 MB: it would not fit in one call"; exit 1; }
done

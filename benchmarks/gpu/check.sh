#!/usr/bin/env bash
# Run THERE, on the lent GPU machine, in one device call (well under 9 minutes), from the repository root:
#   device run (carry .whl): bash benchmarks/gpu/check.sh
# after benchmarks/gpu/prepare.sh has put the wheels into .whl/ here. Writes under $OUT (default ./gpu-out):
#   gpu.txt            nvidia-smi and torch's view of the device
#   pytest.log         the tests marked gpu (policy and learner on CUDA, the memory cap, gen + train sharing
#                      the GPU in one process over the in-memory bus), and the fast device/pipeline tests
#   forward.json       generation's forward pass, CPU vs GPU (benchmarks/gpu/forward.py)
#   quickstart.json    a real `ebrl up` of the quickstart with gen and train on the GPU (device, memory, rates)
#   mps.log            the same with the allocator's MPS shares: the launcher starts an MPS control daemon for
#                      the run and quits it at the end
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-$PWD/gpu-out}"
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "check.sh: installing .whl/ failed (run benchmarks/gpu/prepare.sh here first)"; exit 1; }
export PYTHONPATH="$PWD:/tmp/site" PYTHONUNBUFFERED=1 MUJOCO_GL=egl
status=0
{ nvidia-smi; python3 -c "import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"; } \
    > "$OUT/gpu.txt" 2>&1
echo "== pytest -m gpu"
timeout 240 python3 -m pytest -q -rs -p no:cacheprovider -o addopts="" -m "gpu or not slow" \
    tests/test_devices.py tests/test_pipeline.py 2>&1 | tee "$OUT/pytest.log" || status=1
echo "== forward pass, CPU vs GPU"
timeout 150 python3 benchmarks/gpu/forward.py --out "$OUT/forward.json" || status=1
echo "== ebrl up on the GPU"
timeout 150 python3 - "$OUT/quickstart.json" <<'PY' || status=1
import json, sys, tempfile
from ebrl.testing import Run, StatsWatcher
with tempfile.TemporaryDirectory() as out, Run("configs/quickstart.toml", "run.iterations=30", 'viz.rerun="off"',
                                               name="gpu-quickstart", out_dir=out) as run, StatsWatcher(run) as w:
    w.wait_for(lambda: (w.latest("train/0", "train/policy_version") or 0) >= 30, 130, "30 updates")
    code = run.stop()
    keys = ("cuda_device", "cuda_mem_allocated_mb", "cuda_mem_cap_mb")
    result = {"exit": code, "gen": {k: w.latest("gen/0", f"gen/{k}") for k in keys},
              "train": {k: w.latest("train/0", f"train/{k}") for k in keys},
              "env_steps_per_s": w.latest("sim/0", "sim/env_steps_per_s"),
              "train_update_s": w.latest("train/0", "train/update_s"),
              "return": w.latest("train/0", "train/episode_return_mean")}
    print(json.dumps(result, indent=1))
    json.dump(result, open(sys.argv[1], "w"), indent=1)
    assert result["gen"]["cuda_device"] == 0 and result["train"]["cuda_device"] == 0, result
PY
echo "== ebrl up with MPS shares (the launcher starts the control daemon and quits it)"
had_mps=0; [ -e /tmp/nvidia-mps/control ] && had_mps=1
timeout 180 python3 -m ebrl.cli up configs/quickstart.toml --set alloc.enabled=true --set 'alloc.gpu_pool="mps"' \
    --set run.iterations=20 --set 'run.output_dir="/tmp/mps-run"' --set 'viz.rerun="off"' > "$OUT/mps.log" 2>&1 \
    || status=1
tail -n 25 "$OUT/mps.log"
grep -h "device" /tmp/mps-run/*/logs/gen-0.log /tmp/mps-run/*/logs/train-0.log 2>/dev/null | head -4
# never leave a daemon this script's run started behind, even if the launcher was killed
if [ $had_mps = 0 ] && [ -e /tmp/nvidia-mps/control ]; then echo quit | nvidia-cuda-mps-control; status=1; fi
exit $status

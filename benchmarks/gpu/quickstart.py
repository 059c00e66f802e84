"""A real ``ebrl up`` of the quickstart with generation and training on the GPU (``gen.device = "cuda"``: its
"auto" may measure the CPU faster for this small policy; ``train.device`` left at "auto"): what each stage's
stats say about its device, precision and memory, and the run's rates.

    python benchmarks/gpu/quickstart.py --out quickstart.json      # on a GPU machine (check.sh runs it)

Fails (exit 1) unless both stages report CUDA device 0 and the GPU's utilisation (NVML) is on the stream.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent.parent))

from ebrl.testing import Run, StatsWatcher  # noqa: E402

KEYS = ("cuda_device", "cuda_mem_allocated_mb", "cuda_mem_reserved_mb", "cuda_mem_cap_mb")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--out", default="gpu_quickstart.json")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out, \
            Run("configs/quickstart.toml", f"run.iterations={args.iterations}", 'viz.rerun="off"', 'gen.device="cuda"',
                name="gpu-quickstart", out_dir=out) as run, StatsWatcher(run) as w:
        w.wait_for(lambda: (w.latest("train/0", "train/policy_version") or 0) >= args.iterations - 1, 80,
                   f"{args.iterations - 1} updates")
        result = {"gen": {k: w.latest("gen/0", f"gen/{k}") for k in (*KEYS, "dtype", "compiled")},
                  "train": {k: w.latest("train/0", f"train/{k}") for k in (*KEYS, "dtype")},
                  "gpu0_sm_percent": w.latest("sim/0", "gpu/0_sm_percent"),
                  "gpu0_mem_used_mb": w.latest("sim/0", "gpu/0_mem_used_mb"),
                  "env_steps_per_s": w.latest("sim/0", "sim/env_steps_per_s"),
                  "train_update_s": w.latest("train/0", "train/update_s"),
                  "return": w.latest("train/0", "train/episode_return_mean")}
        result["exit"] = run.stop()
    print(json.dumps(result, indent=1))
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    ok = (result["gen"]["cuda_device"] == 0 and result["train"]["cuda_device"] == 0
          and result["gpu0_mem_used_mb"] is not None and result["exit"] in (0, 130))  # 130: stopped, as asked
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()

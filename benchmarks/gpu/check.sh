#!/usr/bin/env bash
# The GPU acceptance kit. Run THERE, on the lent GPU machine, in one device call, from the repository root:
#   device run (carry .whl): bash benchmarks/gpu/check.sh [PART ...]
# after benchmarks/gpu/prepare.sh has put what the machine lacks into .whl/ here. With no PART it runs every
# part below, in order, within 9 minutes (each part has its own time limit, so one that hangs costs only its
# own). DURATION (seconds, default 15) is each benchmark window; longer windows give the numbers in
# BENCHMARKS.md (`DURATION=45 bash benchmarks/gpu/check.sh bench` in a call of its own).
#   tests       the tests marked gpu (policy and learner on CUDA, the memory cap, CUDA graphs, gen + train
#               sharing the GPU over the in-memory bus, PPO's update waiting for the device once per epoch) and
#               the fast device/pipeline/MPS/PPO tests
#   train_rate  training's decisions/s on W2 and W3: the fused on-device step skip vs a host check per step
#   auto        what "auto" (policy.dtype, gen.compile, gen.device) decides for the quickstart, W2 and W3, with
#               the numbers behind it (python -m ebrl.autotune CONFIG; kept in the machine's cache for the
#               parts after it)
#   quickstart_auto  the quickstart with no flags vs gen.device = "cpu", back to back (ebrl bench, 20 s each)
#   w3_accept   issue 35's acceptance: W3 with no flags, ebrl vs colocated (the best baseline of every W3
#               record), REPEAT (3) interleaved rounds of DURATION (30 here) seconds
#   forward     generation's forward pass: CPU vs GPU, float32 vs bfloat16, eager vs CUDA graphs, up to W3
#   vla         the VLA policy (policy.kind = "vla", transformers + peft: the image has both) on the GPU: its
#               tests (CUDA graphs in float32 and bfloat16), then generation's forwards/s and training's updates/s
#               of tiny VLAs (both heads) and a W3-sized one beside W3, in bfloat16 with CUDA graphs
#               (benchmarks/vla_rates.py; parts vla_tests, vla_rates)
#   quickstart  a real `ebrl up` of the quickstart with gen and train on the GPU (device, memory, rates)
#   mps         the same with the allocator's MPS shares: the launcher starts an MPS control daemon for the run
#               and quits it at the end
#   shares      gen and train of W3 sharing the GPU under MPS at 30/70, 50/50 and without MPS
#   w3          W3 (306M-parameter flow transformer, robosuite Lift camera) learning with gen + train on the GPU
#   bench       trajectories/s of ebrl vs colocated, hybrid and async: W1 (16 cores), W2 and W3 on the GPU
#               (parts bench_w1, bench_w2, bench_w3)
#   adapt       a 30 % simulator slowdown injected mid-run on 16 cores, with and without the allocator
#   maniskill   (needs .whl-ms, staged by benchmarks/gpu/prepare_maniskill.sh) the ManiSkill tests, a vectorized
#               group's chunk time on GPU PhysX against what moving its data costs, and 2 pipelined groups vs
#               one group of the same size (parts maniskill_tests, maniskill_step, maniskill_groups)
#   maniskill_race  ebrl to 90 % success on PickCube, then the GPU PPO peer, RACE_SECONDS (240) each
#   stage       (MuJoCo Warp's kit, benchmarks/gpu/prepare_mjwarp.sh) copy the carried .whl-mjw/K part to /tmp
#   mjwarp      (every part of .whl-mjw staged) the MuJoCo Warp tests on the GPU (mjwarp_tests, which also
#               compile Warp's kernels before anything is timed), a group's chunk time at 1024-4096 worlds with
#               and without CUDA graphs (mjwarp_step), the race: ebrl to 90 % success on PandaPickCube, then the
#               one-process GPU PPO peer, RACE_SECONDS each, a pair for each of SEEDS ("0"; "0 1 2" gives the
#               spread, which single pairs hide) (mjwarp_race: it ends with each side's median seconds to 90 %,
#               in the run and by the whole command, and the ratios of issue 51's acceptance, from
#               benchmarks/gpu/race_summary.py), and 2 pipelined groups of 1024 worlds vs one group of 2048
#               (mjwarp_groups); mjwarp_race_separate, in a call of its own, races EBRL's side again with every
#               service a process of its own (run.processes = []) to show what sharing one buys;
#               Warp's compiled kernels come back as $OUT/warp-cache.tgz.0, .1, ... (put them in .whl-mjw/cache
#               here and re-run prepare_mjwarp.sh: the next machine loads them instead of compiling)
#   mjwarp_start_end  (after mjwarp_tests) each side's seconds to its first env step and from its last update to
#               its exit (benchmarks/start_end.py --gpu), 2 rounds
#   mjwarp_variants  (after mjwarp_tests, in a later call) what closes the gap to the peer (issue 33): ebrl up
#               configs/mjwarp_pickcube.toml to 90 %, VARIANT_SECONDS (150) at most each, with algo.max_staleness
#               = 0 (on 2 CPU cores staler data cost EBRL updates, BENCHMARKS.md), as one env step per decision
#               without MPS, one group of 4096 worlds, and the defaults under an MPS daemon started and quit around
#               the run (parts mjwarp_fresh, mjwarp_chunk1, mjwarp_group4096, mjwarp_mps)
# Everything lands in $OUT (default ./gpu-out): summary.txt, gpu.txt and results.tgz (JSON results, logs).
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
OUT="${OUT:-$ROOT/gpu-out}"
DURATION="${DURATION:-15}"
W3_SECONDS="${W3_SECONDS:-120}"
SHARES_SECONDS="${SHARES_SECONDS:-8}"
RACE_SECONDS="${RACE_SECONDS:-240}"
SEEDS="${SEEDS:-0}"
VARIANT_SECONDS="${VARIANT_SECONDS:-150}"
RES=/tmp/ebrl-gpu-results
mkdir -p "$OUT" "$RES"
PARTS=("$@")
[ ${#PARTS[@]} -eq 0 ] && PARTS=(tests forward quickstart mps shares w3 bench adapt)
SUMMARY="$OUT/summary.txt"
: > "$SUMMARY"
T0=$(date +%s)

# --- set-up: wheels, the slim robosuite, the EGL loaders (.whl); ManiSkill, SAPIEN and Vulkan (.whl-ms, staged)
install() { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$@"; }
if [ -d .whl ]; then
    install .whl/*.whl || { echo "check.sh: installing .whl/ failed (run benchmarks/gpu/prepare.sh here first)"; exit 1; }
    [ -f .whl/robosuite-slim.tgz ] && tar xzf .whl/robosuite-slim.tgz -C /tmp/site
fi
if [ -d .whl-ms/b ]; then  # benchmarks/gpu/prepare_maniskill.sh: bundle a in an earlier call, b in this one
    [ -d .whl-ms/a ] || { echo "check.sh: .whl-ms/a was not staged (carry it in a call just before)"; exit 1; }
    install .whl-ms/a/*.whl .whl-ms/b/*.whl || { echo "check.sh: installing .whl-ms/ failed"; exit 1; }
    tar xzf .whl-ms/b/mani_skill-slim.tgz -C /tmp/site
fi
# MuJoCo Warp (benchmarks/gpu/prepare_mjwarp.sh): each call copies the part it carries to /tmp, which stays while
# the machine is warm; once every part named in MANIFEST is there (sha256 checked), they unpack into /tmp/site
# and, when the kit holds Warp's kernels from an earlier run, /tmp/warp-cache
MJW=/tmp/ebrl-mjw
for d in .whl-mjw/[0-9]*; do [ -d "$d" ] && mkdir -p $MJW && cp "$d"/* $MJW/; done
if [ -f $MJW/MANIFEST ] && [ ! -f $MJW/installed ] && (cd $MJW && sha256sum -c --quiet MANIFEST >/dev/null 2>&1); then
    unxz() { if command -v xz >/dev/null; then xz -d -T0; else  # Python's lzma where the image has no xz
        python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.stdin.buffer), sys.stdout.buffer)"; fi; }
    (cat $MJW/part-* | unxz | tar x -C /tmp) && touch $MJW/installed \
        || { echo "check.sh: installing MuJoCo Warp's kit failed"; exit 1; }
fi
export WARP_CACHE_PATH=/tmp/warp-cache  # Warp's compiled kernels: brought in with the kit, sent back at the end
[ -d .whl ] || [ -d .whl-ms/b ] || [ -d $MJW ] || { echo "check.sh: nothing to install (run benchmarks/gpu/prepare.sh here)"; exit 1; }
for gl in .whl/gl .whl-ms/b/gl; do
    if [ -d $gl ] && ! { ldconfig -p | grep -q libEGL.so.1 && ldconfig -p | grep -q libvulkan.so.1; }; then
        for f in $gl/*.deb; do dpkg -x "$f" /; done; ldconfig
    fi
done
[ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] && \
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
export PYTHONPATH="$ROOT:/tmp/site" PYTHONUNBUFFERED=1
# MuJoCo renders through EGL where its loader is there (the .gl/.whl kits bring it); without one, MUJOCO_GL=egl
# makes `import mujoco` itself fail, so rendering is switched off and everything else runs
if ldconfig -p | grep -q libEGL.so.1; then export MUJOCO_GL=egl PYOPENGL_PLATFORM=egl; else export MUJOCO_GL=disable; fi
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && \
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
{ nvidia-smi; python3 -c "import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"
  nproc; free -g; } > "$OUT/gpu.txt" 2>&1
mps_up() { python3 -c "from ebrl.resources.pool import mps_reachable; raise SystemExit(not mps_reachable())"; }
had_mps=0; mps_up && had_mps=1

part() {  # part NAME LIMIT_S COMMAND...: runs it with a time limit, logs to $RES/NAME.log, notes the outcome
    local name=$1 limit=$2; shift 2
    local t=$(date +%s)
    echo "== $name (limit ${limit}s, at $((t - T0))s)"
    timeout -k 10 "$limit" "$@" > "$RES/$name.log" 2>&1
    local rc=$?
    tail -n 15 "$RES/$name.log"
    echo "$name: exit $rc in $(($(date +%s) - t))s" | tee -a "$SUMMARY"
}

timed() {  # timed SIDE SEED COMMAND...: runs it, appends "SIDE SEED SECONDS" (its whole wall clock) to times.txt
    local side=$1 seed=$2; shift 2
    local t=$(date +%s.%N)
    "$@"
    echo "$side $seed $(python3 -c "import sys; print(round($(date +%s.%N) - $t, 2))")" >> "$RES/times.txt"
}

race_summary() {  # the race's medians and ratios (benchmarks/gpu/race_summary.py), into the summary
    python3 benchmarks/gpu/race_summary.py "$RES" --seeds "$SEEDS" --json "$RES/mjwarp_race_summary.json" \
        | tee -a "$SUMMARY"
}

variant() {  # variant NAME KEY=VALUE...: ebrl up configs/mjwarp_pickcube.toml to 90 %, VARIANT_SECONDS at most
    local name=$1; shift
    local sets=(--set 'viz.rerun="off"' --set "run.output_dir=\"$RES/variant-$name\"")
    for kv; do sets+=(--set "$kv"); done
    part "mjwarp_$name" $((VARIANT_SECONDS + 60)) timeout "$VARIANT_SECONDS" python3 -m ebrl.cli up \
        configs/mjwarp_pickcube.toml "${sets[@]}"
}

# ebrl bench CONFIG: the four modes, interleaved, one window of DURATION seconds each
BENCH_BASE=(python3 -m ebrl.cli bench --raw-seconds 0 --set 'viz.rerun="off"')
BENCH=("${BENCH_BASE[@]}" --modes ebrl,colocated,hybrid,async)

i=0
while [ $i -lt ${#PARTS[@]} ]; do
    p=${PARTS[$i]}; i=$((i + 1))
    case $p in
    tests) part tests 120 python3 -m pytest -q -rs -p no:cacheprovider -o addopts="" --timeout 60 -m "gpu or not slow" \
               tests/test_devices.py tests/test_pipeline.py tests/test_mps.py tests/test_ppo.py ;;
    auto) for c in quickstart bench_w2_gpu bench_w3; do
              part "auto_$c" 240 python3 -m ebrl.autotune "configs/$c.toml"
              tail -n 1 "$RES/auto_$c.log" >> "$RES/auto.jsonl"
          done ;;
    quickstart_auto) part quickstart_auto 150 "${BENCH_BASE[@]}" --modes ebrl \
                         configs/quickstart.toml --variant 'ebrl+gen_cpu=gen.device="cpu"' --duration 20 \
                         --json "$RES/quickstart_auto.json" ;;
    # W3 measures the GPU levers; its records so far gave every mode ebrl's rendering of only the observations
    # read, so these parts keep that (sim.lazy_render=true) to stay comparable with them
    w3_accept) part w3_accept 590 "${BENCH_BASE[@]}" --modes ebrl,colocated \
                   configs/bench_w3.toml --set sim.lazy_render=true --duration "${DURATION_ACCEPT:-30}" \
                   --repeat "${REPEAT:-3}" --json "$RES/bench_w3_accept.json" ;;
    train_rate) part train_rate 200 python3 benchmarks/train_rate.py --configs configs/bench_w2_gpu.toml \
                    configs/bench_w3.toml --seconds 3 --rounds 2 --out "$RES/train_rate.json" ;;
    forward) part forward 120 python3 benchmarks/gpu/forward.py --seconds 0.5 --out "$RES/forward.json" ;;
    vla) set -- vla_tests vla_rates; for b; do PARTS+=("$b"); done ;;
    vla_tests) part vla_tests 150 python3 -m pytest -q -rs -p no:cacheprovider -o addopts="" --timeout 120 \
                   -m "gpu or not slow" tests/test_vla.py -k "not ebrl_up" ;;
    vla_rates) part vla_rates 300 python3 benchmarks/vla_rates.py --device cuda --dtype bfloat16 \
                   --policies vla-tiny vla-tiny-tokens vla-base w3 --seconds 1 --rounds 3 --out "$RES/vla_rates_gpu.json" ;;
    quickstart) part quickstart 90 python3 benchmarks/gpu/quickstart.py --out "$RES/quickstart.json" ;;
    mps) part mps 120 python3 -m ebrl.cli up configs/quickstart.toml --set alloc.enabled=true \
             --set 'alloc.gpu_pool="mps"' --set alloc.profile_seconds=0.3 --set run.iterations=20 --set "run.output_dir=\"$RES/mps-run\"" \
             --set 'viz.rerun="off"'
         grep -h "device" "$RES"/mps-run/*/logs/gen-0.log "$RES"/mps-run/*/logs/train-0.log 2>/dev/null | head -4 ;;
    shares) part shares $((7 * SHARES_SECONDS + 120)) python3 benchmarks/gpu/mps_shares.py --seconds "$SHARES_SECONDS" \
                --warmup 10 --out "$RES/mps_shares.json" ;;
    w3) part w3 $((W3_SECONDS + 100)) python3 benchmarks/gpu/w3_learning.py --seconds "$W3_SECONDS" --out "$RES/w3_learning.json" ;;
    bench) set -- bench_w1 bench_w2 bench_w3; for b; do PARTS+=("$b"); done ;;
    bench_w1) part bench_w1 $((8 * DURATION + 100)) "${BENCH[@]}" configs/bench_lift_16core.toml \
                  --duration "$DURATION" --json "$RES/bench_w1_16core.json" ;;
    bench_w2) part bench_w2 $((8 * DURATION + 100)) "${BENCH[@]}" configs/bench_w2_gpu.toml \
                  --duration "$DURATION" --json "$RES/bench_w2_gpu.json" ;;
    bench_w3) part bench_w3 $((8 * DURATION + 160)) "${BENCH[@]}" configs/bench_w3.toml \
                  --set sim.lazy_render=true --duration "$DURATION" --json "$RES/bench_w3.json" ;;
    adapt) part adapt 330 python3 benchmarks/adaptation.py --config configs/bench_lift_16core.toml \
               --slowdown "sim=1.3@55" --duration 120 --tag lift_16core_gpu --set 'viz.rerun="off"' \
               --set alloc.profile_seconds=0.3
           cp benchmarks/results/adaptation_lift_16core_gpu.json "$RES/" 2>/dev/null ;;
    maniskill) set -- maniskill_tests maniskill_step maniskill_groups; for b; do PARTS+=("$b"); done ;;
    maniskill_tests) part maniskill_tests 180 python3 -m pytest -q -rs -p no:cacheprovider -o addopts="" \
                         --timeout 120 tests/test_maniskill.py tests/test_vector.py ;;
    maniskill_step) part maniskill_step 240 python3 benchmarks/gpu/maniskill_step.py --envs 128,256,512 \
                        --out "$RES/maniskill_step.json" ;;
    # env steps/s of ebrl with 2 pipelined groups of 256 vs one group of 512, side by side (group_pipeline off)
    maniskill_groups) part maniskill_groups $((4 * DURATION + 200)) sh -c "
        python3 -m ebrl.cli bench configs/maniskill.toml --modes ebrl --raw-seconds 0 --duration $DURATION \
            --set 'viz.rerun=\"off\"' --json $RES/maniskill_pipelined.json &&
        python3 -m ebrl.cli bench configs/maniskill.toml --modes ebrl --raw-seconds 0 --duration $DURATION \
            --set 'viz.rerun=\"off\"' --set sim.group_pipeline=false --json $RES/maniskill_one_group.json" ;;
    # the learning race, back to back: ebrl to 90 % success on PickCube, then the one-process GPU PPO peer
    maniskill_race) part maniskill_ebrl $((RACE_SECONDS + 60)) timeout "$RACE_SECONDS" python3 -m ebrl.cli up \
                        configs/maniskill.toml --set 'viz.rerun="off"' --set "run.output_dir=\"$RES/race\""
                    part maniskill_peer $((RACE_SECONDS + 60)) python3 benchmarks/peers/maniskill_ppo.py \
                        --max-seconds "$RACE_SECONDS" --json "$RES/peer_maniskill_ppo.json" ;;
    stage) n=$(ls $MJW/part-* 2>/dev/null | wc -l)
           echo "stage: $n of $(wc -l < $MJW/MANIFEST) parts of MuJoCo Warp's kit in $MJW" ;;
    mjwarp) [ -f $MJW/installed ] || { echo "check.sh: MuJoCo Warp's kit is not complete in $MJW (stage every part)"
                                       exit 1; }
            set -- mjwarp_tests mjwarp_step mjwarp_race mjwarp_groups; for b; do PARTS+=("$b"); done ;;
    mjwarp_tests) part mjwarp_tests 300 python3 -m pytest -q -rs -p no:cacheprovider -o addopts="" --timeout 240 \
                      -m gpu tests/test_mjwarp.py ;;
    mjwarp_step) part mjwarp_step 150 python3 benchmarks/gpu/mjwarp_step.py --worlds 1024,2048,4096 \
                     --out "$RES/mjwarp_step.json" ;;
    # the learning race, back to back (after the tests: Warp's kernels compiled and cached for both sides):
    # ebrl to 90 % success on PandaPickCube, then the one-process GPU PPO peer
    # (SEEDS: one pair a seed, ebrl first; updates to 90 % vary about 2x from seed to seed on either side)
    # (issue 51: the config as it is, run.processes = "auto": sim, gen and train in one process on a GPU host);
    # each command's whole wall clock into times.txt; then race_summary.py prints the medians and the ratios
    mjwarp_race) for s in $SEEDS; do
                     timed ebrl "$s" part "mjwarp_ebrl_s$s" $((RACE_SECONDS + 90)) timeout "$RACE_SECONDS" \
                         python3 -m ebrl.cli up configs/mjwarp_pickcube.toml --set 'viz.rerun="off"' \
                         --set "run.seed=$s" --set "run.output_dir=\"$RES/mjwarp-race-s$s\""
                     timed peer "$s" part "mjwarp_peer_s$s" $((RACE_SECONDS + 90)) python3 benchmarks/peers/mjwarp_ppo.py \
                         --seed "$s" --max-seconds "$RACE_SECONDS" --json "$RES/peer_mjwarp_ppo_s$s.json"
                 done
                 race_summary ;;
    # the same EBRL side with every service a process of its own (run.processes = []): what sharing one buys
    mjwarp_race_separate) for s in $SEEDS; do
                     timed ebrl_separate "$s" part "mjwarp_ebrl_separate_s$s" $((RACE_SECONDS + 90)) \
                         timeout "$RACE_SECONDS" python3 -m ebrl.cli up configs/mjwarp_pickcube.toml \
                         --set 'viz.rerun="off"' --set 'run.processes=[]' --set "run.seed=$s" \
                         --set "run.output_dir=\"$RES/mjwarp-race-separate-s$s\""
                 done
                 race_summary ;;
    # what each side spends outside its loop (issue 51: each end within 3 s of the peer's): to the first env step,
    # and from the last update to the exit, 2 rounds of 2 iterations (updates) each
    mjwarp_start_end) part mjwarp_start_end 400 python3 benchmarks/start_end.py --gpu --rounds 2 \
                          --json "$RES/start_end_gpu.json" ;;
    mjwarp_variants) set -- mjwarp_fresh mjwarp_chunk1 mjwarp_group4096 mjwarp_mps; for b; do PARTS+=("$b"); done ;;
    mjwarp_fresh) variant fresh algo.max_staleness=0 ;;  # no decision acted by an older version than its update's
    mjwarp_chunk1) variant chunk1 policy.chunk=1 train.batch_size=65536 train.max_pending=131072 sim.segment_length=32 ;;
    mjwarp_group4096) variant group4096 sim.groups=1 sim.envs_per_group=4096 train.batch_size=32768 \
                          train.max_pending=65536 ;;
    mjwarp_mps) had=0; mps_up && had=1; [ $had = 1 ] || nvidia-cuda-mps-control -d
                variant mps
                [ $had = 1 ] || { echo quit | nvidia-cuda-mps-control; } ;;
    # env steps/s of ebrl with 2 pipelined groups of 1024 worlds vs one group of 2048, side by side
    mjwarp_groups) part mjwarp_groups $((4 * DURATION + 240)) sh -c "
        python3 -m ebrl.cli bench configs/mjwarp_pickcube.toml --modes ebrl --raw-seconds 0 --duration $DURATION \
            --set 'viz.rerun=\"off\"' --json $RES/mjwarp_pipelined.json &&
        python3 -m ebrl.cli bench configs/mjwarp_pickcube.toml --modes ebrl --raw-seconds 0 --duration $DURATION \
            --set 'viz.rerun=\"off\"' --set sim.group_pipeline=false --json $RES/mjwarp_one_group.json" ;;
    *) echo "check.sh: no part '$p'"; exit 2 ;;
    esac
done

# never leave a daemon this script's runs started behind, even if a launcher was killed
if [ $had_mps = 0 ] && mps_up; then
    echo quit | nvidia-cuda-mps-control; echo "mps: a control daemon was left running; quit it" | tee -a "$SUMMARY"
fi
nvidia-smi --query-gpu=name,memory.used,utilization.gpu --format=csv >> "$OUT/gpu.txt" 2>&1
if [ -n "$(ls -A $WARP_CACHE_PATH 2>/dev/null)" ]; then  # the kernels compiled here, for the next machine, in
    # pieces under the 16 MiB a file from $OUT may have (put them in .whl-mjw/cache/ and re-run prepare_mjwarp.sh)
    tar czf - -C $WARP_CACHE_PATH . | split -b 15M -d -a 1 - "$OUT/warp-cache.tgz." && ls -la "$OUT"/warp-cache.tgz.*
fi
tar czf "$OUT/results.tgz" -C "$RES" --exclude='*.safetensors' --exclude='*.msgpack' --exclude='*.pt' .
echo "total: $(($(date +%s) - T0))s" | tee -a "$SUMMARY"
cat "$SUMMARY"
! grep -qv "exit 0 \|^total" "$SUMMARY"

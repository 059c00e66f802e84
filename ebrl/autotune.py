"""The ``"auto"`` settings a measurement decides: ``policy.dtype``, ``gen.compile`` and ``gen.device``.

Decided once per run, at start, by the launcher (:func:`settle`), and written into the run's ``config.toml`` as
explicit values, so that generation and training (which must agree on the precision: the PPO ratio compares
their log-probs) and every restart use the same ones; the launcher prints the decision, sends it as the run's
``auto`` event (so the report shows it) and keeps it in ``meta.json``:

* With no GPU on the host nothing is measured and nothing changes: float32, eager, generation on the CPU.
* With a GPU, a child process (``python -m ebrl.autotune CONFIG``: torch and CUDA stay out of the launcher)
  builds the run's policy and times each candidate (:func:`measure`): generation's chunk forward at the batch
  sizes the run will use (one group, and every group) on the GPU in float32 and bfloat16 autocast, eagerly
  and through CUDA graphs, and on the CPU (float32, eager, ``gen.threads`` threads); training's gradient
  step at its minibatch size in each precision on ``train.device``. A capture that fails is a candidate
  that is not there (logged), never an error; so is bfloat16 where the GPU has no bfloat16 units.
* :func:`decide` picks the candidate with the least time per decision of the busiest resource -- generation
  and training on one GPU add up (they share it), generation on the CPU runs beside training on the GPU (the
  larger of the two) -- among those within ``TIE`` of the best, the first of: float32 before bfloat16, eager
  before graphs, the GPU before the CPU. bfloat16 only where generation and training both run on a GPU.
* A measured decision is kept in ``~/.cache/ebrl/autotune.json`` (``EBRL_AUTOTUNE_CACHE``: another file, or
  "off"), keyed by the GPUs, torch and what of the config shapes the measurement: the next run of the same
  config on the same machine (a benchmark's rounds) starts without measuring again.
* Explicit values are kept and narrow the candidates. Over several hosts, ``policy.dtype = "auto"`` is
  float32 (each host would measure its own GPU, and the hosts must agree); gen.compile and gen.device are
  measured on the host that runs generation.

A service started without the launcher (tests, embedding) takes ``"auto"`` it finds as float32, eager
(``ebrl.devices.autocast``, ``ebrl.policies.graphs.Actor``), on the GPU when torch sees one.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ebrl import durable

log = logging.getLogger(__name__)

TIE = 0.05  # candidates within 5 % of the fastest count as as fast: the simpler one wins (decide)
TIMEOUT_S = 300.0  # the child's measurement (a large policy's first CUDA graphs take a while)
GEN_SECONDS = 0.3  # timing of one generation candidate at one batch size
TRAIN_SECONDS = 0.6  # timing of training's step in one precision


@dataclass(frozen=True)
class Candidate:
    """One way generation could run: ``device`` "cpu" or "cuda", ``dtype``, ``compile`` ("off"/"cudagraphs")."""

    device: str
    dtype: str
    compile: str

    def __str__(self) -> str:
        how = "CUDA graphs" if self.compile == "cudagraphs" else "eager"
        return f"{'GPU' if self.device == 'cuda' else 'CPU'} {self.dtype} {how}"


PREFERENCE = [Candidate("cuda", "float32", "off"), Candidate("cuda", "float32", "cudagraphs"),
              Candidate("cuda", "bfloat16", "off"), Candidate("cuda", "bfloat16", "cudagraphs"),
              Candidate("cpu", "float32", "off")]  # the order ties are broken in


@dataclass
class Decision:
    """What ``"auto"`` became (``settings``: field -> value, only the fields that were "auto"), why (``line``),
    and the numbers (``gen_s``: candidate -> seconds per decision of generation; ``train_s``: dtype -> of
    training; ``costs``: candidate -> the busiest resource's seconds per decision)."""

    settings: dict[str, str]
    line: str
    gen_s: dict[str, float] = field(default_factory=dict)
    train_s: dict[str, float] = field(default_factory=dict)
    costs: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


AUTO_FIELDS = ("policy.dtype", "gen.compile", "gen.device")


def auto_fields(cfg: Any) -> list[str]:
    """The fields of :data:`AUTO_FIELDS` that ``cfg`` leaves to a measurement."""
    return [name for name in AUTO_FIELDS if _get(cfg, name) == "auto"]


def _get(cfg: Any, name: str) -> Any:
    section, key = name.split(".")
    return getattr(getattr(cfg, section), key)


def apply(cfg: Any, settings: dict[str, str]) -> Any:
    """``cfg`` with ``settings`` (field -> value) in place of its ``"auto"``."""
    sections: dict[str, dict[str, Any]] = {}
    for name, value in settings.items():
        section, key = name.split(".")
        sections.setdefault(section, {})[key] = value
    return dataclasses.replace(cfg, **{s: dataclasses.replace(getattr(cfg, s), **kv) for s, kv in sections.items()})


def candidates(cfg: Any, gpu: bool, bf16: bool, train_on_gpu: bool) -> list[Candidate]:
    """The ways generation may run under ``cfg``'s explicit values, on a host with (``gpu``) or without a GPU;
    bfloat16 only where the GPU has it (``bf16``) and training runs on a GPU too."""
    device, dtype, compile_ = cfg.gen.device, cfg.policy.dtype, cfg.gen.compile
    out = []
    for c in PREFERENCE:
        if c.device == "cuda" and not (gpu and device != "cpu"):
            continue
        if c.device == "cpu" and (device not in ("auto", "cpu") or compile_ == "cudagraphs"):
            continue  # (CUDA graphs asked for: generation stays on a GPU; config refuses them on the CPU)
        if dtype != "auto" and c.dtype != dtype or c.dtype == "bfloat16" and not (bf16 and train_on_gpu):
            continue
        if compile_ != "auto" and c.compile != compile_ and c.device == "cuda":
            continue
        out.append(c)
    return out


def decide(cfg: Any, gen_s: dict[Candidate, float], train_s: dict[str, float], train_on_gpu: bool) -> Decision:
    """The candidate of ``gen_s`` (seconds per decision of generation, measured) with the least busy time per
    decision of its busiest resource (module docstring), as settings for ``cfg``'s "auto" fields."""
    costs: dict[Candidate, float] = {}
    for c, g in gen_s.items():
        t = train_s.get(c.dtype, 0.0)
        costs[c] = g + t if (c.device == "cuda" and train_on_gpu) else max(g, t)
    best = min(costs.values())
    chosen = next(c for c in PREFERENCE if c in costs and costs[c] <= best * (1 + TIE))
    wanted = auto_fields(cfg)
    settings = {"policy.dtype": chosen.dtype, "gen.compile": chosen.compile,
                "gen.device": "cpu" if chosen.device == "cpu" else "auto"}
    settings = {k: v for k, v in settings.items() if k in wanted}
    numbers = ", ".join(f"{c} {1 / g:,.0f}/s" for c, g in gen_s.items())
    trains = ", ".join(f"{d} {1 / t:,.0f}/s" for d, t in train_s.items() if t > 0)
    line = (f"auto: generation on the {str(chosen)} ({_shown(settings)}); "
            f"decisions/s of generation: {numbers}" + (f"; of training: {trains}" if trains else ""))
    return Decision(settings, line, {str(c): g for c, g in gen_s.items()}, dict(train_s),
                    {str(c): v for c, v in costs.items()})


def static(cfg: Any, why: str) -> Decision:
    """The choice where nothing is measured: float32, eager, generation where ``"auto"`` puts it."""
    wanted = auto_fields(cfg)
    settings = {k: v for k, v in {"policy.dtype": "float32", "gen.compile": "off"}.items() if k in wanted}
    return Decision(settings, f"auto: {_shown(settings)} ({why})" if settings else "")


# --- the measurement (the child process: imports torch) ---

def _timed(step, seconds: float, sync, give_up_s: float = float("inf")) -> float:
    """Median seconds of one ``step()`` over rounds filling ``seconds`` (after 3 warm-up calls); a first call
    slower than ``give_up_s`` is all that is timed (a candidate that slow loses anyway: W3 on the CPU)."""
    start = time.perf_counter()
    step()
    sync()
    if (first := time.perf_counter() - start) > give_up_s:
        return first
    for _ in range(2):
        step()
    sync()
    times, spent = [], 0.0
    while spent < seconds or len(times) < 3:
        start = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - start)
        spent += times[-1]
    return statistics.median(times)


def gen_batches(cfg: Any) -> list[int]:
    """The batch sizes generation will run: one group, and every group it may serve at once."""
    per = cfg.sim.envs_per_group
    groups = min(cfg.sim.groups, cfg.gen.max_batch_groups or cfg.sim.groups)
    return sorted({per, per * groups})


def measure(cfg: Any, accelerator: Any = None) -> Decision:
    """Time every candidate of ``cfg`` here and :func:`decide` (module docstring). ``accelerator``: a torch
    device standing in for the GPU, training's too (tests run the whole measurement on the CPU with it)."""
    import torch

    from ebrl import devices
    from ebrl.envs import EnvSpec, describe

    if accelerator is None:
        if not torch.cuda.is_available():
            return static(cfg, "torch sees no CUDA GPU here")
        gpu = torch.device("cuda", torch.cuda.current_device())
        train_device, bf16 = devices.resolve(cfg.train.device, "train.device"), torch.cuda.is_bf16_supported()
    else:
        gpu = train_device = torch.device(accelerator)
        bf16 = True
    train_on_gpu = train_device.type == gpu.type
    info = describe(EnvSpec.from_config(cfg.env))
    torch.manual_seed(0)
    gen_s = _time_generation(cfg, info, candidates(cfg, True, bf16, train_on_gpu), gpu)
    train_s: dict[str, float] = {}
    if train_on_gpu:
        train_s = _time_training(cfg, info, sorted({c.dtype for c in gen_s}) or ["float32"], train_device)
        gen_s = {c: v for c, v in gen_s.items() if c.dtype in train_s}  # a precision training cannot run in
    if not gen_s:
        return static(cfg, "no candidate ran on this GPU")
    return decide(cfg, gen_s, train_s, train_on_gpu)


def _synced(device: Any):
    """A function that waits for ``device``'s queued work (nothing to wait for on the CPU)."""
    import torch

    return (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)


def _time_generation(cfg: Any, info: Any, cands: list[Candidate], gpu: Any) -> dict[Candidate, float]:
    """Seconds per decision of each candidate's chunk forward, averaged over the run's batch sizes; a
    candidate that cannot run (out of memory, a failed capture) is left out."""
    import torch

    from ebrl import devices, threads
    from ebrl.envs.obs import sample_observations
    from ebrl.policies import make_policy
    from ebrl.policies.graphs import Actor

    batches, gen_s = gen_batches(cfg), {}
    policy_cfg = dataclasses.replace(cfg.policy, checkpoint="")
    for device in sorted({c.device for c in cands}, reverse=True):  # the GPU's first: the CPU's can give up early
        where = gpu if device == "cuda" else torch.device("cpu")
        model = make_policy(policy_cfg, info.layout, info.action_dim, info.bounds).to(where).eval()
        if device == "cpu":
            threads.set_threads(cfg.gen.threads)
        for c in (c for c in cands if c.device == device):
            actor, stage = Actor(model, c.compile, c.dtype), devices.Staging(where)
            give_up = 20 * max(batches) * min(gen_s.values()) if gen_s else float("inf")
            try:
                per = [_timed(lambda: actor(stage(obs)), GEN_SECONDS, _synced(where), give_up) / len(obs)
                       for obs in (sample_observations(info.layout, b) for b in batches)]
            except RuntimeError as exc:  # e.g. out of memory at the largest batch: not a candidate here
                log.warning("auto: %s could not run (%s)", c, str(exc).splitlines()[0])
                continue
            if c.compile == "cudagraphs" and not actor.graphed:
                continue  # the capture failed (Actor logged it): it ran eagerly, which is the other candidate
            gen_s[c] = sum(per) / len(per)
    return gen_s


def _time_training(cfg: Any, info: Any, dtypes: list[str], device: Any) -> dict[str, float]:
    """Seconds per decision of training in each precision of ``dtypes``: a gradient step of a minibatch
    (``train.batch_size / algo.minibatches``) times ``algo.epochs``, per decision; a precision that cannot
    run (out of memory) is left out."""
    import torch

    from ebrl import devices
    from ebrl.algos.ppo import make_adam
    from ebrl.envs.obs import sample_observations
    from ebrl.policies import make_policy

    model = make_policy(dataclasses.replace(cfg.policy, checkpoint=""), info.layout, info.action_dim,
                        info.bounds).to(device)
    optimizer = make_adam(model.parameters(), 1e-6)
    mb = max(1, cfg.train.batch_size // max(1, cfg.algo.minibatches))
    obs = torch.as_tensor(sample_observations(info.layout, mb), dtype=torch.float32, device=device)
    actions, _, _, latents = (torch.as_tensor(a, device=device) for a in model.act(obs))

    def step() -> None:
        logp, entropy, value = model.evaluate(obs, actions, latents)
        loss = -logp.float().mean() - entropy.float().mean() + value.float().pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    out = {}
    for dtype in dtypes:
        try:
            with devices.autocast(device, dtype):
                out[dtype] = _timed(step, TRAIN_SECONDS, _synced(device)) * cfg.algo.epochs / mb
        except RuntimeError as exc:  # e.g. out of memory: training cannot run so; neither can its generation
            log.warning("auto: training in %s could not run (%s)", dtype, str(exc).splitlines()[0])
    return out


# --- the launcher's side ---

def settle(cfg: Any, roles: tuple[str, ...], multi: bool,
           earlier: dict[str, str] | None = None) -> tuple[Any, Decision | None]:
    """``cfg`` with its "auto" fields decided for this host (``roles``: the services it runs; ``multi``: one
    host of several), and the decision (None: nothing was "auto"). ``earlier``: the settings the run decided at
    its first start (``meta.json``), which a resumed run keeps: its checkpoint was trained in that precision."""
    kept, notes = {}, []
    if cpu_bf16_refused(cfg, roles):
        kept["policy.dtype"] = "float32"
        notes.append("policy.dtype = 'float32' (the config asks for bfloat16 on this host's CPU, which has no "
                     "bfloat16 units: emulated, it would be slower)")
        cfg = apply(cfg, kept)
    if not auto_fields(cfg) and not kept:
        return cfg, None
    if resumed := {k: v for k, v in (earlier or {}).items() if k in auto_fields(cfg)}:
        kept.update(resumed)  # (gen.device "auto" kept as "auto": the GPU was chosen, wherever the run resumes)
        notes.append(f"{_shown(resumed)} (as this run decided at its start)")
    if multi and cfg.policy.dtype == "auto" and "policy.dtype" not in kept:  # hosts must agree: none measures it
        kept["policy.dtype"] = "float32"
        notes.append("policy.dtype = 'float32' (one precision on every host of the run)")
    cfg = apply(cfg, kept)
    if not [f for f in auto_fields(cfg) if f not in kept]:
        decision = Decision({}, "")
    elif cfg.gen.device == "cpu":  # one candidate: float32 (bfloat16 on a CPU is not faster), eager
        decision = static(cfg, "gen.device = 'cpu'")
    elif "gen" not in roles and "train" not in roles:
        decision = static(cfg, "no gen or train on this host")
    elif not host_has_gpu():
        decision = static(cfg, "no GPU on this host")
    else:
        decision = measured(cfg)
    decision.settings = {**kept, **decision.settings}
    if notes:
        decision.line = "auto: " + "; ".join(notes + ([decision.line.removeprefix("auto: ")] if decision.line else []))
    return apply(cfg, decision.settings), decision


def cpu_bf16_refused(cfg: Any, roles: tuple[str, ...]) -> bool:
    """Whether an explicit ``policy.dtype = "bfloat16"`` would run on a CPU without bfloat16 units here: this host
    runs generation or training, has no GPU (or generation is on the CPU), and the CPU lacks them."""
    from ebrl import devices

    if cfg.policy.dtype != "bfloat16" or not ({"gen", "train"} & set(roles)):
        return False
    on_cpu = cfg.gen.device == "cpu" or cfg.train.device == "cpu" or not host_has_gpu()
    return on_cpu and not devices.cpu_has_bf16()


def _shown(settings: dict[str, str]) -> str:
    return ", ".join(f"{k} = {v!r}" for k, v in settings.items())


def host_has_gpu() -> bool:
    """Whether NVML finds a GPU here."""
    return bool(gpu_names())


def gpu_names() -> list[str]:
    """The names of this host's GPUs through NVML, as CUDA_VISIBLE_DEVICES leaves them to this process's
    children unnamed ([] without a driver): no torch and no CUDA context in the launcher."""
    from ebrl.resources.nvml import load_nvml

    try:
        nvml = load_nvml()
        if nvml is None:
            return []
        names = [nvml.nvmlDeviceGetName(nvml.nvmlDeviceGetHandleByIndex(i)) for i in range(nvml.nvmlDeviceGetCount())]
        return [n.decode() if isinstance(n, bytes) else str(n) for n in names]
    except Exception:  # no driver, no library: no GPU to measure on
        return []


def cache_path() -> Path | None:
    """Where measured decisions are kept between runs (``EBRL_AUTOTUNE_CACHE``; "off": nowhere): a benchmark's
    rounds, a restart of the launcher, the next run of the same config do not measure again."""
    value = os.environ.get("EBRL_AUTOTUNE_CACHE", "")
    if value == "off":
        return None
    return Path(value) if value else Path.home() / ".cache" / "ebrl" / "autotune.json"


def cache_key(cfg: Any) -> str:
    """What a measurement depends on: the GPUs, torch, and the parts of ``cfg`` that shape the policy, its
    batches and the candidates."""
    import hashlib
    from importlib import metadata

    try:
        torch_version = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch_version = "?"
    parts = {"gpus": gpu_names(), "visible": os.environ.get("CUDA_VISIBLE_DEVICES"), "torch": torch_version,
             "policy": {**dataclasses.asdict(cfg.policy), "checkpoint": ""}, "env": dataclasses.asdict(cfg.env),
             "batches": gen_batches(cfg), "gen": [cfg.gen.threads, cfg.gen.device, cfg.gen.compile],
             "train": [cfg.train.device, cfg.train.batch_size, cfg.algo.minibatches, cfg.algo.epochs]}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:32]


def cached(cfg: Any) -> Decision | None:
    path = cache_path()
    try:
        found = json.loads(path.read_text()).get(cache_key(cfg)) if path is not None else None
        return Decision(**found) if found else None
    except (OSError, ValueError, TypeError):  # none yet, or unreadable: measure
        return None


def remember(cfg: Any, decision: Decision) -> None:
    """Keep a measured decision (``ebrl.durable``: a concurrent run reads the old file or the new one)."""
    path = cache_path()
    if path is None or not decision.gen_s:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            known = json.loads(path.read_text())
        except (OSError, ValueError):
            known = {}
        known[cache_key(cfg)] = decision.to_dict()
        durable.write_text(path, json.dumps(known, indent=1) + "\n")
    except OSError as exc:  # a read-only home: measure again next time
        log.warning("auto: could not keep the measurement in %s: %s", path, exc)


def measured(cfg: Any) -> Decision:
    """The decision kept from an earlier measurement of the same thing, or a new one (:func:`run_child`)."""
    if (decision := cached(cfg)) is not None:
        decision.line += f" (measured earlier on this machine; {cache_path()})"
        return decision
    decision = run_child(cfg)
    remember(cfg, decision)
    return decision


def run_child(cfg: Any) -> Decision:
    """:func:`measure` in a child process (``python -m ebrl.autotune``); where it fails, the static choice,
    saying why (never an error: the run starts either way)."""
    import tempfile

    from ebrl import config as config_mod

    with tempfile.NamedTemporaryFile("w", suffix=".toml") as f:
        f.write(config_mod.dump_toml(cfg))
        f.flush()
        try:
            done = subprocess.run([sys.executable, "-m", "ebrl.autotune", f.name], capture_output=True, text=True,
                                  timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            return static(cfg, f"the measurement took over {TIMEOUT_S:.0f} s")
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        return static(cfg, f"the measurement failed: {last}")
    return Decision(**json.loads(done.stdout.strip().splitlines()[-1]))


def main(argv: list[str]) -> int:
    """``python -m ebrl.autotune CONFIG``: the decision for CONFIG on this machine, as one JSON line."""
    from ebrl import config as config_mod

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    decision = measure(config_mod.load(argv[0]))
    print(json.dumps(decision.to_dict()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

"""``gen.compile``: how generation runs a policy's chunk forward (``ChunkPolicy.sample``).

- ``"off"``: eagerly, one kernel launch per operation.
- ``"cudagraphs"``: on a CUDA device, the whole forward for one batch size (normalisation, encoder, the N
  denoising steps of a flow policy, sampling) is captured once as a CUDA graph and replayed: one launch per
  batch instead of hundreds, which is what a small policy at a small batch is bound by. Generation's batch
  sizes are few (whole groups), so a graph per size is kept, up to ``MAX_GRAPHS``; a further size runs eagerly.
  Parameters are read from their own storage at replay, and new weights are copied into that storage in
  place (``load_arrays``), so a graph stays valid across versions; the sampling noise comes from torch's CUDA
  generator, which advances on every replay. On the CPU there is nothing to capture: ``"cudagraphs"`` runs
  eagerly there (a config naming the CPU explicitly is refused by ``ebrl.config``). A policy whose forward
  cannot be captured (an operation that reads back to the host) is reported once and runs eagerly; a kind that knows it
cannot be (``ChunkPolicy.capturable = False``) is never tried.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch

from ebrl import devices
from ebrl.policies.base import ChunkPolicy, to_host

log = logging.getLogger("ebrl.policies")
# torch's "global" checks every thread of the process while a graph is captured: right for a process of its own;
# services sharing a process (ebrl.process) set "thread_local", so that the simulator's and training's work on
# their own threads and streams does not fail generation's capture, nor the capture theirs
CAPTURE_ERROR_MODE = "global"

MAX_GRAPHS = 16  # batch sizes with a captured graph
WARMUP = 2  # eager passes on a side stream before a capture (cuBLAS handles, autotuning, the allocator)


class Actor:
    """``act`` of ``policy`` under ``policy.dtype`` (``dtype``), eagerly or through per-batch-size CUDA graphs."""

    def __init__(self, policy: ChunkPolicy, mode: str = "off", dtype: str = "float32"):
        self.policy, self.dtype = policy, dtype
        self.device = policy.device
        capturable = type(policy).capturable  # a kind whose sample() reads back to the host says so
        self.graphed = mode == "cudagraphs" and self.device.type == "cuda" and capturable
        if mode == "cudagraphs" and not self.graphed:
            log.info("gen.compile = 'cudagraphs' on %s: %s, running eagerly", self.device,
                     "nothing to capture" if capturable else f"policy.kind = {policy.kind!r} is not capturable")
        self.graphs: dict[int, tuple[torch.Tensor, Any, tuple[torch.Tensor, ...]]] = {}
        self.pool = torch.cuda.graph_pool_handle() if self.graphed else None  # one memory pool for every graph

    def counters(self) -> dict[str, float]:
        """``dtype``: the bits of the forward's matrix products (16: bfloat16 autocast, 32: float32);
        ``compiled``: 1 while the forward runs through CUDA graphs (0: eagerly, or after a failed capture)."""
        return {"dtype": devices.dtype_bits(self.dtype), "compiled": float(self.graphed)}

    def __call__(self, obs: torch.Tensor) -> tuple[np.ndarray, ...]:
        """Chunks for ``obs`` ([B, ...] float32 on the policy's device): actions, log-probs, values, latents."""
        batch = obs.shape[0]
        if self.graphed and (batch in self.graphs or len(self.graphs) < MAX_GRAPHS):
            try:
                static_in, graph, outs = self.graphs.get(batch) or self.capture(obs)
            except RuntimeError as exc:  # an operation CUDA cannot capture: say so once, then run eagerly
                log.warning("gen.compile = 'cudagraphs': capturing the chunk forward failed (%s); running eagerly",
                            str(exc).splitlines()[0])
                self.graphed, self.graphs = False, {}
                torch.cuda.synchronize(self.device)
            else:
                static_in.copy_(obs)
                graph.replay()
                return to_host(*outs)
        with devices.autocast(self.device, self.dtype):
            return self.policy.act(obs)

    def capture(self, obs: torch.Tensor) -> tuple[torch.Tensor, Any, tuple[torch.Tensor, ...]]:
        # torch.distributions checks its arguments and samples by reading them back to the host: a
        # synchronisation, which invalidates a capture (seen on an H100). Generation's own inputs are the
        # policy's; the checks stay on in training, where they guard the loss.
        validate = torch.distributions.Distribution._validate_args
        torch.distributions.Distribution.set_default_validate_args(False)
        try:
            return self._capture(obs)
        finally:
            torch.distributions.Distribution.set_default_validate_args(validate)

    def _capture(self, obs: torch.Tensor) -> tuple[torch.Tensor, Any, tuple[torch.Tensor, ...]]:
        static_in = obs.clone()
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side), torch.no_grad(), devices.autocast(self.device, self.dtype):
            for _ in range(WARMUP):
                self.policy.sample(static_in)
        torch.cuda.current_stream(self.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=self.pool, capture_error_mode=CAPTURE_ERROR_MODE), torch.no_grad(), \
                devices.autocast(self.device, self.dtype):
            outs = self.policy.sample(static_in)
        entry = (static_in, graph, tuple(outs))
        self.graphs[obs.shape[0]] = entry
        log.info("gen.compile: captured the chunk forward for batch %d (%d graphs)", obs.shape[0], len(self.graphs))
        return entry

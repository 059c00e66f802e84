"""Hardware the stages run on: CPU cores and GPUs (NVML)."""

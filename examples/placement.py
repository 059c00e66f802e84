"""The allocator's programming API on CPU: profile the quickstart's stages, place them, re-balance from measurements."""
from ebrl import EmbodiPlacement, ResourcePool, StageRates, config, profile
from ebrl.alloc.profile import measure_gen, measure_sim, measure_train

if __name__ == "__main__":  # env workers are child processes that import this file
    cfg = config.load("configs/quickstart.toml")
    pool = ResourcePool(gpu_pool="none", cpu_pool="flat")
    prof = profile(pool, cfg, seconds=0.2)  # P_sim, P_gen, P_train over this machine's cores
    placement = EmbodiPlacement(pool=pool, profile=prof, window=2, patience=2)
    placement.apply()
    for it in range(4):  # stands in for a training loop that measures each stage on its current cores
        cores = placement.plan.cores
        stats = StageRates(sim=measure_sim(cfg, cores["sim"], len(cores["sim"]), 0.2),
                           gen=measure_gen(cfg, cores["gen"], 8, 0.2),
                           train=measure_train(cfg, cores["train"], 1024, 0.2))
        placement.balance(stats).apply()
        print(f"iteration {it}: plan v{placement.plan.version} {placement.plan.cores}, measured {stats}")

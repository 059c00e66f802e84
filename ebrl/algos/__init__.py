"""Learning algorithms: advantages and PPO."""

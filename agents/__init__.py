"""RL agents (PPO over batches of levels) that train on env tasks (not implemented yet)."""

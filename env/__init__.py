"""Kinetix-style tasks on the engine: levels, episodes, rewards, observations (not implemented yet)."""

"""Launching `kforge run` on Ray clusters: `submit` (Ray Jobs API), `slurm.sbatch`, `ray-cluster.yaml`.

Run from a checkout (`python -m kforge.jobs.submit ...`): the checkout is what a submitted job runs, so this package
is not installed with the project.
"""

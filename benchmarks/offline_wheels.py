"""Wheels for running the accelerator report on a machine without network that already has JAX for its GPU.

Run here, where pip reaches a package index; carry the folder to the machine and install there without an index:

    python -m benchmarks.offline_wheels --python-version 3.12 --out wheels
    # on the machine, from the repository's root:
    pip install --no-index --no-deps --target /tmp/kforge-site wheels/kforge/*.whl
    pip install --no-index --no-deps --target /tmp/kinetix-site wheels/kinetix/*.whl
    PYTHONPATH=/tmp/kforge-site:. python -m benchmarks.accelerator --kinetix-site /tmp/kinetix-site > report.json

The machine is assumed to hold a CUDA image's scientific Python: jax with its CUDA plugin, flax, optax, chex,
tensorstore, numpy, scipy, pandas, matplotlib, seaborn, pyyaml, tqdm, pillow, imageio, protobuf, rich, six and
their needs. `kforge/` holds what the project and Jax2D need beyond that (not Ray, whose wheel alone is larger than many
transfers allow: the report's pipeline then runs its jobs without Ray, `ray.num_workers=0`); `kinetix/` holds
kinetix-env and what its PPO imports, unpinned from its JAX (it runs under newer JAX with jax2d 1.0.2 in place of
its pinned 1.0.1), kept apart because it needs zarr 2 where kforge needs zarr 3. Prints each folder's size.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

KFORGE_WHEELS = (
    "zarr==3.1.6",
    "numcodecs==0.16.6",
    "donfig",
    "google-crc32c",
    "omegaconf==2.4.0",
    "jax2d==1.0.2",  # Jax2D in the same run as ours
)
"""The project's needs (pyproject.toml's pins) missing from a CUDA image, and Jax2D."""

KINETIX_WHEELS = (
    "kinetix-env==3.0.2",
    "zarr==2.18.3",
    "numcodecs==0.13.1",  # zarr 2 needs the blosc functions that numcodecs 0.16 dropped
    "asciitree",
    "antlr4-python3-runtime",
    "jaxgl",
    "distrax",
    "tfp-nightly",  # distrax's TensorFlow Probability; the 0.25 release fails on new JAX
    "dm-tree",
    "decorator",
    "gymnax",
    "gymnasium",
    "farama-notifications",
    "grain",
    "array-record",
    "wandb",  # imported by kinetix.util at module level, never called by the PPO baseline
    "platformdirs",
    "pydantic",
    "pydantic-core",
    "annotated-types",
    "typing-inspection",
    "opentelemetry-api",
    "opentelemetry-sdk",
    "opentelemetry-proto",
    "opentelemetry-semantic-conventions",
    "opentelemetry-exporter-otlp-proto-http",
    "opentelemetry-exporter-otlp-proto-common",
    "opentelemetry-exporter-http-transport",
    "googleapis-common-protos",
    "orbax-export",
    "portpicker",
)
"""What `benchmarks/kinetix_ppo_baseline.py` imports through kinetix-env, beyond a CUDA image and `KFORGE_WHEELS`
(found by importing it with each package blocked in turn)."""

LINUX_PLATFORMS = tuple(f"manylinux_2_{minor}_x86_64" for minor in (17, 24, 27, 28)) + (
    "manylinux2014_x86_64",
    "manylinux1_x86_64",
)
"""Platform tags a current x86-64 Linux accepts (pip matches each exactly)."""


def download(requirements: tuple[str, ...], folder: Path, python_version: str) -> int:
    """Download each requirement's wheel, without its dependencies, into `folder`; returns their bytes."""
    folder.mkdir(parents=True, exist_ok=True)
    platforms = [option for platform in LINUX_PLATFORMS for option in ("--platform", platform)]
    command = [
        sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
        "--python-version", python_version, "--implementation", "cp", *platforms, "--dest", str(folder),
        *requirements,
    ]  # fmt: skip
    subprocess.run(command, check=True)
    return sum(path.stat().st_size for path in folder.glob("*.whl"))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("wheels"), help="folder of kforge/ and kinetix/")
    parser.add_argument(
        "--python-version",
        default=f"{sys.version_info.major}.{sys.version_info.minor}",
        help="the machine's Python, e.g. 3.12 (default: this one's)",
    )
    parser.add_argument("--no-kinetix", action="store_true", help="only kforge/ (no Kinetix PPO in the report)")
    args = parser.parse_args(argv)
    sets = {"kforge": KFORGE_WHEELS} | ({} if args.no_kinetix else {"kinetix": KINETIX_WHEELS})
    for name, requirements in sets.items():
        size = download(requirements, args.out / name, args.python_version)
        print(f"{args.out / name}: {len(requirements)} wheels, {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()

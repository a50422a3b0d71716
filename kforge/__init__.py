"""kforge: expert-trajectory datasets of Kinetix-style 2D physics tasks, generated on its own JAX engine.

The packages, each with its own public surface: `kforge.engine` (rigid-body physics), `kforge.env` (levels, the
task, observations), `kforge.agents` (PPO experts, behaviour cloning), `kforge.pipeline` (dataset format,
generation, reading, Kinetix interop, the `kforge` command), `kforge.configs` (release splits and scales) and, in a
checkout, `kforge.jobs` (cluster launchers).

The names below are the user API of a few lines: generate a dataset, read it, and play levels. Each is imported when
first used, so `import kforge` loads neither JAX nor Ray.
"""

from pathlib import Path

_CHECKOUT = Path(__file__).resolve().parent.parent
if (_CHECKOUT / "pyproject.toml").is_file() and (_CHECKOUT / "pipeline" / "__init__.py").is_file():
    # Run from a checkout without installing (a Ray job's uploaded working dir): its top-level folders are the
    # subpackages, as the installed wheel's package-dir mapping makes them.
    __path__.append(str(_CHECKOUT))

from kforge.pipeline.lazy import lazy_surface  # noqa: E402  (needs the path above in a checkout)

__version__ = "0.1.0"

__getattr__, _names = lazy_surface(
    __name__,
    {
        "kforge.pipeline.generation": "load_config run_job",
        "kforge.pipeline.reading": "TrajectoryDatasetManager",
        "kforge.env": "Environment EnvParams load_level sample_levels filter_levels",
    },
)
__all__ = [*_names, "__version__"]

"""The job config's schema: its sections as dataclasses, each key's type, default and meaning on its line."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import textwrap
import tokenize
import typing

from omegaconf import MISSING

from kforge.agents import PPOHyperparameters
from kforge.pipeline.generation.compile_cache import DEFAULT_COMPILE_CACHE_DIR

PHYSICS_SCHEME_NAMES = ("kforge", "kinetix")
"""Names of the engine's physics schemes (`engine.PHYSICS_SCHEMES`), the values of `env.physics`."""

JOB_PHYSICS_SCHEME = "kinetix"
"""The scheme a job plays under unless `env.physics` names another: Kinetix's play, as the data stands for Kinetix's
(the engine's own default scheme, kforge, stays available)."""

ENV_SIZES = ("s", "m", "l")
"""Kinetix env sizes (`engine.KINETIX_SIZES`), the values of `split.size`."""


@dataclasses.dataclass
class SplitConfig:
    """Which levels make up the dataset split."""

    name: str = MISSING  # split name as in the release, e.g. "1M/s"
    size: str = "s"  # env size: s, m or l
    seed: int = 0  # split seed; level i's PRNG key derives from (seed, i)
    num_levels: int = 64  # levels sampled for the split (kept trajectories are at most this many)
    expert_budget: int = 1_000_000  # PPO env steps per level (the release's "1M" / "10M")


@dataclasses.dataclass
class WorkConfig:
    """How levels are cut into units of work; both sizes are part of the data's identity."""

    levels_per_shard: int = 64  # levels per shard (one writer per shard)
    levels_per_batch: int = 16  # levels trained together in one vmapped program; divides levels_per_shard


@dataclasses.dataclass
class FilterConfig:
    """The trivial-level filter applied before training."""

    enabled: bool = True  # drop flagged levels before paying for PPO (they are recorded with the reason)
    noop_steps: int = 256  # env steps of the no-op rollout that detects levels solved by doing nothing


PPO_KEYS_SET_BY_THE_JOB = {"env_steps_per_level": "split.expert_budget", "select_greedy": "collect.greedy"}
"""`agents.PPOHyperparameters` fields the `ppo` section leaves out, and the key each comes from."""


def section_of(declaration: type, name: str, doc: str, leave_out: tuple[str, ...] = ()) -> type:
    """A config section (a plain dataclass OmegaConf can merge into) with the fields of dataclass `declaration`
    but `leave_out`, in its order, with its annotations, defaults and line comments (`field_docs`)."""
    docs = field_docs(declaration)
    fields = [
        (field.name, field.type, dataclasses.field(default=field.default, metadata={"doc": docs[field.name]}))
        for field in dataclasses.fields(declaration)
        if field.name not in leave_out
    ]
    namespace = {"__doc__": doc, "__module__": __name__, "__qualname__": name}
    return dataclasses.make_dataclass(name, fields, namespace=namespace)


def field_docs(section: type) -> dict[str, str]:
    """Field name -> its meaning: the comment on its line in the class's source (`name: type = default  # comment`),
    or for a generated section (`section_of`) the comment it was declared with."""
    fields = dataclasses.fields(section)
    if fields and all("doc" in field.metadata for field in fields):
        return {field.name: field.metadata["doc"] for field in fields}
    source = textwrap.dedent(inspect.getsource(section))
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    comments = {token.start[0]: token.string.lstrip("#").strip() for token in tokens if token.type == tokenize.COMMENT}
    body = ast.parse(source).body[0].body
    return {node.target.id: comments.get(node.lineno, "") for node in body if isinstance(node, ast.AnnAssign)}


PPOSection = section_of(
    PPOHyperparameters,
    "PPOSection",
    "Specialist PPO settings, declared by `agents.PPOHyperparameters` (evidence for the values: docs/experts.md).",
    leave_out=tuple(PPO_KEYS_SET_BY_THE_JOB),
)


@dataclasses.dataclass
class ExpertsConfig:
    """How long each expert trains (docs/experts.md, adaptive budgets)."""

    budget_mode: str = "fixed"  # fixed, streamed (filtered levels take no slot) or adaptive: docs/experts.md
    solved_evaluations: int = 2  # adaptive: stop after this many consecutive evaluations with every episode successful
    solved_window: bool = True  # adaptive: ... and only once the window the expert would store succeeds
    give_up_env_steps: int = 250_000  # adaptive: give up once trained this long without any successful episode


@dataclasses.dataclass
class CollectConfig:
    """The stored window of each expert."""

    window_steps: int = 256  # env steps per stored trajectory
    greedy: bool = False  # act with the most probable choice per slot instead of sampling


@dataclasses.dataclass
class EnvSection:
    """Environment parameters of the experts' training episodes."""

    dense_reward_scale: float = 0.2  # shaping scale used for training (Kinetix's repository configs use 0.2)
    physics: str = JOB_PHYSICS_SCHEME  # kinetix (Kinetix's play) or kforge (the engine's own), engine.PHYSICS_SCHEMES


@dataclasses.dataclass
class RayConfig:
    """Where the job runs; none of these change the data."""

    address: str | None = None  # None: embedded local Ray; "auto" or host:port: a running cluster
    num_workers: int = 1  # worker actors; 0: no Ray, the job's own process does the work
    cpus_per_worker: float = 1.0  # CPUs Ray reserves per worker actor
    gpus_per_worker: float = 0.0  # GPUs Ray reserves per worker actor (1.0: one GPU each; JAX then runs on it)
    deterministic_gpu_ops: bool = False  # workers turn on XLA's deterministic GPU ops (not needed: jobs repeat without)


@dataclasses.dataclass
class LeaseConfig:
    """The job's lease on its dataset (one job per dataset, docs/object-storage.md); none of these change the data.
    The defaults are `pipeline.storage`'s."""

    stale_after_s: float = 300.0  # [s] a lease whose heartbeat is older is taken over
    heartbeat_s: float = 30.0  # [s] interval between the running job's heartbeats


TRACKING_MODES = ("offline", "online", "disabled")
"""Values of `tracking.wandb`."""


@dataclasses.dataclass
class TrackingConfig:
    """Experiment tracking of a run (pipeline/generation/tracking.py); none of these change the data."""

    wandb: str = "offline"  # offline: local run files (`wandb sync` uploads them); online: needs a login; disabled
    project: str = "kforge"  # wandb project
    name: str | None = None  # wandb run name; None: wandb picks one
    dir: str | None = None  # directory that receives wandb/<run>; None: the dataset's log folder, beside the run logs


@dataclasses.dataclass
class CompileCacheConfig:
    """JAX's persistent compilation cache of the workers (on a cluster: storage the nodes share); none of these change
    the data."""

    dir: str | None = DEFAULT_COMPILE_CACHE_DIR  # folder of compiled programs reused by workers and re-runs; null: off


@dataclasses.dataclass
class JobConfig:
    """A generation job: the split, how it is cut and trained, and where it runs and writes."""

    output_dir: str = MISSING  # dataset directory (created; re-running resumes); unset: outputs/<split name>-<scale>
    scale: str | None = None  # scale preset applied over the config file (kforge run --scale); recorded, not re-applied
    split: SplitConfig = dataclasses.field(default_factory=SplitConfig)
    work: WorkConfig = dataclasses.field(default_factory=WorkConfig)
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    env: EnvSection = dataclasses.field(default_factory=EnvSection)
    ppo: PPOSection = dataclasses.field(default_factory=PPOSection)
    experts: ExpertsConfig = dataclasses.field(default_factory=ExpertsConfig)
    collect: CollectConfig = dataclasses.field(default_factory=CollectConfig)
    ray: RayConfig = dataclasses.field(default_factory=RayConfig)
    lease: LeaseConfig = dataclasses.field(default_factory=LeaseConfig)
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    compile_cache: CompileCacheConfig = dataclasses.field(default_factory=CompileCacheConfig)


FIXED_BUDGET_MODE, STREAMED_BUDGET_MODE, ADAPTIVE_BUDGET_MODE = "fixed", "streamed", "adaptive"
BUDGET_MODES = (FIXED_BUDGET_MODE, STREAMED_BUDGET_MODE, ADAPTIVE_BUDGET_MODE)
"""Values of `experts.budget_mode`; a fixed-budget job's data definition leaves the `experts` section out (no key of
it changes a fixed-budget job's data)."""


class ConfigError(ValueError):
    """A job config that cannot be used; the message names the key."""


def schema_type(key: str, schema: type = JobConfig):
    """The annotated type of a dotted key in `schema` (`schema` itself for ""); None if there is no such key."""
    hint = schema
    for part in key.split(".") if key else ():
        if not dataclasses.is_dataclass(hint):
            return None
        hint = typing.get_type_hints(hint).get(part)
    return hint


def type_name(hint) -> str:
    """A schema type as users write it: int, float, bool, str, "str or null", "section"."""
    if dataclasses.is_dataclass(hint):
        return "section"
    args = typing.get_args(hint)
    if args:
        return " or ".join("null" if arg is type(None) else type_name(arg) for arg in args)
    return hint.__name__

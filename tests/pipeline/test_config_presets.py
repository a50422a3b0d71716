"""Release split configs at every scale: budgets, sizes and level counts as the release; the scale changes PPO only
at tiny (and only the documented keys); errors name the layer, the key and the expected type; the resolved config
documents every key and loads back to the same job."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from kforge.agents import PPOConfig, PPOHyperparameters
from kforge.configs import PPO_SPECIALIST
from kforge.pipeline.cli.run import main as run_main
from kforge.pipeline.generation import ConfigError, JobConfig, load_config, resolve, to_yaml
from kforge.pipeline.generation.config_yaml import specialist_yaml
from kforge.pipeline.generation.schema import PPO_KEYS_SET_BY_THE_JOB, PPOSection

pytestmark = pytest.mark.smoke

SPLITS_DIR = Path(__file__).resolve().parents[2] / "configs" / "splits"

RELEASE = {
    "1M/s": ("s", 1_000_000, 5_980_000),
    "1M/m": ("m", 1_000_000, 3_450_000),
    "1M/l": ("l", 1_000_000, 1_050_000),
    "10M/s": ("s", 10_000_000, 637_400),
    "10M/m": ("m", 10_000_000, 422_100),
}
"""Split -> (env size, expert budget [env steps per level], unique levels in the release); docs/kinetix.md,
released splits (level counts as published, rounded)."""

SCALES = ("tiny", "local", "local-gpu", "full")

TINY_LEVELS = 8
TINY_BUDGET = 65_536  # [env steps per level]
TINY_PPO = {"num_envs": 8, "num_steps": 32, "select_every_updates": 128}
"""The only PPO keys the tiny scale changes (documented in configs/scales/tiny.yaml)."""

LOCAL_LEVELS = 64
DATA_SETTINGS = ("filter", "env", "experts", "collect")
"""Sections a scale never changes: the split's filter, env, expert budget mode and collection settings."""


def split_file(name: str) -> Path:
    return SPLITS_DIR / f"{name}.yaml"


def test_there_is_one_config_per_release_split():
    files = sorted(path.relative_to(SPLITS_DIR).with_suffix("").as_posix() for path in SPLITS_DIR.rglob("*.yaml"))
    assert files == sorted(RELEASE)


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("split", RELEASE)
def test_split_at_a_scale_has_the_release_settings(split, scale):
    size, budget, release_levels = RELEASE[split]
    job = load_config(split_file(split), scale=scale)
    unscaled = load_config(split_file(split))
    assert (job.split.name, job.split.size, job.split.seed) == (split, size, unscaled.split.seed)
    assert job.split.expert_budget == (TINY_BUDGET if scale == "tiny" else budget)
    assert (
        job.split.num_levels
        == {"tiny": TINY_LEVELS, "local": LOCAL_LEVELS, "local-gpu": LOCAL_LEVELS, "full": release_levels}[scale]
    )
    assert job.scale == scale
    assert job.output_dir == f"outputs/{split.replace('/', '-')}-{scale}"
    for section in DATA_SETTINGS:
        assert getattr(job, section) == getattr(unscaled, section), section

    ppo = dataclasses.asdict(job.ppo)
    expected = dataclasses.asdict(PPOSection()) | (TINY_PPO if scale == "tiny" else {})
    assert ppo == expected


def test_gpu_scale_runs_one_worker_per_gpu_on_the_local_levels():
    local, gpu = (load_config(split_file("1M/s"), scale=scale) for scale in ("local", "local-gpu"))
    assert (gpu.ray.gpus_per_worker, local.ray.gpus_per_worker) == (1.0, 0.0)
    assert gpu.work.levels_per_batch > local.work.levels_per_batch
    assert gpu.work.levels_per_shard % gpu.work.levels_per_batch == 0


def test_splits_have_distinct_seeds():
    seeds = [load_config(split_file(split)).split.seed for split in RELEASE]
    assert len(set(seeds)) == len(seeds)


def test_scale_presets_other_than_tiny_set_no_training_keys():
    scales_dir = SPLITS_DIR.parent / "scales"
    for scale in ("local", "local-gpu", "full"):
        preset = OmegaConf.to_container(OmegaConf.load(scales_dir / f"{scale}.yaml"))
        assert not {"ppo", "filter", "env", "collect"} & set(preset), scale
        assert "expert_budget" not in preset.get("split", {}), scale


# -------------------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("split.num_levels=many", "overrides: split.num_levels: expected int, got 'many' (str)"),
        ("ppo.num_envs=3.5", "overrides: ppo.num_envs: expected int, got 3.5 (float)"),
        ("ppo.learning_rate=fast", "overrides: ppo.learning_rate: expected float, got 'fast' (str)"),
        ("filter.enabled=maybe", "overrides: filter.enabled: expected bool, got 'maybe' (str)"),
        ("ppo.learning_rat=0.1", "unknown key ppo.learning_rat (did you mean ppo.learning_rate?)"),
        ("ppo.zzz=1", "unknown key ppo.zzz; ppo has: num_envs, num_steps,"),
        ("num_levels=3", "unknown key num_levels; the top level has: output_dir, scale, split,"),
        ("ppo=3", "overrides: ppo: expected a section with keys num_envs,"),
        ("scale=tiny", "--scale"),
        ("split.num_levels", "'split.num_levels' is not of the form key=value"),
        ("ray.num_workers=-1", "ray.num_workers must be >= 0 (0: no Ray, in this process), got -1"),
    ],
)
def test_a_bad_override_names_the_key_and_expected_type(override, message):
    with pytest.raises(ConfigError) as error:
        load_config(split_file("1M/s"), [override], scale="tiny")
    assert message in str(error.value)


def test_a_bad_value_in_a_file_names_the_file_key_and_type(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("split:\n  name: x/s\n  seed: first\n")
    with pytest.raises(ConfigError, match=rf"^{path}: split\.seed: expected int, got 'first' \(str\)$"):
        load_config(path)


def test_a_job_without_ray_cannot_name_a_ray_cluster():
    with pytest.raises(ConfigError, match=r"^ray\.address \('auto'\) needs ray\.num_workers >= 1; 0 runs without Ray$"):
        load_config(split_file("1M/s"), ["ray.num_workers=0", "ray.address=auto"], scale="tiny")


def test_an_unknown_scale_lists_the_presets():
    with pytest.raises(ConfigError, match=r"scale 'huge': expected one of full, local, local-gpu, tiny or a path"):
        load_config(split_file("1M/s"), scale="huge")


def test_without_output_dir_or_split_name_the_missing_key_is_named():
    with pytest.raises(ConfigError, match=r"^output_dir: missing"):
        load_config(None, [])


# --------------------------------------------------------------------------------------- resolved config


def _leaf_fields(schema: type, prefix: str = ""):
    """(dotted key, annotation string) of every non-section field of the schema."""
    for field in dataclasses.fields(schema):
        section = field.default_factory
        if section is not dataclasses.MISSING and dataclasses.is_dataclass(section):
            yield from _leaf_fields(section, f"{prefix}{field.name}.")
        else:
            yield f"{prefix}{field.name}", field.type


def _commented_keys(text: str) -> dict[str, str]:
    """Dotted key -> comment of each key line of a two-level YAML text."""
    comments, section = {}, ""
    for line in text.splitlines():
        entry, comment = line.split("  # ", 1)
        name, value = entry.strip().split(":", 1)
        if not line.startswith(" "):
            section = "" if value.strip() else f"{name}."
            if value.strip():
                comments[name] = comment
        else:
            comments[section + name] = comment
    return comments


def test_resolved_config_documents_every_key_with_its_type():
    comments = _commented_keys(to_yaml(load_config(split_file("1M/m"), scale="local")))
    keys = dict(_leaf_fields(JobConfig))
    assert len(keys) > 30  # the walk found the sections' keys
    assert sorted(comments) == sorted(keys)
    for key, annotation in keys.items():
        expected_type = annotation.replace(" | None", " or null")
        declared_type, meaning = comments[key].split(": ", 1)
        assert declared_type == expected_type, key
        assert meaning.strip(), f"{key} has no description"


def test_resolved_config_records_the_scale_and_loads_back_without_reapplying_it(tmp_path):
    job = load_config(split_file("1M/s"), ["split.num_levels=12"], scale="tiny")
    saved = tmp_path / "config.yaml"
    saved.write_text(to_yaml(job))
    assert "scale: tiny" in saved.read_text()
    assert load_config(saved) == job  # num_levels stays 12: the recorded scale is not applied again


def test_run_print_config_prints_the_resolved_config_and_runs_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    run_main([str(split_file("10M/s")), "--scale", "tiny", "collect.greedy=true", "--print-config"])
    expected = to_yaml(load_config(split_file("10M/s"), ["collect.greedy=true"], scale="tiny"))
    assert capsys.readouterr().out == expected
    assert "greedy: true" in expected
    assert not (tmp_path / "outputs").exists()


def test_the_ppo_section_is_the_agents_declaration_less_the_keys_the_job_sets():
    declared = [field.name for field in dataclasses.fields(PPOHyperparameters)]
    section = [field.name for field in dataclasses.fields(PPOSection)]
    assert section == [name for name in declared if name not in ("env_steps_per_level", "select_greedy")]
    assert set(PPO_KEYS_SET_BY_THE_JOB) == {"env_steps_per_level", "select_greedy"}
    job = load_config("1M/s", ["collect.greedy=true"])
    assert resolve(job).ppo == PPOConfig(env_steps_per_level=1_000_000, select_greedy=True)
    assert "  num_minibatches: 4  # int: minibatches per epoch; must divide num_envs * num_steps" in to_yaml(job)


def test_the_specialist_yaml_is_generated_from_the_agents_declaration():
    assert PPO_SPECIALIST.read_text() == specialist_yaml(), (
        "configs/ppo_specialist.yaml is out of date; regenerate it: python -c 'from "
        'kforge.pipeline.generation.config_yaml import specialist_yaml; print(specialist_yaml(), end="")\' '
        "> configs/ppo_specialist.yaml"
    )
    assert PPOConfig.from_mapping(yaml.safe_load(specialist_yaml())) == PPOConfig()


def test_a_split_is_named_like_the_release_or_given_as_a_file(tmp_path):
    by_name, by_file = load_config("10M/m"), load_config(split_file("10M/m"))
    assert by_name == by_file and by_name.split.name == "10M/m"
    with pytest.raises(ConfigError, match=r"config '3M/s': no such file, and not a split name \(splits: 10M/m, "):
        load_config("3M/s")


def test_a_job_resolves_once_into_settings_equal_and_hashed_by_its_config():
    job = load_config("10M/m", ["env.dense_reward_scale=0.5"], scale="tiny")
    resolved = resolve(job)
    assert resolved == resolve(load_config("10M/m", ["env.dense_reward_scale=0.5"], scale="tiny"))
    assert hash(resolved) == hash(resolve(load_config("10M/m", ["env.dense_reward_scale=0.5"], scale="tiny")))
    assert resolved != resolve(load_config("10M/m", ["env.dense_reward_scale=0.5", "split.seed=9"], scale="tiny"))
    assert resolved.ppo.env_steps_per_level == 65_536 and resolved.ppo.num_envs == 8
    assert resolved.env_params.dense_reward_scale == 0.5
    assert (resolved.split, resolved.work, resolved.collect) == (job.split, job.work, job.collect)
    with pytest.raises(dataclasses.FrozenInstanceError):
        resolved.ppo = None

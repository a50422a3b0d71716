"""`kforge levels`: sampled levels survive import unchanged, export writes the levels a run of the split trains,
import names the field of a malformed file and reports normalisation, previews are real images, --help explains."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
import pytest
from PIL import Image

from kforge.env import StaticEnvParams, load_level, sample_levels
from kforge.pipeline.cli.levels import main
from kforge.pipeline.generation import load_config, resolve
from kforge.pipeline.generation.level_batch import KeyPurpose, level_keys, sample_batch

SPLIT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "splits" / "1M" / "s.yaml"
SEED = 7
SAMPLED_IDS = (3, 4)
KEY_BATCH = 64  # levels per direct sampler call here (the CLI's chunk; one compiled shape for the session)
EXPORTED_ID = 5
TINY_LEVELS_PER_BATCH = 4  # work.levels_per_batch of the tiny scale: level 5 is slot 1 of the batch of levels 4-7
PREVIEW_PIXELS = 64  # [px] preview side
GIF_STEPS = 4  # [env steps]
TRAINING_DENSE_REWARD_SCALE = 0.2  # env.dense_reward_scale of every split


def assert_levels_equal(a, b):
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree.leaves(b), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, jax.tree_util.keystr(path)
        np.testing.assert_array_equal(x, y, err_msg=jax.tree_util.keystr(path))


def level_at(levels, index):
    return jax.tree.map(lambda x: np.asarray(x)[index], levels)


@pytest.fixture(scope="module")
def sampled_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sampled")
    argv = ["sample", "--size", "s", "--seed", str(SEED), "--start", str(SAMPLED_IDS[0])]
    main([*argv, "--num", str(len(SAMPLED_IDS)), "--out", str(out), "--no-progress"])
    return out


def test_sampled_levels_survive_import_unchanged(sampled_dir, tmp_path, capsys):
    direct = sample_levels(level_keys(SEED, np.arange(KEY_BATCH), KeyPurpose.SAMPLE), StaticEnvParams.for_size("s"))
    assert sorted(path.name for path in sampled_dir.iterdir()) == [f"level-{i:07d}.json" for i in SAMPLED_IDS]
    for level_id in SAMPLED_IDS:
        imported = tmp_path / f"{level_id}.json"
        main(["import", str(sampled_dir / f"level-{level_id:07d}.json"), "--out", str(imported)])
        assert "already normalised" in capsys.readouterr().out
        loaded = load_level(imported)
        assert loaded.static == StaticEnvParams.for_size("s")
        assert loaded.params.dense_reward_scale == pytest.approx(TRAINING_DENSE_REWARD_SCALE)
        assert_levels_equal(loaded.level, level_at(direct, level_id))


def test_export_writes_the_level_a_run_of_the_split_trains(sampled_dir, tmp_path):
    main(["export", str(SPLIT_CONFIG), str(EXPORTED_ID), "--scale", "tiny", "--out", str(tmp_path), "--no-progress"])
    job = resolve(load_config(SPLIT_CONFIG, scale="tiny"))
    batch_start = EXPORTED_ID - EXPORTED_ID % TINY_LEVELS_PER_BATCH
    trained = sample_batch(job, np.arange(batch_start, batch_start + TINY_LEVELS_PER_BATCH))
    exported = tmp_path / f"level-{EXPORTED_ID:07d}.json"
    assert_levels_equal(load_level(exported).level, level_at(trained, EXPORTED_ID - batch_start))

    # `sample` with the split's size and seed writes the same file.
    sample = ["sample", "--size", "s", "--seed", str(job.split.seed), "--start", str(EXPORTED_ID), "--num", "1"]
    main([*sample, "--out", str(tmp_path / "sampled"), "--no-progress"])
    assert (tmp_path / "sampled" / exported.name).read_text() == exported.read_text()


def test_export_refuses_an_id_outside_the_split(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(SPLIT_CONFIG), "8", "--scale", "tiny", "--out", str(tmp_path)])
    assert exit_info.value.code == 2  # a usage / config error, as in every subcommand
    assert "level ids [8] are outside split 1M/s (split.num_levels = 8)" in capsys.readouterr().err


def test_export_takes_overrides_as_positional_key_value_like_run(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(SPLIT_CONFIG), "5", "split.num_levels=4", "--scale", "tiny", "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "level ids [5] are outside split 1M/s (split.num_levels = 4)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(SPLIT_CONFIG), "five", "--scale", "tiny", "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "error: 'five' is neither a level id nor a key=value override" in capsys.readouterr().err


def test_import_names_the_field_of_a_malformed_file(sampled_dir, tmp_path, capsys):
    raw = json.loads((sampled_dir / f"level-{SAMPLED_IDS[0]:07d}.json").read_text())
    raw["env_state"]["polygon"][4]["role"] = 7
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps(raw))
    with pytest.raises(SystemExit) as exit_info:
        main(["import", str(broken), "--out", str(tmp_path / "out.json")])
    assert exit_info.value.code == 2
    assert f"{broken}: env_state.polygon[4].role: must be in 0..3, got 7" in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists()


def test_import_normalises_and_reports_what_changed(sampled_dir, tmp_path, capsys):
    original = sampled_dir / f"level-{SAMPLED_IDS[0]:07d}.json"
    raw = json.loads(original.read_text())
    matrix = raw["env_state"]["collision_matrix"]
    matrix["4"]["5"] = not matrix["4"]["5"]  # the loader recomputes the matrix from the joints
    raw["env_state"]["polygon"][4]["comment"] = "not a field"
    edited = tmp_path / "edited.json"
    edited.write_text(json.dumps(raw))
    main(["import", str(edited), "--out", str(tmp_path / "normalised.json")])
    report = capsys.readouterr().out
    assert "env_state.collision_matrix[][]: 1 values changed" in report
    assert "env_state.polygon[].comment: 1 values dropped" in report
    assert (tmp_path / "normalised.json").read_text() == original.read_text()


def test_import_warns_about_a_task_without_a_green_shape(sampled_dir, tmp_path, capsys):
    raw = json.loads((sampled_dir / f"level-{SAMPLED_IDS[0]:07d}.json").read_text())
    for shape in raw["env_state"]["polygon"] + raw["env_state"]["circle"]:
        shape["role"] = 0 if shape["role"] == 1 else shape["role"]
    path = tmp_path / "no_green.json"
    path.write_text(json.dumps(raw))
    main(["import", str(path), "--out", str(tmp_path / "out.json")])
    assert "warning: role: no active green shape, so no episode can succeed" in capsys.readouterr().out


def test_preview_writes_a_png_of_the_start_and_a_gif_of_an_episode(sampled_dir, tmp_path):
    level = sampled_dir / f"level-{SAMPLED_IDS[0]:07d}.json"
    png, gif = tmp_path / "start.png", tmp_path / "episode.gif"
    main(["preview", str(level), "--out", str(png), "--resolution", str(PREVIEW_PIXELS)])
    with Image.open(png) as image:
        pixels = np.asarray(image.convert("RGB"))
    assert pixels.shape == (PREVIEW_PIXELS, PREVIEW_PIXELS, 3) and pixels.std() > 0
    sampled = ["--size", "s", "--seed", str(SEED), "--index", str(SAMPLED_IDS[0])]
    main(["preview", *sampled, "--out", str(gif), "--resolution", str(PREVIEW_PIXELS), "--steps", str(GIF_STEPS)])
    frames = iio.imread(gif, index=None)
    assert frames.shape[:3] == (GIF_STEPS + 1, PREVIEW_PIXELS, PREVIEW_PIXELS)  # the start and one frame per step


def test_preview_plays_the_episode_under_the_physics_scheme_named(tmp_path):
    frames = {}
    for physics in ("kforge", "kinetix"):
        gif = tmp_path / f"{physics}.gif"
        argv = ["s/h0_weak_thrust", "--out", str(gif), "--resolution", str(PREVIEW_PIXELS), "--steps", str(GIF_STEPS)]
        main(["preview", *argv, "--physics", physics])
        frames[physics] = iio.imread(gif, index=None)
    assert (frames["kforge"][0] == frames["kinetix"][0]).all()  # the start does not depend on the physics
    assert (frames["kforge"][1:] != frames["kinetix"][1:]).any()  # free fall in substeps or in Jax2D's one step


@pytest.mark.parametrize(
    ("subcommand", "phrase"),
    [
        ("sample", "key (seed, i)"),
        ("preview", ".gif"),
        ("import", "path of the offending field"),
        ("export", "sampled in the job's own level batches"),
    ],
)
def test_help_explains_each_subcommand(subcommand, phrase, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([subcommand, "--help"])
    assert exit_info.value.code == 0
    assert phrase in " ".join(capsys.readouterr().out.split())


def test_levels_list_names_every_bundled_level_by_size(capsys):
    main(["list"])
    lines = capsys.readouterr().out.splitlines()
    assert [line for line in lines if line.endswith(")")] == ["10 levels (s)", "24 levels (m)", "40 levels (l)"]
    names = [line for line in lines if not line.endswith(")")]
    assert len(names) == 74 and "l/h4_cartpole" in names and "s/h4_thrust_aim" in names
    main(["list", "--size", "m"])
    assert capsys.readouterr().out.splitlines()[-1] == "24 levels (m)"

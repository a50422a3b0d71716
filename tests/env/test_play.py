"""`kforge render` plays a level file and writes a GIF with one frame per state."""

import imageio.v3 as iio

from kforge.pipeline.cli import main


def test_render_command_writes_one_frame_per_state(levels_dir, tmp_path, capsys):
    out = tmp_path / "h0.gif"
    main(["render", str(levels_dir / "s" / "h0_weak_thrust.json"), "--steps", "40", "--out", str(out)])
    frames = iio.imread(out, index=None)
    assert frames.shape == (41, 500, 500, 3)
    printed = capsys.readouterr().out
    # The level's design: without thrust the green ball falls onto the red floor.
    assert str(out) in printed and "failure at step" in printed


def test_render_plays_under_the_physics_scheme_named(levels_dir, tmp_path, capsys):
    level = str(levels_dir / "s" / "h0_weak_thrust.json")
    kforge, kinetix, default = tmp_path / "kforge.gif", tmp_path / "kinetix.gif", tmp_path / "default.gif"
    main(["render", level, "--steps", "40", "--out", str(kforge), "--physics", "kforge"])
    main(["render", level, "--steps", "40", "--out", str(kinetix), "--physics", "kinetix"])
    main(["render", level, "--steps", "40", "--out", str(default)])
    a, b = iio.imread(kforge, index=None), iio.imread(kinetix, index=None)
    assert (iio.imread(default, index=None) == b).all()  # Kinetix's play unless --physics names another
    assert (a[0] == b[0]).all()  # the level's start does not depend on the physics
    assert (a[1] != b[1]).any()  # one env step of free fall: four substeps against one step of Jax2D's scheme
    assert "failure at step" in capsys.readouterr().out.split("\n")[-2]  # the ball still lands on the red floor

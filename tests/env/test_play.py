"""`kforge render` plays a level file and writes a GIF with one frame per state."""

import imageio.v3 as iio

from pipeline.cli import main


def test_render_command_writes_one_frame_per_state(levels_dir, tmp_path, capsys):
    out = tmp_path / "h0.gif"
    main(["render", str(levels_dir / "s" / "h0_weak_thrust.json"), "--steps", "40", "--out", str(out)])
    frames = iio.imread(out, index=None)
    assert frames.shape == (41, 500, 500, 3)
    printed = capsys.readouterr().out
    # The level's design: without thrust the green ball falls onto the red floor.
    assert str(out) in printed and "failure at step" in printed

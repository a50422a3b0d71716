"""Run-wide test settings: wandb is disabled and writes nowhere but a temporary directory, so no test needs the
network or a wandb login (a test that checks tracking turns it back on with its own `WANDB_MODE`)."""

import pytest

WANDB_DIR_VARIABLES = ("WANDB_DIR", "WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR")
"""wandb's environment variables for where it writes runs, settings, caches and artifacts."""


@pytest.fixture(autouse=True, scope="session")
def wandb_disabled(tmp_path_factory):
    """WANDB_MODE=disabled (it overrides `tracking.wandb`, see pipeline/generation/tracking.py) and wandb's folders
    in tmp."""
    directory = tmp_path_factory.mktemp("wandb")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("WANDB_MODE", "disabled")
        for name in WANDB_DIR_VARIABLES:
            patch.setenv(name, str(directory / name.lower()))
        yield

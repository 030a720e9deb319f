import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def short_episodes(tmp_path):
    """A YAML file of EnvConfig overrides with 40-step episodes (for quick training runs)."""
    path = tmp_path / "env.yml"
    path.write_text("max_cycles: 40\n")
    return str(path)

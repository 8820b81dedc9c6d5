import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")

import pytest  # noqa: E402

# Small networks for tests that check plumbing rather than learning; the learning test uses thesis sizes.
SMALL = {"hidden_sizes": [64, 64], "mc_hidden_sizes": [64, 64], "buffer_size": 20_000, "batch_size": 64,
         "eval_episodes": 2, "learning_starts": 100}


@pytest.fixture
def small():
    return dict(SMALL)

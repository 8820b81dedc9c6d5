import os
import signal

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")

# The fault tests play a user's Ctrl-C. A suite started as a background job (`cmd &` in a script) inherits SIGINT
# ignored and would pass that on to the runs it starts, which then rightly keep ignoring it (mcrl.run.stop).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

import pytest  # noqa: E402

# Small networks for tests that check plumbing rather than learning; the learning test uses thesis sizes.
SMALL = {"hidden_sizes": [64, 64], "intrinsic_hidden_sizes": [64, 64], "buffer_size": 20_000, "batch_size": 64,
         "eval_episodes": 2, "learning_starts": 100}


@pytest.fixture
def small():
    return dict(SMALL)

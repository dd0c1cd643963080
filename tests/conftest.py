import os

import numpy as np
import pytest
import torch

# Keep the two CPU cores of CI from being oversubscribed by intra-op threads in tests.
torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(0)

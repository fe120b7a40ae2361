import numpy as np
import pytest

from harvest_qp import Configuration


@pytest.fixture
def configuration() -> Configuration:
    return Configuration.dual_ur5e()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)

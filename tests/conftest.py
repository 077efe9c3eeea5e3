import os

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
# No helper process for the perturbation rounds, except in the tests that ask for one
# (test_helper_process.py): it runs attempts with jtet's code as imported in a new
# process, so a test that monkeypatches an attempt's code would see a mix.
os.environ["JTET_HELPER"] = "0"


@pytest.fixture
def rng():
    return np.random.default_rng(12345)

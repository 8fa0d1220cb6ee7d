import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def robot():
    from campaign.model.robot import RobotModel

    return RobotModel.load()


@pytest.fixture(scope="session")
def base(robot):
    from campaign.model.base_params import base_parameters

    return base_parameters(robot)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)

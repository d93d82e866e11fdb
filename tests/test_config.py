"""Config overrides as the benchmarks' --set flags give them."""

import pytest

from neld_jax.config import apply_overrides, base_config
from neld_jax.errors import ConfigError


def test_overrides_parse_literals_and_bare_strings():
    c = apply_overrides(base_config(), ["train.steps=20", "train.init_poses=baseline",
                                        "baseline.icp_distances_m=(0.5, 0.1)", "sampling.z_low_m=0.25"])
    assert c.train.steps == 20 and c.train.init_poses == "baseline"
    assert tuple(c.baseline.icp_distances_m) == (0.5, 0.1) and c.sampling.z_low_m == 0.25


@pytest.mark.parametrize("item, message", [("train.stepz=3", "no field train.stepz"),
                                           ("nosuch.steps=3", "no field nosuch.steps"),
                                           ("train.steps", "expected KEY=VALUE")])
def test_bad_overrides_name_the_field(item, message):
    with pytest.raises(ConfigError, match=message):
        apply_overrides(base_config(), [item])

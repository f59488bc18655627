"""benchmarks/screen_physics.py: the variant texts it reads."""

from __future__ import annotations

import pytest

from pigp_torch.optimizers.physics_bo import BROADER_SHAPE, relaxed_stages
from tests.benchmark.conftest import load_script


@pytest.fixture(scope="module")
def screen():
    return load_script("screen_physics")


def test_variant_texts(screen):
    """Plain names, key=value lists (numbers, booleans, words, relax.ARG) and JSON objects."""
    assert screen.parse_variant("default") == ("default", {})
    name, opts = screen.parse_variant("v=f_inf_std=0.05,evidence_from=6,prior_check=False")
    assert (name, opts) == ("v", {"f_inf_std": 0.05, "evidence_from": 6, "prior_check": False})
    assert screen.parse_variant("s=shape_prior=model") == ("s", {"shape_prior": "model"})
    _, opts = screen.parse_variant("r=relax.f_inf_std=0.3")
    assert opts == {"relax": [BROADER_SHAPE, *relaxed_stages(f_inf_std=0.3)]}
    text = 'j:{"schedule": "i@8/uui", "relax": [{"shape_factor": 3.0}]}'
    assert screen.parse_variant(text) == (
        "j",
        {"schedule": "i@8/uui", "relax": [{"shape_factor": 3.0}]},
    )


def test_oracle_variants(screen):
    """A variant named oracle... modifies the oracle reference, any other pigp-physics."""
    assert screen.base_spec("oracle").name == "pigp-physics-oracle"
    assert screen.base_spec("oracle-beta6").name == "pigp-physics-oracle"
    assert screen.base_spec("default").name == "pigp-physics"


def test_machines_1_to_24_only_when_reported(screen):
    """The benchmark's machines are refused unless --reported says they are reported."""
    with pytest.raises(SystemExit, match="--reported to report"):
        screen.main(["--seeds", "1-2", "default"])

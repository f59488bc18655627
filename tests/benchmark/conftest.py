"""A tiny benchmark run shared by the protocol and figure tests (cheap settings, 2 machines)."""

import importlib.util
import sys
from pathlib import Path

import pytest

from pigp_torch.bench import METHODS, model_prior, run_benchmark

SEEDS = (1, 2)
MODEL_SEED = 0
BUDGETS = {"gp": 6, "direct": 8}
CHEAP_BO = {"num_restarts": 2, "raw_samples": 32}
OPTIMUM_STARTS = 2


def tiny_methods():
    """Cheap variants of pigp, pigp-zero-mean, ml2 and the two direct methods."""
    return [
        METHODS["pigp"].with_options(**CHEAP_BO),
        METHODS["pigp-zero-mean"].with_options(**CHEAP_BO),
        METHODS["ml2"].with_options(**CHEAP_BO, refit_every=3),
        METHODS["nelder-mead"],
        METHODS["rcds"],
    ]


@pytest.fixture(scope="session")
def tiny_prior():
    return model_prior(MODEL_SEED, n_starts=4)


@pytest.fixture(scope="session")
def tiny_table(tiny_prior):
    return run_benchmark(
        tiny_methods(),
        SEEDS,
        model_seed=MODEL_SEED,
        budgets=BUDGETS,
        archive_size=40,
        progress=False,
        prior=tiny_prior,
        optimum_starts=OPTIMUM_STARTS,
    )


def load_script(name: str):
    """Import ``benchmarks/<name>.py`` (a script, not a package module) as a module; its folder
    goes on ``sys.path`` as when the script runs, so that it can import its siblings."""
    folder = Path(__file__).resolve().parents[2] / "benchmarks"
    if str(folder) not in sys.path:
        sys.path.append(str(folder))
    path = folder / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module

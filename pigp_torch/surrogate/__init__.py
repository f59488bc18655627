r"""Neural-network surrogate :math:`\hat f(x)` of the simulated loss rate.

A smooth MLP (twice differentiable, so the prior can take its Hessian), its training with
validation split and early stopping, and pickle-free save/load.
"""

import importlib

#: public name -> the module that defines it (imported on first use: the ``pigp`` parser reads
#: :mod:`pigp_torch.surrogate.defaults` without loading torch)
_EXPORTS = {
    "SurrogateEnsemble": "ensemble",
    "train_ensemble": "ensemble",
    "load_surrogate": "io",
    "save_surrogate": "io",
    "SurrogateMLP": "mlp",
    "train_surrogate": "train",
}


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "SurrogateEnsemble",
    "SurrogateMLP",
    "load_surrogate",
    "save_surrogate",
    "train_ensemble",
    "train_surrogate",
]

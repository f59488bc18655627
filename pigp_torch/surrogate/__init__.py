r"""Neural-network surrogate :math:`\hat f(x)` of the simulated loss rate.

A smooth MLP (twice differentiable, so the prior can take its Hessian), its training with
validation split and early stopping, and pickle-free save/load.
"""

from pigp_torch._utils.lazy import lazy_exports

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

__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = [
    "SurrogateEnsemble",
    "SurrogateMLP",
    "load_surrogate",
    "save_surrogate",
    "train_ensemble",
    "train_surrogate",
]

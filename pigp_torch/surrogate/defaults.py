r"""Defaults and choices of the surrogate's training, as plain data (imports nothing heavy).

The single source of :func:`~pigp_torch.surrogate.train_surrogate`'s tuned defaults and of the
choices the command line offers; the ``pigp`` parser reads them without loading torch. The
defaults (target ``inv_sq_excess``, 3 x 64 SiLU, batch 1024, lr 1e-2, 200 epochs, float32, one
thread) were tuned for the accuracy of the Hessian of :math:`\log(\hat f - f_\infty)` at the
optimum on 100k samples in 13 knobs.
"""

#: smooth activations (twice differentiable: the prior takes the network's Hessian)
ACTIVATION_NAMES = ("gelu", "silu", "softplus", "tanh")
#: what the network fits: (f - f_inf)^-2, log(f - f_inf), (f - f_inf)^-1 or f itself
TARGETS = ("inv_sq_excess", "log_excess", "inv_excess", "raw")
DEFAULT_TARGET = "inv_sq_excess"
#: defaults of train_surrogate's tuned arguments
TRAIN_DEFAULTS = {
    "widths": (64, 64, 64),
    "activation": "silu",
    "target": DEFAULT_TARGET,
    "val_fraction": 0.1,
    "batch_size": 1024,
    "lr": 1e-2,
    "max_epochs": 200,
    "patience": 40,
    "num_threads": 1,
}

"""Small helpers shared by several layers. Nothing here imports other layers, and importing the
package loads nothing heavy: the tensor helpers (:mod:`~pigp_torch._utils.tensors`: ``DTYPE``,
``default_dtype``, ``as_knob_tensor``, ``check_bounds``, ``max_step_tensor``, ``utc_now``) are
imported, with torch, on first use; :mod:`~pigp_torch._utils.lazy` does that."""

from pigp_torch._utils.lazy import lazy_exports

#: public name -> the module that defines it
_EXPORTS = dict.fromkeys(
    ("DTYPE", "as_knob_tensor", "check_bounds", "default_dtype", "max_step_tensor", "utc_now"),
    "tensors",
)
__getattr__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

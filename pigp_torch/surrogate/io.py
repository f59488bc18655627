r"""Save and load a :class:`SurrogateMLP` as one ``.pt`` file without pickled objects.

The file is a plain dict of tensors and strings, read back with ``torch.load(weights_only=True)``
(no arbitrary code runs on loading):

* ``format``: ``"pigp-surrogate"``; ``format_version``: ``1``,
* ``config``: JSON string of the architecture (``dim``, ``widths``, ``activation``, ``target``),
  or for a :class:`SurrogateEnsemble` ``{"n_members": K, "member": <that>}``,
* ``state_dict``: weights and buffers (bounds, ``f_inf``, target normalization),
* ``metadata``: JSON string of user metadata (knob names, data provenance, metrics, ...).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from pigp_torch.surrogate.ensemble import SurrogateEnsemble
from pigp_torch.surrogate.mlp import SurrogateMLP

FORMAT = "pigp-surrogate"
FORMAT_VERSION = 1
_KEYS = ("format", "format_version", "config", "state_dict", "metadata")


def save_surrogate(
    model: SurrogateMLP | SurrogateEnsemble, path, metadata: dict | None = None
) -> Path:
    """Write ``model`` and JSON-serializable ``metadata`` to ``path`` (parents created).

    Args:
        model: the surrogate to save (any device/dtype; stored as float64 on CPU).
        path: destination file, conventionally ``*.pt``.
        metadata: JSON-serializable dict (knob names, bounds, data provenance, metrics).

    Returns:
        The path written.

    Raises:
        ValueError: ``model`` is not a :class:`SurrogateMLP` or ``metadata`` is not JSON-able.
    """
    if not isinstance(model, SurrogateMLP | SurrogateEnsemble):
        raise ValueError(
            f"model must be a SurrogateMLP or SurrogateEnsemble, got {type(model).__name__}"
        )
    metadata = {} if metadata is None else metadata
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata must be a dict, got {type(metadata).__name__}")
    try:
        meta_json = json.dumps(metadata)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata must be JSON-serializable: {exc}") from exc
    state = {
        k: v.detach().to(device="cpu", dtype=torch.float64).clone()
        for k, v in model.state_dict().items()
    }
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": json.dumps(model.config),
        "state_dict": state,
        "metadata": meta_json,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


def load_surrogate(path, *, map_location: str | torch.device = "cpu") -> tuple[SurrogateMLP, dict]:
    """Read a surrogate written by :func:`save_surrogate`.

    Only tensors, strings and numbers are unpickled (``torch.load(weights_only=True)``); a file
    holding any other Python object is refused.

    Args:
        path: file written by :func:`save_surrogate`.
        map_location: device for the tensors (default CPU).

    Returns:
        ``(model, metadata)``: the model in float64 eval mode, and the metadata dict.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a surrogate file (missing keys, wrong format, non-loadable objects,
            state dict not matching the architecture).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"surrogate file not found: {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # unpickling error for anything but plain data
        raise ValueError(
            f"{path} could not be loaded safely (weights_only=True refuses arbitrary objects): "
            f"{exc}"
        ) from exc
    if not isinstance(payload, dict):
        raise ValueError(f"{path} is not a pigp surrogate file (top level is not a dict)")
    missing = [k for k in _KEYS if k not in payload]
    if missing:
        raise ValueError(f"{path} is not a pigp surrogate file: missing keys {missing}")
    if payload["format"] != FORMAT:
        raise ValueError(f"{path}: unknown format {payload['format']!r} (expected {FORMAT!r})")
    if int(payload["format_version"]) > FORMAT_VERSION:
        raise ValueError(
            f"{path}: format version {payload['format_version']} is newer than supported "
            f"({FORMAT_VERSION})"
        )
    try:
        config = json.loads(payload["config"])
        metadata = json.loads(payload["metadata"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: config/metadata are not valid JSON strings: {exc}") from exc
    state = payload["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{path}: state_dict is not a dict")
    if "n_members" in config:
        n = int(config["n_members"])
        members = [_member(path, config["member"], state, prefix=f"members.{k}.") for k in range(n)]
        model = SurrogateEnsemble(members).double()
    else:
        model = _member(path, config, state, prefix="")
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{path}: weights do not match the architecture: {exc}") from exc
    return model.eval(), metadata


def _member(path, config: dict, state: dict, prefix: str) -> SurrogateMLP:
    """A fresh :class:`SurrogateMLP` with the architecture of ``config`` (weights come later)."""
    missing_cfg = [k for k in ("dim", "widths", "activation", "target") if k not in config]
    if missing_cfg:
        raise ValueError(f"{path}: architecture config lacks {missing_cfg}")
    if f"{prefix}bounds" not in state or f"{prefix}f_inf" not in state:
        raise ValueError(f"{path}: state_dict lacks the bounds/f_inf buffers")
    bounds = state[f"{prefix}bounds"].to(torch.float64)
    if tuple(bounds.shape) != (2, int(config["dim"])):
        raise ValueError(f"{path}: bounds shape {tuple(bounds.shape)} does not match dim")
    return SurrogateMLP(
        bounds,
        float(state[f"{prefix}f_inf"]),
        widths=config["widths"],
        activation=config["activation"],
        target=config["target"],
    ).double()

r"""The cache of ``pigp demo``: what does not change between runs, as plain JSON files.

Two entries, each a JSON file named by the sha256 of its key:

* ``prior-<key>.json``: the physics prior of the surrogate (stages 1-3: simulated data, the
  surrogate, its optimum and Hessian) and the surrogate's training reports, keyed by the model
  ring's error seed, the sample count, the surrogate's members and target;
* ``ensemble-<key>.json``: the error ensemble's ``center_cov`` and ``peak_shape`` (the optima of
  N more simulated rings), keyed by the model ring's seed, the knobs and N.

Every key also holds :func:`code_digest` (the sources and data files that produce the numbers,
and the torch and numpy versions), so a changed simulator or trainer never reuses an old entry.
Floats are stored with ``repr`` precision: a cached prior equals the computed one bit for bit.
Nothing is unpickled. The default folder is ``$PIGP_CACHE_DIR``, else
``$XDG_CACHE_HOME/pigp``, else ``~/.cache/pigp``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path

import torch

from pigp_torch._utils import DTYPE

#: Parts of the package whose code or data determine the cached numbers.
_SOURCES = ("simulation", "surrogate", "prior", "data", "_utils")


def default_cache_dir() -> Path:
    """``$PIGP_CACHE_DIR``, else ``$XDG_CACHE_HOME/pigp``, else ``~/.cache/pigp``."""
    if os.environ.get("PIGP_CACHE_DIR"):
        return Path(os.environ["PIGP_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "pigp"


@lru_cache(maxsize=1)
def code_digest() -> str:
    """sha256 over the package's simulation, surrogate and prior sources, its lattice data, and
    the torch and numpy versions."""
    import numpy

    root = Path(__file__).parents[1]  # the package folder
    h = hashlib.sha256(f"torch {torch.__version__} numpy {numpy.__version__}".encode())
    for part in _SOURCES:
        path = root / part
        files = sorted(path.rglob("*")) if path.is_dir() else [path]
        for f in files:
            if f.is_file() and f.suffix in (".py", ".json"):
                h.update(str(f.relative_to(root)).encode())
                h.update(f.read_bytes())
    return h.hexdigest()


class DemoCache:
    r"""A folder of cache entries (created on the first write).

    Args:
        folder: where the entries live.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def path(self, kind: str, key: dict) -> Path:
        """The file of entry ``kind`` for ``key`` (a JSON-serializable dict)."""
        text = json.dumps({**key, "code": code_digest()}, sort_keys=True)
        return self.folder / f"{kind}-{hashlib.sha256(text.encode()).hexdigest()[:24]}.json"

    def _read(self, kind: str, key: dict) -> dict | None:
        path = self.path(kind, key)
        try:
            return json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):  # missing, unreadable or cut short: recompute
            return None

    def _write(self, kind: str, key: dict, data: dict) -> Path:
        path = self.path(kind, key)
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(data, allow_nan=False), encoding="utf-8")
        tmp.replace(path)  # atomic: a reader never sees half a file
        return path

    # -- the surrogate's prior -----------------------------------------------------------------
    def load_prior(self, key: dict):
        """``(prior, reports)`` of a cached surrogate prior, or ``None``."""
        from pigp_torch.prior import PhysicsPrior

        data = self._read("prior", key)
        if data is None:
            return None
        try:
            return PhysicsPrior.from_dict(data["prior"]), list(data["reports"])
        except (KeyError, TypeError, ValueError):
            return None

    def save_prior(self, key: dict, prior, reports) -> Path:
        """Store a surrogate prior and the training reports (JSON-safe values only)."""
        safe = [{k: v for k, v in r.items() if isinstance(v, (int, float, str))} for r in reports]
        return self._write("prior", key, {"prior": prior.to_dict(), "reports": safe})

    # -- the error ensemble --------------------------------------------------------------------
    def load_ensemble(self, key: dict) -> dict | None:
        """``{"center_cov", "peak_shape", "seeds"}`` of a cached ensemble, or ``None``."""
        data = self._read("ensemble", key)
        if data is None:
            return None
        try:
            return {
                "center_cov": torch.tensor(data["center_cov"], dtype=DTYPE),
                "peak_shape": torch.tensor(data["peak_shape"], dtype=DTYPE),
                "seeds": list(data["seeds"]),
            }
        except (KeyError, TypeError, ValueError):
            return None

    def save_ensemble(self, key: dict, prior) -> Path:
        """Store the ensemble fields of ``prior`` (computed with a centre ensemble)."""
        return self._write(
            "ensemble",
            key,
            {
                "center_cov": prior.center_cov.tolist(),
                "peak_shape": prior.peak_shape.tolist(),
                "seeds": prior.provenance.get("center_ensemble_seeds"),
            },
        )


def ensemble_key(model_seed: int, size: int, knob_names) -> dict:
    """The cache key of an error ensemble of ``size`` rings of the model ring ``model_seed``."""
    return {"model_seed": int(model_seed), "size": int(size), "knobs": list(knob_names)}


def apply_cached_ensemble(prior, hit: dict):
    """``prior`` with the fields of a cached ensemble (:meth:`DemoCache.load_ensemble`)."""
    provenance = {**prior.provenance, "center_ensemble_seeds": hit["seeds"]}
    fields = {"center_cov": hit["center_cov"], "peak_shape": hit["peak_shape"]}
    return dataclasses.replace(prior, **fields, provenance=provenance)


def with_cached_ensemble(prior, size: int, model_seed: int, cache: DemoCache | None, compute):
    r"""``prior`` with the error ensemble's fields: from ``cache`` when it holds them, else
    ``compute(prior)`` (which returns the prior with them), then stored.

    Returns:
        ``(prior, source)``, ``source`` the cache file read or ``None`` when computed.
    """
    key = ensemble_key(model_seed, size, prior.knob_names)
    hit = None if cache is None else cache.load_ensemble(key)
    if hit is not None:
        return apply_cached_ensemble(prior, hit), cache.path("ensemble", key)
    out = compute(prior)
    if cache is not None:
        cache.save_ensemble(key, out)
    return out, None

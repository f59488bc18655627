r"""Lattices and knobs: a ring from a lattice file or an element table (pyAT), knob names resolved
to elements, and thin skew-quadrupole knobs inserted into the ring."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import at
import numpy as np

from pigp_torch.machines.ring import deck as _deck


def load_ring(source, *, energy: float | None = None) -> at.Lattice:
    """A radiating pyAT ring from an element table or any lattice file pyAT loads.

    Args:
        source: an ``at.Lattice``; a key of :data:`~pigp_torch.machines.ring.deck.DECKS`; a JSON
            element table (our format); or any file ``at.load_lattice`` reads (.mat, .m, .lte,
            ...).
        energy: beam energy (eV) for element tables (default 3 GeV) and for files that carry none.

    Returns:
        A fresh 6-D ring (:func:`~pigp_torch.machines.ring.deck.make_radiating` applied when the
        source is not 6-D).

    Raises:
        FileNotFoundError: no such file.
        ValueError: the lattice has no RF cavity (no equilibrium emittance without one).
    """
    if isinstance(source, at.Lattice):
        ring = source.deepcopy()
    elif str(source) in _deck.DECKS or _is_element_table(source):
        e = _deck.SPEAR3_ENERGY if energy is None else float(energy)
        return _deck.ring_from_table(_deck.load_table(source), energy=e)
    else:
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"no lattice file at {path}")
        kw = {} if energy is None else {"energy": float(energy)}
        ring = at.load_lattice(str(path), **kw)
    if not any(isinstance(e, at.RFCavity) for e in ring):
        raise ValueError("the lattice has no RF cavity: add one to compute equilibrium emittances")
    if not ring.is_6d:
        _deck.make_radiating(ring)
    return ring


def _is_element_table(source) -> bool:
    path = Path(str(source))
    if path.suffix.lower() != ".json" or not path.is_file():
        return False
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    return isinstance(data, dict) and isinstance(data.get("elements"), list)


_INDEXED = re.compile(r"^(?P<fam>.+)\[(?P<n>\d+)\]$")


def resolve_knob(ring: at.Lattice, name: str) -> int:
    """Element index of the knob ``name`` (``FAM``, ``FAM[n]`` or ``#i``; module docstring).

    Raises:
        ValueError: no such element, or a family name that is not unique.
    """
    name = str(name)
    if name.startswith("#"):
        i = int(name[1:])
        if not 0 <= i < len(ring):
            raise ValueError(f"knob {name!r}: the ring has {len(ring)} elements")
        return i
    m = _INDEXED.match(name)
    fam, nth = (m["fam"], int(m["n"])) if m else (name, None)
    idx = [i for i, e in enumerate(ring) if e.FamName == fam]
    if not idx:
        raise ValueError(f"knob {name!r}: no element of family {fam!r} in the ring")
    if nth is None:
        if len(idx) > 1:
            raise ValueError(
                f"knob {name!r}: {len(idx)} elements of that family; name one as {fam}[n]"
            )
        return idx[0]
    if nth >= len(idx):
        raise ValueError(f"knob {name!r}: family {fam!r} has only {len(idx)} elements")
    return idx[nth]


def insert_knobs(ring: at.Lattice, names) -> tuple[at.Lattice, list[int]]:
    """A copy of ``ring`` with a thin winding at every knob, and the windings' element indices.

    A thin multipole is used as it is; a thick multipole (sextupole, quadrupole, ...) is split in
    two halves with ``at.ThinMultipole(name)`` between them (the halves keep every attribute:
    errors applied later treat them as one magnet).

    Raises:
        ValueError: an unknown or repeated knob, or a knob on an element that is neither thin
            nor a multipole.
    """
    names = [str(n) for n in names]
    if not names:
        raise ValueError("at least one knob is needed")
    if len(set(names)) != len(names):
        raise ValueError("knob names must be unique")
    targets = [resolve_knob(ring, n) for n in names]
    if len(set(targets)) != len(targets):
        raise ValueError("two knob names resolve to the same element")
    by_index = dict(zip(targets, names, strict=True))
    elems = []
    where = {}
    for i, e in enumerate(ring):
        if i not in by_index:
            elems.append(e.deepcopy())
            continue
        name = by_index[i]
        thin_already = isinstance(e, at.ThinMultipole) and not getattr(e, "Length", 0.0) > 0
        if thin_already:
            thin = e.deepcopy()
            elems.append(thin)
        elif isinstance(e, at.Multipole) and e.Length > 0:
            half = e.deepcopy()
            half.Length = e.Length / 2
            twin = half.deepcopy()
            thin = at.ThinMultipole(name, [0.0, 0.0], [0.0, 0.0])
            elems += [half, thin, twin]
        else:
            raise ValueError(
                f"knob {name!r}: element {type(e).__name__} {e.FamName!r} cannot carry a skew "
                "winding (use a thin multipole, a sextupole or a quadrupole)"
            )
        where[name] = len(elems) - (1 if thin_already else 2)
    for i in where.values():
        pa = np.zeros(max(2, len(elems[i].PolynomA)))
        pb = np.zeros(max(2, len(elems[i].PolynomB)))
        pa[: len(elems[i].PolynomA)] = elems[i].PolynomA
        pb[: len(elems[i].PolynomB)] = elems[i].PolynomB
        elems[i].PolynomA, elems[i].PolynomB = pa, pb
        elems[i].MaxOrder = max(int(getattr(elems[i], "MaxOrder", 1)), 1)
    out = at.Lattice(elems, **ring.attrs)
    return out, [where[n] for n in names]


def fingerprint(ring: at.Lattice) -> str:
    """A content hash of a ring (cache key of the machines built on it)."""
    h = hashlib.sha1()
    for e in ring:
        h.update(repr(sorted((k, repr(v)) for k, v in e.items())).encode())
    return h.hexdigest()

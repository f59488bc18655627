r"""The ARES Experimental Area (DESY linac) in Cheetah: five magnets, a beam on a screen.

The segment AREASOLA1 … AREABSCR1 is built from the shipped ``machines/ares_ea/data/lattice.json``:
drifts, three thick quadrupoles (AREAMQZM1/2/3, each with a transverse misalignment), a vertical
and a horizontal corrector (AREAMCVM1, AREAMCHM1) and the screen AREABSCR1 (2448 × 2040 pixels
of 3.3198 × 2.4469 µm; its own misalignment shifts what it reads). The five knobs, in this order,
are

.. math:: x = (k_{1,Q1},\ k_{1,Q2},\ \theta_{CV},\ k_{1,Q3},\ \theta_{CH})
    \quad [1/\mathrm{m}^2,\ 1/\mathrm{m}^2,\ \mathrm{rad},\ 1/\mathrm{m}^2,\ \mathrm{rad}],

and the four observables are the beam's centroid and rms size on the screen, in the screen's
frame, :math:`o = (\mu_x, \sigma_x, \mu_y, \sigma_y)` in m.

What the operator does not know is the incoming beam (11 parameters, :data:`INCOMING_NAMES`: energy
in eV, centroid :math:`\mu_x, \mu_{x'}, \mu_y, \mu_{y'}` in m and rad, rms sizes and divergences
:math:`\sigma_x, \sigma_{x'}, \sigma_y, \sigma_{y'}`, bunch length :math:`\sigma_s` in m, relative
energy spread :math:`\sigma_p`) and the misalignments of the three quadrupoles and the screen
(8 numbers in m, :data:`MISALIGNMENT_NAMES`).

The beam is Cheetah's :class:`~cheetah.ParameterBeam` (first and second moments tracked through
the first-order transfer maps): exact for this segment, which has no dipoles and no nonlinear
elements, so the moments of any particle distribution propagate linearly; it costs one 7 × 7
matrix product per element for a whole batch of settings and is differentiable in every knob and
unknown. The incoming beam is uncorrelated (:math:`\langle x x' \rangle = 0`: a waist at the
segment's entrance), its centroid offset and angle given; the optics do not depend on the energy
(k1 is the geometric strength), only the longitudinal map does.

Batching: every argument may carry leading batch dimensions; they broadcast against each other
(e.g. ``N x 5`` knobs with one trial's ``11`` incoming parameters and ``8`` misalignments).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import torch

from pigp_torch._utils import DTYPE

#: The five knobs in the order of the knob vector.
KNOB_NAMES: tuple[str, ...] = ("AREAMQZM1", "AREAMQZM2", "AREAMCVM1", "AREAMQZM3", "AREAMCHM1")
#: Units of the knobs.
KNOB_UNITS: tuple[str, ...] = ("1/m^2", "1/m^2", "rad", "1/m^2", "rad")
#: The four observables on the screen (m).
OBSERVABLE_NAMES: tuple[str, ...] = ("mu_x", "sigma_x", "mu_y", "sigma_y")
#: The incoming beam's parameters in the order of an ``11`` vector (SI: eV, m, rad).
INCOMING_NAMES: tuple[str, ...] = (
    "energy",
    "mu_x",
    "mu_xp",
    "mu_y",
    "mu_yp",
    "sigma_x",
    "sigma_xp",
    "sigma_y",
    "sigma_yp",
    "sigma_s",
    "sigma_p",
)
#: The misalignments in the order of an ``8`` vector (m).
MISALIGNMENT_NAMES: tuple[str, ...] = (
    "q1_x",
    "q1_y",
    "q2_x",
    "q2_y",
    "q3_x",
    "q3_y",
    "screen_x",
    "screen_y",
)
#: The published BO's start setting (k1 in 1/m², angles in rad).
START_SETTING: tuple[float, ...] = (10.0, -10.0, 0.0, 10.0, 0.0)


def _data_dir():
    return resources.files("pigp_torch.machines.ares_ea") / "data"


def load_lattice(path: str | Path | None = None) -> dict:
    """The ARES-EA lattice table (``lattice.json``; default: the copy shipped in the package)."""
    if path is None:
        return json.loads((_data_dir() / "lattice.json").read_text())
    return json.loads(Path(path).read_text())


def default_trials_path():
    """The shipped trials 0–149 (``machines/ares_ea/data/trials_000-149.yaml``), as a readable
    resource."""
    return _data_dir() / "trials_000-149.yaml"


def knob_bounds(unidirectional: bool = False, lattice: dict | None = None) -> torch.Tensor:
    r"""``2 x 5`` knob bounds (float64): bidirectional (quadrupoles ±72 1/m², correctors
    ±6.1782 mrad) or with unidirectional quadrupoles (Q1 ≥ 0, Q2 ≤ 0, Q3 ≥ 0)."""
    lattice = load_lattice() if lattice is None else lattice
    key = "bounds_unidirectional_quads" if unidirectional else "bounds_bidirectional"
    return torch.tensor(lattice["knobs"][key], dtype=DTYPE)


def _cheetah():
    try:
        import cheetah
    except ImportError as err:  # pragma: no cover - the extra is part of dev
        raise ImportError(
            "the ARES model needs Cheetah: pip install 'pigp-torch[ares]' (cheetah-accelerator)"
        ) from err
    return cheetah


def screen_half_size(lattice: dict | None = None) -> torch.Tensor:
    """``2`` half width and half height of the screen's sensor (m): a beam centre is on the screen
    when :math:`|\\mu_x|` and :math:`|\\mu_y|` are strictly below them."""
    lattice = load_lattice() if lattice is None else lattice
    scr = next(e for e in lattice["elements"] if e["type"] == "Screen")
    res = torch.tensor(scr["resolution"], dtype=DTYPE)
    px = torch.tensor(scr["pixel_size_m"], dtype=DTYPE)
    return res * px / 2


class AresSegment:
    r"""The ARES-EA segment as a differentiable, batched function of knobs and unknowns.

    Args:
        lattice: the lattice table (default: the shipped ``lattice.json``).
        dtype: floating type of all tensors (default float64).

    Attributes:
        segment: the :class:`cheetah.Segment` (elements named as in the lattice).
        knob_names, bounds: the knobs and their bidirectional ``2 x 5`` bounds.
        screen_half_size: ``2`` half width / height of the screen (m).
    """

    def __init__(self, lattice: dict | None = None, dtype: torch.dtype = DTYPE) -> None:
        ch = _cheetah()
        self.lattice = load_lattice() if lattice is None else lattice
        self.dtype = dtype
        kw = {"dtype": dtype}
        elements = []
        for e in self.lattice["elements"]:
            name, kind = e["name"], e["type"]
            if kind == "Marker":
                el = ch.Marker(name=name, sanitize_name=True)
            elif kind == "Drift":
                el = ch.Drift(length=torch.tensor(e["length"], **kw), name=name, **kw)
            elif kind == "Quadrupole":
                el = ch.Quadrupole(length=torch.tensor(e["length"], **kw), name=name, **kw)
            elif kind == "VerticalCorrector":
                el = ch.VerticalCorrector(length=torch.tensor(e["length"], **kw), name=name, **kw)
            elif kind == "HorizontalCorrector":
                el = ch.HorizontalCorrector(length=torch.tensor(e["length"], **kw), name=name, **kw)
            elif kind == "Screen":
                el = ch.Screen(
                    resolution=tuple(int(r) for r in e["resolution"]),
                    pixel_size=torch.tensor(e["pixel_size_m"], **kw),
                    is_active=True,
                    name=name,
                    **kw,
                )
            else:
                raise ValueError(f"unknown element type {kind!r} in the ARES lattice")
            elements.append(el)
        self.segment = ch.Segment(elements, name="ARES_EA")
        self._el = {e.name: e for e in elements}
        self.knob_names = list(self.lattice["knobs"]["order"])
        if tuple(self.knob_names) != KNOB_NAMES:
            raise ValueError(f"lattice knobs {self.knob_names} are not {list(KNOB_NAMES)}")
        self.bounds = knob_bounds(False, self.lattice).to(dtype)
        self.screen_half_size = screen_half_size(self.lattice).to(dtype)

    @property
    def length(self) -> float:
        """Total length of the segment (m)."""
        return float(sum(float(e.get("length", 0.0)) for e in self.lattice["elements"]))

    def incoming_beam(self, incoming: torch.Tensor, energy: torch.Tensor | None = None):
        r"""A :class:`cheetah.ParameterBeam` from ``... x 11`` incoming parameters
        (:data:`INCOMING_NAMES`, SI units), uncorrelated, electrons; ``energy`` (eV), when given,
        replaces ``incoming[..., 0]``."""
        ch = _cheetah()
        p = torch.as_tensor(incoming, dtype=self.dtype)
        if p.shape[-1] != len(INCOMING_NAMES):
            raise ValueError(f"incoming beam needs {len(INCOMING_NAMES)} numbers, got {p.shape}")
        v = dict(zip(INCOMING_NAMES, p.unbind(-1), strict=True))
        return ch.ParameterBeam.from_parameters(
            mu_x=v["mu_x"],
            mu_px=v["mu_xp"],
            mu_y=v["mu_y"],
            mu_py=v["mu_yp"],
            sigma_x=v["sigma_x"],
            sigma_px=v["sigma_xp"],
            sigma_y=v["sigma_y"],
            sigma_py=v["sigma_yp"],
            sigma_tau=v["sigma_s"],
            sigma_p=v["sigma_p"],
            energy=v["energy"] if energy is None else torch.as_tensor(energy, dtype=self.dtype),
            dtype=self.dtype,
        )

    def observe(
        self,
        knobs: torch.Tensor,
        incoming: torch.Tensor,
        misalignments: torch.Tensor,
        energy: torch.Tensor | None = None,
    ) -> torch.Tensor:
        r"""The beam on the screen :math:`(\mu_x, \sigma_x, \mu_y, \sigma_y)` in m.

        Args:
            knobs: ``... x 5`` settings (k1 in 1/m², angles in rad), :data:`KNOB_NAMES` order.
            incoming: ``... x 11`` incoming beam (:data:`INCOMING_NAMES`).
            misalignments: ``... x 8`` misalignments in m (:data:`MISALIGNMENT_NAMES`).
            energy: the beam energy (eV), replacing ``incoming[..., 0]`` when given (a fixed
                energy keeps the transfer maps unbatched when only the other parameters vary,
                e.g. under forward-mode autograd).

        Returns:
            ``B x 4`` (``B`` the broadcast batch shape of the three arguments), differentiable in
            all three.
        """
        x = torch.as_tensor(knobs, dtype=self.dtype)
        m = torch.as_tensor(misalignments, dtype=self.dtype)
        if x.shape[-1] != 5 or m.shape[-1] != 8:
            raise ValueError(f"knobs need 5 and misalignments 8 numbers, got {x.shape}, {m.shape}")
        el = self._el
        el["AREAMQZM1"].k1 = x[..., 0]
        el["AREAMQZM2"].k1 = x[..., 1]
        el["AREAMCVM1"].angle = x[..., 2]
        el["AREAMQZM3"].k1 = x[..., 3]
        el["AREAMCHM1"].angle = x[..., 4]
        el["AREAMQZM1"].misalignment = m[..., 0:2]
        el["AREAMQZM2"].misalignment = m[..., 2:4]
        el["AREAMQZM3"].misalignment = m[..., 4:6]
        # The screen's own offset is subtracted from the read centroid here, as Cheetah's Screen
        # does for a ParameterBeam (the same subtraction, so the same numbers), because its
        # Screen broadcasts a batched offset against the 7-vector of moments instead of the
        # batch and fails for a batch of screen offsets.
        el["AREABSCR1"].misalignment = torch.zeros(2, dtype=self.dtype)
        # Cheetah caches each element's transfer map under the id() and version of its tensors;
        # the views assigned above are new objects whose ids Python may reuse from freed ones, and
        # forward-mode tangents do not enter the key. Dropping the caches makes every call
        # recompute its maps (a few 7 x 7 products) instead of possibly reusing stale ones.
        for module in self.segment.modules():
            module.__dict__.pop("_cache", None)
        self.segment.track(self.incoming_beam(incoming, energy))
        read = el["AREABSCR1"].get_read_beam()
        mu_x, mu_y = read.mu_x - m[..., 6], read.mu_y - m[..., 7]
        return torch.stack(torch.broadcast_tensors(mu_x, read.sigma_x, mu_y, read.sigma_y), -1)

    def on_screen(self, observables: torch.Tensor) -> torch.Tensor:
        r"""``...`` bool: the beam centre is on the screen (:math:`|\mu| <` half size)."""
        o = torch.as_tensor(observables, dtype=self.dtype)
        h = self.screen_half_size
        return (o[..., 0].abs() < h[0]) & (o[..., 2].abs() < h[1])


@dataclass(frozen=True)
class AresTrial:
    r"""One published ARES-EA trial.

    Attributes:
        index: the trial's key in the trials file.
        target: ``4`` target :math:`(\mu_x, \sigma_x, \mu_y, \sigma_y)` (m).
        incoming: ``11`` incoming beam (:data:`INCOMING_NAMES`, SI units).
        misalignments: ``8`` misalignments (m, :data:`MISALIGNMENT_NAMES`).
        initial: ``5`` knobs the published RL agent started from, or ``None``.
    """

    index: int
    target: torch.Tensor
    incoming: torch.Tensor
    misalignments: torch.Tensor
    initial: torch.Tensor | None = None


_INITIAL_KEYS = ("q1", "q2", "cv", "q3", "ch")


def _vector(entry: dict, names, what: str, index) -> torch.Tensor:
    missing = [n for n in names if n not in entry]
    if missing:
        raise ValueError(f"trial {index}: {what} lacks {missing}")
    return torch.tensor([float(entry[n]) for n in names], dtype=DTYPE)


def load_trials(path: str | Path | None = None) -> dict[int, AresTrial]:
    """Trials in the published format (a YAML mapping with integer keys; each with ``target``,
    ``incoming``, ``misalignments`` and optionally ``initial``), by key.

    Args:
        path: the trials file (default: the shipped trials 0–149).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a mapping with integer keys, or a trial lacks a field.
    """
    import yaml

    if path is None:
        text = default_trials_path().read_text()
    else:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"trials file not found: {path}")
        text = path.read_text()
    data = yaml.safe_load(text)
    if not isinstance(data, dict) or not data:
        raise ValueError("trials file must be a non-empty mapping trial number -> trial")
    trials = {}
    for key, entry in data.items():
        if isinstance(key, bool) or not isinstance(key, int):
            raise ValueError(f"trial keys must be integers, got {key!r}")
        if not isinstance(entry, dict):
            raise ValueError(f"trial {key}: expected a mapping")
        for field in ("target", "incoming", "misalignments"):
            if not isinstance(entry.get(field), dict):
                raise ValueError(f"trial {key}: no {field!r} mapping")
        init = entry.get("initial")
        trials[key] = AresTrial(
            index=key,
            target=_vector(entry["target"], OBSERVABLE_NAMES, "target", key),
            incoming=_vector(entry["incoming"], INCOMING_NAMES, "incoming", key),
            misalignments=_vector(entry["misalignments"], MISALIGNMENT_NAMES, "misalignments", key),
            initial=None if init is None else _vector(init, _INITIAL_KEYS, "initial", key),
        )
    return trials


_RANGE = re.compile(r"^\s*(\d+)\s*(?:-\s*(\d+)\s*)?$")


def parse_trial_ids(text: str) -> list[int]:
    """Trial numbers from ``"50-149"``, ``"0,3,7-9"`` (ranges inclusive), in the given order,
    without duplicates.

    Raises:
        ValueError: an empty or malformed part, or a range whose end is below its start.
    """
    ids: list[int] = []
    for part in str(text).split(","):
        m = _RANGE.match(part)
        if m is None:
            raise ValueError(f"bad trial ids {text!r}: expected numbers and ranges like 50-149")
        lo = int(m.group(1))
        hi = lo if m.group(2) is None else int(m.group(2))
        if hi < lo:
            raise ValueError(f"bad trial range {part.strip()!r}: end below start")
        ids.extend(i for i in range(lo, hi + 1) if i not in ids)
    return ids

r"""Command-line options that choose the simulated ring and its knobs: an adapter from options to
a :class:`~pigp_torch.machines.ring.spec.RingSpec` (the one description of a simulated ring; a run
file's ``machine`` section gives its own with
:meth:`~..section.SimMachineConfig.ring_spec`).

Used by ``pigp generate-data``, ``compare``, ``serve-sim`` and ``bench simulator``. Light: the
parser is built without heavy imports (``pigp --help`` answers at once).
"""

from __future__ import annotations

import argparse

OPTICS = ("user", "design", "low_emittance")


def add_ring_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add ``--optics --knobs --lattice --knob-calibration --knob-limit --knob-units`` to ``p``."""
    g = p.add_argument_group("simulated ring")
    g.add_argument(
        "--optics",
        default="user",
        choices=OPTICS,
        help="SPEAR3 deck: user (default, sp3v82, tunes 14.13/6.22), design (sp3v81f, "
        "14.19/5.23) or low_emittance (sp3v81f with dispersion in the straights)",
    )
    g.add_argument(
        "--knobs",
        default="paper13",
        help="SPEAR3: paper13 (default, 13 windings), powered14, all72 or comma-separated "
        "winding names (01G-QSS4,...); with --lattice: comma-separated element names of the "
        "lattice (FAM, FAM[n] = n-th element of family FAM from 0, or #index)",
    )
    g.add_argument(
        "--lattice",
        default=None,
        metavar="FILE",
        help="your own ring instead of SPEAR3: a JSON element table or any file pyAT loads "
        "(.mat, .m, .lte, ...); needs --knobs names and --knob-calibration",
    )
    g.add_argument(
        "--knob-calibration",
        default=None,
        metavar="K1SL_PER_UNIT",
        help="with --lattice: K1s·L (1/m) per control unit, one value or comma-separated per knob",
    )
    g.add_argument(
        "--knob-limit",
        type=float,
        default=30.0,
        help="symmetric knob bound in control units (default 30, the SPEAR3 windings' ±30 A)",
    )
    g.add_argument("--knob-units", default="A", help="name of the control unit (default A)")
    return p


def _names(text: str):
    return text if "," not in text else tuple(n.strip() for n in text.split(",") if n.strip())


def ring_spec_from_args(args):
    """The :class:`~pigp_torch.machines.ring.spec.RingSpec` of the options of
    :func:`add_ring_arguments`.

    Raises:
        ValueError: inconsistent options (e.g. ``--lattice`` without knob names or calibration).
    """
    from pigp_torch.machines.ring.spec import RingSpec

    knobs = _names(args.knobs)
    calibration = None
    if args.knob_calibration is not None:
        calibration = tuple(float(v) for v in str(args.knob_calibration).split(","))
    if args.lattice is not None:
        if isinstance(knobs, str) and knobs in ("paper13", "powered14", "all72"):
            raise ValueError("--lattice needs --knobs with element names of that lattice")
        if isinstance(knobs, str):
            knobs = (knobs,)
        return RingSpec(
            lattice=str(args.lattice),
            knobs=knobs,
            knob_calibration=calibration,
            knob_limit=args.knob_limit,
            knob_units=args.knob_units,
        )
    if calibration is not None:
        raise ValueError("--knob-calibration goes with --lattice (SPEAR3 has its own)")
    if isinstance(knobs, str) and knobs not in ("paper13", "powered14", "all72"):
        knobs = (knobs,)
    return RingSpec(optics=args.optics, knobs=knobs, knob_limit=args.knob_limit)


def add_machine_arguments(p: argparse.ArgumentParser, seed_help: str) -> None:
    """Add ``--seed`` (the ring's error seed, help ``seed_help``) and the ring options."""
    p.add_argument("--seed", type=int, default=1, help=seed_help)
    add_ring_arguments(p)


def simulator_from_args(args):
    """The simulated ring of :func:`add_machine_arguments`'s options (built, error seed
    ``args.seed``)."""
    return ring_spec_from_args(args).build(args.seed)

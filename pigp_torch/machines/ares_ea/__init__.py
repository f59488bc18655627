r"""The ARES-EA machine kind (DESY's linac segment AREASOLA1 … AREABSCR1): five magnets (three
quadrupoles' k1 in 1/m², two correctors' angles in rad) and one screen (the beam's
:math:`\mu_x, \sigma_x, \mu_y, \sigma_y` in m), as published with trials 0–149.

Everything ARES-specific is in this folder: the Cheetah simulation (:mod:`.simulation`), the
wrong-model cases (:mod:`.cases`), the simulated machine (:mod:`.machine`), the methods and the
machine model (:mod:`.methods`), the published BO (:mod:`.published`), the run-file section and its
checks (:mod:`.section`, :mod:`.run`), the model's prior (:mod:`.prior`), the benchmark
(:mod:`.benchmark`) and ``pigp bench ares`` (:mod:`.command`). :data:`KIND` is the plug-in that
:data:`pigp_torch.machines.KINDS` lists as ``"ares-ea"``; this module imports nothing heavy (the
registry imports it to find the kind).
"""

from __future__ import annotations

from typing import Any

from pigp_torch.machines.kind import MachineKind


class AresKind(MachineKind):
    r"""The ARES-EA kind: ``model(trial=3)`` is the segment's
    :class:`~pigp_torch.prior.machine_model.MachineModel` for that trial's target (19 unknowns:
    the incoming beam, the misalignments, the quadrupoles' gains), ``simulator(trial=3)`` the
    trial's Cheetah segment, ``benchmark(...)`` :func:`.benchmark.run_ares_benchmark`."""

    name = "ares-ea"
    run_file_kind = "ares-sim"
    default_method = "ares-physics"
    title = "ARES-EA linac segment (DESY): 5 magnets, 1 screen"

    def model(self, *, trial: int = 3, trials=None, family=None, seed: int = 101, **options):
        r"""The machine model for ``trial``'s target (key of the trials file ``trials``, default
        the shipped 0–149); ``options`` go to :func:`.methods.ares_machine_model`
        (``quad_gain_half_width``, ``segment``, ``lattice``). With ``family`` (and draw
        ``seed``), the segment has that family's static gaps (:class:`.drift.GapSegment`: quad
        rolls, corrector map; the time-dependent parts are the machine's, not the model's)."""
        from pigp_torch.machines.ares_ea.methods import ares_machine_model
        from pigp_torch.machines.ares_ea.simulation import load_trials

        trial_ = load_trials(trials)[int(trial)]
        if family is not None:  # the static gaps of a family's machine (rolls, correctors)
            from pigp_torch.machines.ares_ea.drift import GapSegment, draw_gaps

            options["segment"] = GapSegment(draw_gaps(trial_, family, seed))
        return ares_machine_model(trial_.target, **options)

    def simulator(self, *, trial: int = 3, trials=None, model_error: str = "none", **options):
        r"""The simulated machine of ``trial`` (:class:`.machine.AresMachine`, at the published
        start), changed by the wrong-model case ``model_error``; ``options`` go to the machine
        (``objective``, ``noise``, ``seed``, ...)."""
        from pigp_torch.machines.ares_ea.cases import case_machine_parts
        from pigp_torch.machines.ares_ea.machine import AresMachine
        from pigp_torch.machines.ares_ea.simulation import load_trials

        trial_, segment = load_trials(trials)[int(trial)], None
        if model_error != "none":
            trial_, segment = case_machine_parts(trial_, model_error)
        return AresMachine(trial_, segment=segment, **options)

    def section(self) -> type:
        from pigp_torch.machines.ares_ea.section import AresSimConfig

        return AresSimConfig

    def check_run(self, config, method) -> None:
        from pigp_torch.machines.ares_ea.run import check_ares

        check_ares(config)

    def simulated_machine(self, config):
        from pigp_torch.machines.ares_ea.run import build_ares_machine

        return build_ares_machine(config)

    def describe(self, config, machine) -> str:
        """The simulated linac: its trial, trials file, wrong-model case, screen noise (µm),
        noise seed and the objective its machine returns."""
        m = config.machine
        where = "the shipped trials" if m.trials is None else str(m.trials)
        return (
            f"simulated ARES-EA linac (trial {m.trial} of {where}, model error {m.model_error}, "
            f"screen noise {1e6 * m.noise:g} µm, noise seed {m.seed}; objective "
            f"{machine.objective})"
        )

    def true_objective(self, config, say):
        """The simulated linac's objective of the true beam (the machine's noise-free
        observables); no optimum search, and the report keeps its noise."""
        from pigp_torch._utils import DTYPE
        from pigp_torch.machines.kind import TrueObjective

        machine = self.simulated_machine(config)
        return TrueObjective(lambda X: machine.objective_of(machine.true_observables(X)).to(DTYPE))

    def register_bench(self, bench) -> None:
        """``pigp bench ares`` (:mod:`.command`)."""
        from pigp_torch.machines.ares_ea.command import register

        register(None, bench)

    def register_methods(self, register) -> None:
        from pigp_torch.machines.ares_ea.methods import register_ares_methods

        register_ares_methods(register)

    def benchmark(self, **options: Any):
        """:func:`.benchmark.run_ares_benchmark` (trials x methods, one row per step)."""
        from pigp_torch.machines.ares_ea.benchmark import run_ares_benchmark

        return run_ares_benchmark(**options)

    def drift_families(self) -> dict[str, frozenset[str]]:
        """:data:`.drift.ARES_FAMILIES`."""
        from pigp_torch.machines.ares_ea.drift import ARES_FAMILIES

        return dict(ARES_FAMILIES)

    def drift_machine(self, *, family: str, seed: int = 101, trial: int = 3, trials=None, **kw):
        r"""Trial ``trial``'s :class:`.drift.AresDriftMachine` of ``family`` with draw ``seed``
        (:func:`.drift.ares_drift_machine`; ``kw`` go to the machine: ``objective``, ``noise``)."""
        from pigp_torch.machines.ares_ea.drift import ares_drift_machine
        from pigp_torch.machines.ares_ea.simulation import load_trials

        return ares_drift_machine(load_trials(trials)[int(trial)], family, seed, **kw)


#: The plug-in of this kind.
KIND = AresKind()

r"""The contract every machine kind passes, shipped with the package (as GPyTorch ships its kernel
test case): a test class of a kind inherits :class:`MachineKindContract`, names the kind and
how to get its model, and pytest runs every check on it.

.. code-block:: python

    from pigp_torch.machines.contract import MachineKindContract

    class TestMyKind(MachineKindContract):
        kind_name = "my-kind"          # its key in pigp_torch.machines.KINDS
        model_options = {"seed": 0}    # KINDS[kind_name].model(**model_options)
        noise = 0.01                   # a reading's noise (goal units) for the prior chain

The checks (each a ``test_*`` method):

* the registration: ``KINDS[kind_name]`` is a :class:`~pigp_torch.machines.MachineKind` of that
  name whose default method is registered, whose run-file section (if it has one) is chosen by
  ``kind: run_file_kind``, and whose ``model()`` is a
  :class:`~pigp_torch.prior.machine_model.MachineModel`;
* knobs, observables and unknowns have names, units (non-empty text) and ``2 x d`` bounds with
  lower < upper; the unknowns' ranges have positive half widths;
* ``observe`` is batched: ``N x d`` settings give ``N x m`` observables, row ``n`` equal to the
  setting evaluated alone, and ``N x P`` unknowns (one row per setting) give the rows of each row's
  unknowns;
* ``observe`` is differentiable: the goal's gradient in the knobs and in the unknowns is finite and
  agrees with a central finite difference along a random direction (relative error below
  :attr:`MachineKindContract.gradient_rtol`);
* the paper's prior chain runs on the model
  (:func:`~pigp_torch.prior.machine_model.prior_from_machine_model`: optimum, autograd Hessian,
  :math:`\Sigma = -H/2`, :math:`f_\infty`): a prior with :math:`x_0` inside the bounds, a
  symmetric positive-definite precision, :math:`f(x_0) > f_\infty` and the model's knob names.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch

from pigp_torch._utils import DTYPE


class MachineKindContract:
    """Base class of a kind's contract tests (module docstring). Class attributes:

    Attributes:
        kind_name: the kind's key in :data:`pigp_torch.machines.KINDS`.
        model_options: keyword arguments of ``KINDS[kind_name].model``.
        noise: a reading's noise standard deviation for the prior chain (goal units).
        n_settings: settings of the batched checks (default 3).
        gradient_rtol: relative tolerance of the finite-difference check (default 1e-4).
        prior_options: keyword arguments of the prior chain (default a small search: 2 starts,
            64 samples).
    """

    kind_name: ClassVar[str] = ""
    model_options: ClassVar[dict[str, Any]] = {}
    noise: ClassVar[float] = 0.0
    n_settings: ClassVar[int] = 3
    gradient_rtol: ClassVar[float] = 1e-4
    prior_options: ClassVar[dict[str, Any]] = {"n_starts": 2, "n_samples": 64}
    _models: ClassVar[dict] = {}

    # -- helpers --------------------------------------------------------------------------------
    def kind(self):
        from pigp_torch.machines import KINDS

        return KINDS[self.kind_name]

    def model(self):
        """The kind's model, built once per test class."""
        key = (type(self), self.kind_name)
        if key not in MachineKindContract._models:
            MachineKindContract._models[key] = self.kind().model(**self.model_options)
        return MachineKindContract._models[key]

    def settings(self, seed: int = 0) -> torch.Tensor:
        """``n_settings x d`` seeded settings in the middle half of the knob box."""
        b = self.model().bounds
        gen = torch.Generator().manual_seed(seed)
        u = 0.25 + 0.5 * torch.rand(self.n_settings, b.shape[1], generator=gen, dtype=DTYPE)
        return b[0] + (b[1] - b[0]) * u

    def unknowns(self, n: int, seed: int = 1) -> torch.Tensor:
        """``n x P`` unknowns drawn from their ranges."""
        return self.model().sample_unknowns(n, seed=seed)

    # -- the contract ---------------------------------------------------------------------------
    def test_the_kind_is_registered_with_its_parts(self):
        from pigp_torch.machines import MachineKind
        from pigp_torch.methods import METHODS
        from pigp_torch.prior.machine_model import MachineModel

        kind = self.kind()
        assert isinstance(kind, MachineKind) and kind.name == self.kind_name
        assert kind.default_method in METHODS, f"{kind.default_method!r} is not registered"
        if kind.run_file_kind is not None:
            section = kind.section()
            assert section.model_fields["kind"].annotation.__args__ == (kind.run_file_kind,)
        assert isinstance(self.model(), MachineModel)

    def test_knobs_observables_and_unknowns_have_names_units_and_ranges(self):
        m = self.model()
        d = m.dim
        assert m.bounds.shape == (2, d) and m.bounds.dtype == DTYPE
        assert bool((m.bounds[0] < m.bounds[1]).all())
        for names, units in (
            (m.knob_names, m.knob_units),
            (m.observable_names, m.observable_units),
            (m.unknown_names, m.unknown_units),
        ):
            assert len(names) == len(units) > 0
            assert all(isinstance(u, str) and u.strip() for u in units), units
        assert isinstance(m.goal_unit, str) and m.goal_unit.strip()
        assert bool((m.unknown_half_width > 0).all())

    def test_observe_is_batched(self):
        m = self.model()
        X, theta = self.settings(), m.unknown_center
        with torch.no_grad():
            O = m.observe(X, theta)
            assert O.shape == (len(X), len(m.observable_names)) and O.dtype == DTYPE
            assert bool(torch.isfinite(O).all())
            alone = torch.cat([m.observe(X[i : i + 1], theta) for i in range(len(X))])
            torch.testing.assert_close(O, alone, rtol=1e-10, atol=0.0)
            T = self.unknowns(len(X))
            rows = m.observe(X, T)
            each = torch.cat([m.observe(X[i : i + 1], T[i]) for i in range(len(X))])
            torch.testing.assert_close(rows, each, rtol=1e-10, atol=0.0)
            assert not torch.equal(rows, O), "the unknowns change nothing"

    def test_observe_is_differentiable_in_knobs_and_unknowns(self):
        m = self.model()
        x = self.settings()[:1].clone().requires_grad_(True)
        theta = m.unknown_center.clone().requires_grad_(True)
        g = m.goal(m.observe(x, theta)).sum()
        gx, gt = torch.autograd.grad(g, (x, theta))
        assert bool(torch.isfinite(gx).all()) and bool(torch.isfinite(gt).all())
        assert float(gx.abs().max()) > 0 and float(gt.abs().max()) > 0
        gen = torch.Generator().manual_seed(3)
        x0, t0 = x.detach(), theta.detach()

        def goal(xx: torch.Tensor, tt: torch.Tensor) -> float:
            with torch.no_grad():
                return float(m.goal(m.observe(xx, tt)).sum())

        h = 1e-5
        v = torch.randn(x0.shape, generator=gen, dtype=DTYPE) * (m.bounds[1] - m.bounds[0])
        w = torch.randn(t0.shape, generator=gen, dtype=DTYPE) * m.unknown_half_width
        for fd, exact in (
            ((goal(x0 + h * v, t0) - goal(x0 - h * v, t0)) / (2 * h), float((gx * v).sum())),
            ((goal(x0, t0 + h * w) - goal(x0, t0 - h * w)) / (2 * h), float((gt * w).sum())),
        ):
            assert abs(fd - exact) <= self.gradient_rtol * max(abs(exact), 1e-12), (fd, exact)

    def test_the_prior_chain_runs_on_the_model(self):
        from pigp_torch.prior.machine_model import prior_from_machine_model

        m = self.model()
        prior = prior_from_machine_model(m, noise=self.noise, **self.prior_options)
        assert prior.knob_names == list(m.knob_names)
        assert bool((prior.x0 >= m.bounds[0]).all()) and bool((prior.x0 <= m.bounds[1]).all())
        P = prior.precision
        torch.testing.assert_close(P, P.T)
        assert float(torch.linalg.eigvalsh(P).min()) > 0
        assert prior.f_x0 > prior.f_inf

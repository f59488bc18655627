"""``pigp build-prior``: the physics prior (precision matrix) of a trained surrogate."""

from __future__ import annotations

from pathlib import Path


def cmd_build_prior(args) -> int:
    import torch

    from pigp_torch.prior import prior_from_model
    from pigp_torch.simulation.ensemble import check_ensemble_size, with_center_ensemble
    from pigp_torch.surrogate import load_surrogate

    model, meta = load_surrogate(args.model)
    check_ensemble_size(args.center_ensemble, model.dim)  # before the optimum search
    bounds = model.bounds
    if args.knob_limit is not None:
        lim = torch.full((model.dim,), args.knob_limit, dtype=torch.float64)
        bounds = torch.stack([-lim, lim])
    data_meta = meta.get("data_metadata") or {}
    provenance = {
        "surrogate_file": str(args.model.name),
        "data_file": meta.get("data_file"),
        "model_error_seed": data_meta.get("error_seed"),
    }
    prior = prior_from_model(
        model,
        bounds,
        f_inf=float(model.f_inf),
        noise=args.noise,
        n_starts=args.starts,
        seed=args.seed,
        knob_names=meta.get("knob_names") or None,
        provenance=provenance,
    )
    if args.center_ensemble:
        prior = with_center_ensemble(prior, args.center_ensemble, data_meta, progress=True)
    prior.save(args.output)
    path = Path(args.output)
    lengths, _ = prior.length_scales(normalized=True)
    print(f"optimum of the surrogate: {prior.f_x0:.4f} mA/min (f_inf {prior.f_inf:.4f})")
    print(f"precision condition number: {prior.condition_number:.0f}")
    print("correlation lengths (normalized knobs, stiffest first): "
          + " ".join(f"{v:.3g}" for v in lengths.tolist()))  # fmt: skip
    print(f"saved prior to {path.resolve()}")
    return 0


def register(sub, bench) -> None:
    """Add ``pigp build-prior`` to the top-level sub-parsers ``sub``."""
    p = sub.add_parser(
        "build-prior",
        help="physics prior (precision matrix) from a trained surrogate",
        description="Find the surrogate's optimum, take the autograd Hessian H of "
        "log(f - f_inf) there and write the prior (precision -H/2, amplitude, noise) as JSON.",
    )
    p.add_argument("model", type=Path, help="surrogate file from `pigp train-surrogate`")
    p.add_argument("-o", "--output", type=Path, required=True, help="prior file to write (.json)")
    p.add_argument("--noise", type=float, default=0.04, help="objective noise σ (mA/min)")
    p.add_argument(
        "--knob-limit",
        type=float,
        default=None,
        help="search the optimum within ±this (knob units, e.g. A) instead of the surrogate's "
        "bounds",
    )
    p.add_argument("--starts", type=int, default=16, help="multi-start count (default 16)")
    p.add_argument("--seed", type=int, default=0, help="seed of the starts")
    p.add_argument(
        "--center-ensemble",
        type=int,
        default=0,
        metavar="N",
        help="also store the covariance of the optimum and the mean shape of the peak over N "
        "simulated rings with other error seeds (1001...; same knobs and optics as the "
        "surrogate's data; a few seconds per ring); pigp-physics uses them as its prior on "
        "the machine's "
        "optimum and as the shape of its physics form; N must exceed the number of knobs "
        "(at least 14 for the 13 SPEAR3 knobs; default 0: none)",
    )
    p.set_defaults(func=cmd_build_prior)

"""``pigp train-surrogate``: train the neural-network surrogate on a dataset."""

from __future__ import annotations

import argparse
from pathlib import Path


def train_default(name: str):
    """Default of a train_surrogate argument (the single source of the tuned values)."""
    from pigp_torch.surrogate.defaults import TRAIN_DEFAULTS

    return TRAIN_DEFAULTS[name]


def add_train_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``pigp train-surrogate`` (also used by surrogate_training/train.py)."""
    from pigp_torch.surrogate.defaults import ACTIVATION_NAMES, TARGETS

    d = train_default
    p.add_argument("data", type=Path, help="dataset NPZ written by `pigp generate-data`")
    p.add_argument("-o", "--output", type=Path, required=True, help="model file to write (.pt)")
    p.add_argument("--members", type=int, default=3, help="networks averaged (default 3)")
    p.add_argument("--widths", type=int, nargs="+", default=list(d("widths")))
    p.add_argument("--epochs", type=int, default=d("max_epochs"), help="maximum epochs")
    p.add_argument("--batch-size", type=int, default=d("batch_size"))
    p.add_argument("--lr", type=float, default=d("lr"), help="peak learning rate")
    p.add_argument("--patience", type=int, default=d("patience"))
    p.add_argument("--val-fraction", type=float, default=d("val_fraction"))
    p.add_argument("--seed", type=int, default=0, help="seed of the first member")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=d("num_threads"), help="CPU threads")
    p.add_argument("--activation", default=d("activation"), choices=list(ACTIVATION_NAMES))
    p.add_argument("--target", default=d("target"), choices=list(TARGETS))
    p.add_argument("--float64", action="store_true", help="train in float64 (default float32)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def format_training_report(report: dict) -> str:
    """Human-readable summary of one training report."""
    lines = [
        f"samples: {report['n_train']} train / {report['n_val']} held out",
        f"epochs: {report['epochs']} (best {report['best_epoch']}), "
        f"training time {report['train_time_s']:.1f} s on {report['device']} ({report['dtype']})",
        f"held-out relative RMSE of the loss rate: {100 * report['val_rel_rmse']:.3f} %",
        f"held-out R^2 of log(loss - f_inf):       {report['val_r2_log_excess']:.6f}",
        f"near optimum (top {report['near_opt_n']} held-out points, loss >= "
        f"{report['near_opt_min_loss_rate']:.3g}): relative RMSE "
        f"{100 * report['near_opt_rel_rmse']:.3f} %, max {100 * report['near_opt_rel_max']:.3f} %",
    ]
    if report["n_clamped"]:
        lines.append(
            f"note: {report['n_clamped']} samples had loss - f_inf < {report['excess_floor']:.3g} "
            "and were clamped before the logarithm"
        )
    return "\n".join(lines)


def cmd_train_surrogate(args) -> int:
    import torch

    from pigp_torch.data.dataset import Dataset
    from pigp_torch.surrogate import save_surrogate, train_ensemble

    data = Dataset.load(args.data)
    model, reports = train_ensemble(
        data,
        n_members=args.members,
        seed=args.seed,
        widths=tuple(args.widths),
        activation=args.activation,
        target=args.target,
        val_fraction=args.val_fraction,
        batch_size=args.batch_size,
        lr=args.lr,
        max_epochs=args.epochs,
        patience=args.patience,
        device=args.device,
        dtype=torch.float64 if args.float64 else torch.float32,
        num_threads=args.threads,
        progress=not args.quiet,
    )
    if len(reports) == 1:
        model = model.members[0]
    metadata = {
        "knob_names": data.knob_names,
        "bounds": data.bounds.tolist(),
        "f_inf": data.f_inf,
        "data_file": args.data.name,
        "data_metadata": data.metadata,
        # one report, or one per ensemble member
        "metrics": reports[0] if len(reports) == 1 else {"members": reports},
    }
    path = save_surrogate(model, args.output, metadata)
    for k, report in enumerate(reports):
        if len(reports) > 1:
            print(f"--- member {k + 1}/{len(reports)} (seed {report['seed']})")
        print(format_training_report(report))
    print(f"saved surrogate to {path}")
    return 0


def register(sub, bench) -> None:
    """Add ``pigp train-surrogate`` to the top-level sub-parsers ``sub``."""
    p = sub.add_parser(
        "train-surrogate",
        help="train the neural-network surrogate on a dataset",
        description="Train an ensemble of smooth MLPs on a dataset NPZ (validation split, early "
        "stopping), save it without pickles, and report held-out errors.",
    )
    add_train_arguments(p)
    p.set_defaults(func=cmd_train_surrogate)

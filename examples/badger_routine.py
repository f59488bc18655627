"""A headless Badger routine: ``pigp_physics`` on the ``pigp_sim`` environment (the simulated ring
of ``pigp serve-sim`` over Channel Access), through Badger's own loop, knobs set back at the end.

    pigp badger-setup                      # once: Badger's config, pigp_sim, pigp_physics
    pigp serve-sim --port 5064 &           # the simulated ring on 127.0.0.1
    python examples/badger_routine.py --ca-port 5064

The prior is ``builtin:spear3`` (default), the prior of the 13 windings that ships with the
package, or a ``PhysicsPrior`` JSON file with the same 13 knobs, e.g. the one ``pigp demo``
writes (``--prior runs/demo/prior.json``) or ``pigp build-prior``'s. The routine starts
from the knobs it finds, runs ``--evaluations`` readings (the start included), then sets the
knobs back to where they were (``--end-knobs best``: to the best reading's). Ctrl-C stops it
early, the knobs set back the same way.
"""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--prior",
        default="builtin:spear3",
        help="PhysicsPrior JSON file (13 knobs) or builtin:spear3, the shipped one (default)",
    )
    parser.add_argument("--ca-port", type=int, default=5064, help="IOC port on 127.0.0.1")
    parser.add_argument("--evaluations", type=int, default=20, help="readings, start included")
    parser.add_argument(
        "--max-travel", type=float, default=0.05, help="step limit, fraction of each range"
    )
    parser.add_argument("--end-knobs", choices=["initial", "best"], default="initial")
    args = parser.parse_args(argv)

    from badger.routine import Routine  # Badger reads its config file here

    from pigp_torch.data import BUILTIN_PREFIX, builtin_prior
    from pigp_torch.integrations.badger import register_generator, run_routine
    from pigp_torch.integrations.xopt import vocs_from_prior
    from pigp_torch.prior import PhysicsPrior

    register_generator()  # done by `pigp badger-setup`'s start-up hook already; harmless
    shipped = args.prior.startswith(BUILTIN_PREFIX)
    prior = PhysicsPrior.load(builtin_prior(args.prior) if shipped else args.prior)
    routine = Routine(
        name="pigp-physics on the simulated ring",
        vocs=vocs_from_prior(prior, objective="loss_rate"),
        generator={
            "name": "pigp_physics",
            "prior": prior.to_dict(),
            "max_travel_distances": args.max_travel,
        },
        environment={"name": "pigp_sim", "ca_port": args.ca_port, "end_knobs": args.end_knobs},
    )
    try:  # starts where the machine is (no initial_points given)
        data = run_routine(routine, max_evaluations=args.evaluations, verbose=2)
    except KeyboardInterrupt:
        data = routine.data
        print("stopped by Ctrl-C", file=sys.stderr)
    best = data.loc[data["loss_rate"].idxmax()]
    start = routine.initial_points.iloc[0].to_dict()
    end = routine.environment.get_variables(routine.vocs.variable_names)
    print(f"{len(data)} readings; best loss rate {best['loss_rate']:.4f} mA/min")
    print(
        "knobs (A)   start -> end: "
        + ", ".join(f"{k} {start[k]:.4f} -> {end[k]:.4f}" for k in start)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

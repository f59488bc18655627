"""Glue to other optimization frameworks (optional extras): pigp priors inside Xopt
(:mod:`~pigp_torch.integrations.xopt`), ``pigp-physics`` as an Xopt generator
(:mod:`~pigp_torch.integrations.xopt_physics`) and the Badger plugin's helpers
(:mod:`~pigp_torch.integrations.badger`). Importing this package imports none of them."""
